//! PLACEHOLDER being written in parallel; replaced before merge.
//! Gaussian decomposition: peaks, then a bounded Levenberg-Marquardt fit of a sum of Gaussians.

use serde::{Deserialize, Serialize};

use crate::pulse::FittedReturn;

/// Settings of the decomposition (`type = "decompose"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct DecomposeConfig {}

/// Why a segment could not be decomposed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecomposeError {
    /// NaN or infinite samples.
    #[error("non-finite input sample")]
    NonFiniteInput,
}

/// What one fit did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FitStats {
    /// Levenberg-Marquardt iterations.
    pub iterations: u32,
}

/// Fits Gaussians to one segment at a time, buffers sized once.
pub struct Decomposer {
    _config: DecomposeConfig,
}

impl Decomposer {
    /// Builds it for segments of up to `max_samples`.
    pub fn new(config: DecomposeConfig, _max_samples: usize) -> Self {
        Decomposer { _config: config }
    }

    /// Fits `y` (one segment, signal units, `noise_v` its noise level) and appends one
    /// [`FittedReturn`] per component to `out` (`segment`, `time_ns` left 0 for the caller to
    /// set; `position_bins` from the segment's first sample).
    pub fn fit(
        &mut self,
        _y: &[f32],
        _noise_v: f32,
        _out: &mut Vec<FittedReturn>,
    ) -> Result<FitStats, DecomposeError> {
        Ok(FitStats::default())
    }
}
