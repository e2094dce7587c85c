//! Run configuration for `fwlidar replay` (`config/replay.toml`) and the on-board daemon
//! (`config/onboard.toml`): the pipeline, its edges, outputs and recording policy.

use serde::{Deserialize, Serialize};

use crate::pipeline::registry::StageConfig;

/// What to do when an edge (bounded queue) is full.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum FullPolicy {
    /// Wait for room (replay: nothing is lost, the source slows down).
    #[default]
    Block,
    /// Drop the newest item and count it (live input: never stall the receiver).
    DropNewest,
}

/// The top level of a run configuration file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Sensor profile file, relative to this file's folder; used when the input does not carry
    /// its own sensor description (live input). Optional for replay (the capture header has it).
    #[serde(default)]
    pub sensor_profile: Option<String>,
    /// The per-pulse pipeline.
    #[serde(default)]
    pub pipeline: PipelineConfig,
    /// Outputs.
    #[serde(default)]
    pub output: OutputConfig,
}

/// The per-pulse pipeline: workers, edges and stages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipelineConfig {
    /// Worker threads running the per-pulse stages; 0 = one per core left after the source and
    /// sink threads (at least 1). Default 0.
    #[serde(default)]
    pub workers: usize,
    /// Capacity of every edge, pulses. Default 1024.
    #[serde(default = "default_queue_capacity")]
    pub queue_capacity: usize,
    /// Policy of the edge from the source into the workers. Default `block`.
    #[serde(default)]
    pub input_edge: FullPolicy,
    /// The stages, in order. Default: one `denoise` stage with its defaults.
    #[serde(default = "default_stages")]
    pub stages: Vec<StageConfig>,
}

fn default_queue_capacity() -> usize {
    1024
}

fn default_stages() -> Vec<StageConfig> {
    vec![StageConfig::Denoise(Default::default())]
}

impl Default for PipelineConfig {
    fn default() -> Self {
        PipelineConfig {
            workers: 0,
            queue_capacity: default_queue_capacity(),
            input_edge: FullPolicy::Block,
            stages: default_stages(),
        }
    }
}

/// Outputs of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// Output folder (the command line's `--out` takes precedence). Default `out`.
    #[serde(default = "default_out_dir")]
    pub dir: String,
    /// Write the processed waveforms (`waveforms.csv` + `pulses.csv`). Default true.
    #[serde(default = "yes")]
    pub waveforms: bool,
}

fn default_out_dir() -> String {
    "out".to_string()
}
fn yes() -> bool {
    true
}

impl Default for OutputConfig {
    fn default() -> Self {
        OutputConfig {
            dir: default_out_dir(),
            waveforms: true,
        }
    }
}
