//! A run put together: what `fwlidar replay` and the on-board daemon (`fwlidar run`) share
//! between parsing their command line and printing their summary.
//!
//! ```text
//!  cli/replay.rs, cli/daemon.rs:  parse → run::assemble → pipeline::run → run::summary
//! ```
//!
//! - [`input`]: the input opened (files in sequence, a shard of them, or the daemon's live
//!   source), wrapped in the georeferencing, with the DEM;
//! - [`assemble`]: the stage chain prepared for that input ([`crate::stages::Chain`]), the
//!   pipeline's shape, the outputs and the navigation consumer, ready to run;
//! - [`outputs`]: the sinks replay and the daemon write, and the voxel store's identity;
//! - [`warnings`]: what in a finished run's report means an output is empty or thinned, with
//!   the setting to change;
//! - [`summary`]: `summary.json` and the one-screen summary.

pub mod assemble;
pub mod input;
pub mod learn;
pub mod outputs;
pub mod summary;
pub mod warnings;

use crate::nav::consumer::NavReport;
use crate::sink::SinkReports;
use crate::source::report::SourceReport;

/// The report of a run this module puts together (`summary.json`, less the warnings).
pub type RunReport = crate::pipeline::RunReport<SourceReport, SinkReports, NavReport>;

/// The controls of such a run.
pub type RunControl = crate::pipeline::RunControl<SourceReport, SinkReports, NavReport>;

/// What such a run publishes live (the daemon's QC).
pub type LivePublish = crate::pipeline::LivePublish<SourceReport, SinkReports, NavReport>;

/// A run that cannot be put together or finished.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The configuration or the command line asks for what cannot be (exit code 2).
    #[error("{0}")]
    Usage(String),
    /// An input or an output cannot be used (exit code 1).
    #[error("{0}")]
    Job(String),
}

impl RunError {
    /// A configuration or command-line problem.
    pub fn usage(message: impl std::fmt::Display) -> Self {
        RunError::Usage(message.to_string())
    }

    /// An input or output problem.
    pub fn job(message: impl std::fmt::Display) -> Self {
        RunError::Job(message.to_string())
    }
}
