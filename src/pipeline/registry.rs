//! The closed registry of stage kinds: `[[pipeline.stages]]` entries are a tagged enum, built
//! into boxed [`Stage`]s once per worker.

use serde::{Deserialize, Serialize};

use crate::pipeline::stage::{Passthrough, Stage};
use crate::signal::denoise::{Denoise, DenoiseConfig};

/// One entry of `[[pipeline.stages]]`, selected by its `type` key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum StageConfig {
    /// Emits every pulse unchanged (runtime overhead measurement).
    Passthrough,
    /// FFT low-pass noise reduction.
    Denoise(DenoiseConfig),
}

impl StageConfig {
    /// The kind name, as written in `type = "..."`.
    pub fn kind(&self) -> &'static str {
        match self {
            StageConfig::Passthrough => "passthrough",
            StageConfig::Denoise(_) => "denoise",
        }
    }

    /// Builds a fresh stage instance (one per worker thread).
    pub fn build(&self) -> Box<dyn Stage> {
        match self {
            StageConfig::Passthrough => Box::new(Passthrough),
            StageConfig::Denoise(c) => Box::new(Denoise::new(c.clone())),
        }
    }
}
