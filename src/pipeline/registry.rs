//! The closed registry of stage kinds: `[[pipeline.stages]]` entries are a tagged enum, built
//! into boxed [`Stage`]s once per worker.

use serde::{Deserialize, Serialize};

use crate::pipeline::stage::{Passthrough, Stage};
use crate::signal::calibrate::{Calibrate, CalibrateConfig};
use crate::signal::decompose::{Decompose, DecomposeConfig};
use crate::signal::deconvolve::{Deconvolve, DeconvolveConfig};
use crate::signal::denoise::{Denoise, DenoiseConfig};

/// One entry of `[[pipeline.stages]]`, selected by its `type` key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum StageConfig {
    /// Emits every pulse unchanged (runtime overhead measurement).
    // serde ignores extra keys of a unit variant of an internally tagged enum, even with
    // `deny_unknown_fields`; `no_keys` rejects them.
    #[serde(deserialize_with = "no_keys")]
    Passthrough,
    /// FFT low-pass noise reduction.
    Denoise(DenoiseConfig),
    /// Deconvolution of the return segments (Richardson-Lucy, Gold, Wiener, NNLS).
    Deconvolve(DeconvolveConfig),
    /// Gaussian decomposition of the return segments into discrete returns.
    Decompose(DecomposeConfig),
    /// Radiometric calibration: volts, range, outgoing energy, system constant.
    Calibrate(CalibrateConfig),
    /// Forest structure metrics per pulse (`src/forest/stage.rs`).
    Metrics(crate::forest::pulse_metrics::MetricsConfig),
}

/// Accepts only an empty table: the keys of a stage kind that has none.
fn no_keys<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<(), D::Error> {
    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    struct NoKeys {}
    NoKeys::deserialize(deserializer).map(|_| ())
}

impl StageConfig {
    /// The kind name, as written in `type = "..."`.
    pub fn kind(&self) -> &'static str {
        match self {
            StageConfig::Passthrough => "passthrough",
            StageConfig::Denoise(_) => "denoise",
            StageConfig::Deconvolve(_) => "deconvolve",
            StageConfig::Decompose(_) => "decompose",
            StageConfig::Calibrate(_) => "calibrate",
            StageConfig::Metrics(_) => "metrics",
        }
    }

    /// Builds a fresh stage instance (one per worker thread).
    pub fn build(&self) -> Box<dyn Stage> {
        match self {
            StageConfig::Passthrough => Box::new(Passthrough),
            StageConfig::Denoise(c) => Box::new(Denoise::new(c.clone())),
            StageConfig::Deconvolve(c) => Box::new(Deconvolve::new(c.clone())),
            StageConfig::Decompose(c) => Box::new(Decompose::new(c.clone())),
            StageConfig::Calibrate(c) => Box::new(Calibrate::new(c.clone())),
            StageConfig::Metrics(c) => Box::new(crate::forest::stage::Metrics::new(c.clone())),
        }
    }

    /// Fills the keys a stage leaves to the input (the `calibrate` stage's system constant
    /// and time origin, [`CalibrateConfig::resolve_from_input`]) from what the opened input
    /// states. Run once, before the stages are built.
    pub fn resolve_from_input(&mut self, facts: &crate::core::facts::SourceFacts) {
        if let StageConfig::Calibrate(c) = self {
            c.resolve_from_input(facts);
        }
    }

    /// Hands the run's DEM (`[georeference] dem`) to a `metrics` stage with `ground = "dem"`.
    /// Run once, before the stages are built.
    pub fn attach_dem(&mut self, dem: Option<&std::sync::Arc<crate::geo::dem::Dem>>) {
        if let StageConfig::Metrics(c) = self
            && c.ground == crate::forest::pulse_metrics::GroundFrom::Dem
        {
            c.dem = dem.cloned().map(crate::forest::pulse_metrics::RunDem);
        }
    }
}
