//! Configuration: what the user wrote (TOML, `deny_unknown_fields`, documented defaults), loaded
//! with every error reported by the field's path, then validated into runtime objects.
//!
//! Entry points: [`load_file`] / [`load_str`] for a file of a known kind;
//! [`read_top_level_keys`] for a caller that decides the kind by what a file holds (`fwlidar
//! validate` does, in `cli/validate.rs`, which knows the simulator's scene kinds: this module
//! does not depend on them). `load` and `error` are a leaf: generic loading and validation
//! helpers that name no configuration kind. Errors are [`ConfigErrors`]: the file
//! and every [`ConfigIssue`] found, printed one per line as `FILE:LINE:COL: field.path: reason`.

pub mod error;
pub mod load;
pub mod overrides;
pub mod run;
pub mod sensor;
mod stages;

pub use error::{ConfigErrors, ConfigIssue, IssueKind, Location};
pub use load::{
    Validate, Validator, load_file, load_file_with, load_str, load_str_with, read_top_level_keys,
};
pub use run::{FullPolicy, OutputConfig, PipelineConfig, RunConfig, WaveformFormat};
pub use sensor::{SensorFile, SensorProfile};

/// The default run configuration for `fwlidar replay`, embedded in the binary
/// (`config/replay.toml`).
pub const DEFAULT_REPLAY_CONFIG: &str = include_str!("../../config/replay.toml");

/// Loads the run configuration at `path`, or the embedded default when `None`.
pub fn load_run_config(path: Option<&std::path::Path>) -> Result<RunConfig, ConfigErrors> {
    load_run_config_with(path, &[] as &[&str])
}

/// As [`load_run_config`], with `--set KEY=VALUE` overrides ([`overrides`]) applied before the
/// configuration is checked: a misspelt key or a bad value is refused like one in the file.
pub fn load_run_config_with(
    path: Option<&std::path::Path>,
    sets: &[impl AsRef<str>],
) -> Result<RunConfig, ConfigErrors> {
    match path {
        Some(p) => load_file_with(p, sets),
        None => load_str_with(DEFAULT_REPLAY_CONFIG, "config/replay.toml (embedded)", sets),
    }
}
