//! The run configuration of `fwlidar replay` and `fwlidar run` (`config/replay.toml`,
//! `config/onboard.toml`): what the user wrote (TOML, `deny_unknown_fields`, documented
//! defaults), loaded by `core::toml_load` with every error reported by the field's path.
//!
//! Entry points: [`load_run_config`] / [`load_run_config_with`] (the embedded default when no
//! file is named). Errors are `core::config_error::ConfigErrors`: the file and every issue
//! found, printed one per line as `FILE:LINE:COL: field.path: reason`.

pub mod run;
#[cfg(test)]
mod tests;

pub use run::{OutputConfig, PipelineConfig, RunConfig, WaveformFormat};

use crate::core::config_error::ConfigErrors;
use crate::core::toml_load::{load_file_with, load_str_with};

/// The default run configuration for `fwlidar replay`, embedded in the binary
/// (`config/replay.toml`).
pub const DEFAULT_REPLAY_CONFIG: &str = include_str!("../../config/replay.toml");

/// Loads the run configuration at `path`, or the embedded default when `None`.
pub fn load_run_config(path: Option<&std::path::Path>) -> Result<RunConfig, ConfigErrors> {
    load_run_config_with(path, &[] as &[&str])
}

/// As [`load_run_config`], with `--set KEY=VALUE` overrides (`core::overrides`) applied before
/// the configuration is checked: a misspelt key or a bad value is refused like one in the file.
pub fn load_run_config_with(
    path: Option<&std::path::Path>,
    sets: &[impl AsRef<str>],
) -> Result<RunConfig, ConfigErrors> {
    match path {
        Some(p) => load_file_with(p, sets),
        None => load_str_with(DEFAULT_REPLAY_CONFIG, "config/replay.toml (embedded)", sets),
    }
}
