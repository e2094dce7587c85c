//! Configuration: what the user wrote (TOML, `deny_unknown_fields`, documented defaults), loaded
//! with every error reported by the field's path, then validated into runtime objects.
//!
//! Entry points: [`load_file`] for a file of a known kind, [`validate_any`] for any file of
//! `config/` (the kind decided by its top-level tables). Errors are [`ConfigErrors`]: the file
//! and every [`ConfigIssue`] found, printed one per line as `FILE:LINE:COL: field.path: reason`.

pub mod error;
pub mod load;
pub mod run;
pub mod sensor;
mod stages;

pub use error::{ConfigErrors, ConfigIssue, IssueKind, Location};
pub use load::{Validate, Validated, Validator, load_file, load_str, validate_any};
pub use run::{FullPolicy, OutputConfig, PipelineConfig, RunConfig};
pub use sensor::{SensorFile, SensorProfile};
