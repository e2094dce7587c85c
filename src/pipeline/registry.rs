//! The closed registry of stage kinds: `[[pipeline.stages]]` entries are a tagged enum, built
//! into boxed [`Stage`]s once per worker.

use serde::{Deserialize, Serialize};

use crate::pipeline::stage::{Passthrough, Stage};
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
        }
    }

    /// Builds a fresh stage instance (one per worker thread).
    pub fn build(&self) -> Box<dyn Stage> {
        match self {
            StageConfig::Passthrough => Box::new(Passthrough),
            StageConfig::Denoise(c) => Box::new(Denoise::new(c.clone())),
            StageConfig::Deconvolve(c) => Box::new(Deconvolve::new(c.clone())),
            StageConfig::Decompose(c) => Box::new(Decompose::new(c.clone())),
        }
    }
}
