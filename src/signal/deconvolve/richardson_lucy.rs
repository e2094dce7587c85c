//! PLACEHOLDER being written in parallel; replaced before merge.

use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::{DeconvError, Deconvolver, MethodStats};
use crate::signal::kernel::Kernel;

/// Settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct RlConfig {}

/// The method.
pub struct RichardsonLucy {
    _config: RlConfig,
}

impl RichardsonLucy {
    /// Builds it.
    pub fn new(config: RlConfig, _max_samples: usize, _max_taps: usize) -> Self {
        RichardsonLucy { _config: config }
    }
}

impl Deconvolver for RichardsonLucy {
    fn name(&self) -> &'static str {
        "richardson_lucy"
    }
    fn run(
        &mut self,
        y: &[f32],
        _k: &Kernel,
        _noise_v: f32,
        _sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        out.copy_from_slice(y);
        Ok(MethodStats::default())
    }
    fn worst_case_flops(&self, _n: usize, _m: usize) -> u64 {
        0
    }
}
