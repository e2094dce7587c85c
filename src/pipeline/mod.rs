//! The streaming runtime: the stage contract, bounded edges, the runner and telemetry.

pub mod registry;
pub mod stage;
pub mod testing;

pub use stage::{DropCounts, Emitter, Passthrough, Stage, StageError};
