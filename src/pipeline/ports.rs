//! The runtime's ports: what it reads pulses and navigation bytes from ([`Source`]), what it
//! writes processed pulses to ([`PulseSink`]) and what it hands navigation bytes to
//! ([`NavConsumer`]). The runtime defines them and never names an implementation; sources,
//! sinks and navigation consumers live above it (`source/`, `sink/`, `nav/`) and
//! implement these traits.

use crate::core::facts::SourceFacts;
use crate::pulse::{Pulse, PulsePool};

/// What a port says about itself in `summary.json` (and, copied about four times a second, on
/// the daemon's QC page): a typed value, serialised when the summary is written. `()` says
/// nothing (`null`).
pub trait Report: serde::Serialize + Clone + Default + Send + 'static {}

impl<T: serde::Serialize + Clone + Default + Send + 'static> Report for T {}

/// Raw navigation bytes as they came off a port, kept intact so that replay runs the very same
/// parsers as live flight.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NavChunk {
    /// Port identifier (index of the serial port in the configuration).
    pub port: u8,
    /// Host receive time, nanoseconds since the Unix epoch.
    pub receive_time_ns: u64,
    /// The bytes.
    pub bytes: Vec<u8>,
}

/// What a source produced next.
pub enum SourceEvent {
    /// A pulse, taken from the pool and filled (its `seq` and `arrived` are set by the runner).
    Pulse(Box<Pulse>),
    /// Navigation bytes.
    Nav(NavChunk),
    /// Nothing came for a while (live sources only); ask again. Lets the source's thread look
    /// at its stop flag and publish its telemetry while the input is quiet.
    Idle,
    /// Nothing more will come.
    End,
}

/// Errors a source reports. Per-record damage (skipped bytes, bad checksums) is not an error: it
/// is counted in the source's report.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The input cannot be read any further.
    #[error("{0}")]
    Fatal(String),
}

/// A producer of pulses and navigation bytes, run on its own thread.
pub trait Source: Send {
    /// What the source reports (`summary.json` → `source`).
    type Report: Report;

    /// Short name for logs and reports (e.g. `"capture"`).
    fn name(&self) -> &'static str;

    /// Produces the next event, waiting if it must. Takes pulses from `pool`.
    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError>;

    /// Progress as (done, total) in the source's own unit (bytes for files), when known.
    fn progress(&self) -> Option<(u64, u64)> {
        None
    }

    /// The source's own report for `summary.json` (e.g. bytes skipped in a damaged capture).
    /// Default: the report type's default.
    fn report(&self) -> Self::Report {
        Self::Report::default()
    }

    /// What the input states about its sensor, time base and coordinates, as far as known so far
    /// (a capture source reads its first header when it is opened). `fwlidar import` writes it
    /// into the capture header.
    fn facts(&self) -> SourceFacts {
        SourceFacts::default()
    }

    /// At most how many pulses the source may hold at once between taking them from the pool
    /// and handing them out (e.g. pulses waiting for the navigation that brackets them). The
    /// runner sizes the pool's idle capacity with it, so that those pulses return to the pool
    /// instead of being freed and allocated again on every pulse. Default 0.
    fn held_pulses(&self) -> usize {
        0
    }
}

/// A consumer of navigation bytes, run on its own thread.
pub trait NavConsumer: Send {
    /// What it reports (`summary.json` → `nav`).
    type Report: Report;
    /// Takes one chunk of navigation bytes.
    fn consume(&mut self, chunk: NavChunk);
    /// Called once when no more chunks will come (the end of the input), before `report`.
    fn finish(&mut self) {}
    /// Its report for `summary.json`.
    fn report(&self) -> Self::Report;
}

/// Errors a sink reports; all are fatal to the run (an output we cannot write is not an output).
#[derive(Debug, thiserror::Error)]
pub enum SinkError {
    /// Writing failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file being written.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The output failed in a way of its own (a voxel store, a LAS file that cannot hold the
    /// data); the error names the file.
    #[error(transparent)]
    Output(Box<dyn std::error::Error + Send + Sync>),
}

impl SinkError {
    /// The error of writing `path`.
    pub fn io(path: &std::path::Path, source: std::io::Error) -> Self {
        SinkError::Io {
            path: path.display().to_string(),
            source,
        }
    }

    /// An output's own error (it names the file).
    pub fn output(e: impl std::error::Error + Send + Sync + 'static) -> Self {
        SinkError::Output(Box::new(e))
    }
}

impl From<crate::core::atomic_file::WriteError> for SinkError {
    fn from(e: crate::core::atomic_file::WriteError) -> Self {
        SinkError::Io {
            path: e.path,
            source: e.source,
        }
    }
}

/// A consumer of processed pulses, run on the sink thread after order is restored.
pub trait PulseSink: Send {
    /// What the sink reports (`summary.json` → `sinks`).
    type Report: Report;

    /// Short name for logs and reports.
    fn name(&self) -> &'static str;

    /// Writes one pulse.
    fn write(&mut self, pulse: &Pulse) -> Result<(), SinkError>;

    /// Flushes everything written so far to the operating system; called at the end of the run
    /// (also on SIGINT/SIGTERM) and may be called periodically.
    fn flush(&mut self) -> Result<(), SinkError>;

    /// Completes the outputs at the end of the run (also after SIGINT/SIGTERM): flushes and, for
    /// files written under a temporary name, moves them into place. Default: `flush`.
    fn finish(&mut self) -> Result<(), SinkError> {
        self.flush()
    }

    /// What the sink wrote and skipped, for `summary.json`. Default: the report type's
    /// default.
    fn report(&self) -> Self::Report {
        Self::Report::default()
    }
}

/// Discards pulses (benchmarks, dry runs).
#[derive(Debug, Default)]
pub struct NullSink;

impl PulseSink for NullSink {
    type Report = ();

    fn name(&self) -> &'static str {
        "null"
    }
    fn write(&mut self, _pulse: &Pulse) -> Result<(), SinkError> {
        Ok(())
    }
    fn flush(&mut self) -> Result<(), SinkError> {
        Ok(())
    }
}
