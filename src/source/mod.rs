//! Sources: where pulses and navigation bytes come from (a recorded capture now; the network,
//! serial ports, LAS and PulseWaves files as later issues land).

pub mod capture;

use crate::pulse::{Pulse, PulsePool};

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
    /// Short name for logs and reports (e.g. `"capture"`).
    fn name(&self) -> &'static str;

    /// Produces the next event, waiting if it must. Takes pulses from `pool`.
    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError>;

    /// Progress as (done, total) in the source's own unit (bytes for files), when known.
    fn progress(&self) -> Option<(u64, u64)> {
        None
    }

    /// The source's own report for `summary.json` (e.g. bytes skipped in a damaged capture).
    fn report(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}
