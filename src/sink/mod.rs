//! Sinks: where processed pulses go, in arrival order (processed waveforms, fitted returns as CSV
//! and as LAS 1.4 with waveforms; voxel tiles as a later issue lands).

pub mod atomic_file;
pub mod hyper_points;
pub mod las_wave;
pub mod metrics_rasters;
pub mod nav_decode;
pub mod nav_tally;
pub mod pulse_metrics_csv;
pub mod returns_csv;
pub mod voxel_tiles;
pub mod waveform_csv;
pub mod waveform_npy;

use crate::pulse::Pulse;

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
    /// The voxel tile store failed (it names the file).
    #[error("voxel tiles: {0}")]
    Voxels(#[from] crate::voxel::zarr::StoreError),
    /// The data cannot be represented in the LAS file being written.
    #[error("cannot write {path}: {source}")]
    Las {
        /// The file being written.
        path: String,
        /// What cannot be represented.
        source: crate::format::las_write::LasWriteError,
    },
}

/// A consumer of processed pulses, run on the sink thread after order is restored.
pub trait PulseSink: Send {
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

    /// What the sink wrote and skipped, for `summary.json` (`sinks.NAME`); `null` when it has
    /// nothing to say. Default `null`.
    fn report(&self) -> serde_json::Value {
        serde_json::Value::Null
    }
}

/// Discards pulses (benchmarks, dry runs).
#[derive(Debug, Default)]
pub struct NullSink;

impl PulseSink for NullSink {
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

/// Several sinks fed the same pulses in turn.
pub struct FanOut(pub Vec<Box<dyn PulseSink>>);

impl PulseSink for FanOut {
    fn name(&self) -> &'static str {
        "fan_out"
    }
    fn write(&mut self, pulse: &Pulse) -> Result<(), SinkError> {
        self.0.iter_mut().try_for_each(|s| s.write(pulse))
    }
    fn flush(&mut self) -> Result<(), SinkError> {
        self.0.iter_mut().try_for_each(|s| s.flush())
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        self.0.iter_mut().try_for_each(|s| s.finish())
    }
    /// The reports of the sinks that have one, by name.
    fn report(&self) -> serde_json::Value {
        let mut m = serde_json::Map::new();
        for s in &self.0 {
            let r = s.report();
            if !r.is_null() {
                m.insert(s.name().to_string(), r);
            }
        }
        serde_json::Value::Object(m)
    }
}
