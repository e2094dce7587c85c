//! The streaming runtime: the stage contract, bounded edges, the runner and telemetry.

pub mod edge;
pub mod ports;
pub mod runner;
pub mod stage;
pub mod telemetry;
pub mod testing;

pub use ports::{NavChunk, NavConsumer, PulseSink, SinkError, Source, SourceError, SourceEvent};
pub use runner::{LivePublish, PipelineSpec, RunControl, RunReport, run};
pub use stage::{DropCounts, Emitter, Stage, StageError};
