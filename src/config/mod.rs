//! Configuration: what the user wrote (TOML, `deny_unknown_fields`, documented defaults), loaded
//! with every error reported by the field's path, then validated into runtime objects.

pub mod run;
pub mod sensor;

pub use run::{FullPolicy, OutputConfig, PipelineConfig, RunConfig};
pub use sensor::{SensorFile, SensorProfile};
