//! Putting a run together: the stage chain prepared for the input, the pipeline's shape, the
//! outputs and the navigation consumer — the one function replay and the daemon share.

use super::RunError;
use super::input::Input;
use crate::config::RunConfig;
use crate::nav::consumer::{NavDecode, NavReport};
use crate::pipeline::ports::{NavConsumer, PulseSink};
use crate::pipeline::runner::PipelineSpec;
use crate::sink::{DynSink, FanOut, SinkReports};
use crate::source::DynSource;
use crate::stages::{Chain, RunContext};

/// A run ready to start: hand its parts to [`crate::pipeline::run`].
pub struct Assembled {
    /// The stage chain, prepared for the input (what the outputs and the reports ask about).
    pub chain: Chain,
    /// Workers, edges and each worker's stages.
    pub spec: PipelineSpec,
    /// The input.
    pub source: Box<DynSource>,
    /// Every output, fed the same pulses in turn.
    pub sinks: Box<dyn PulseSink<Report = SinkReports>>,
    /// The navigation consumer (the navigation bytes decoded for the summary).
    pub nav: Box<dyn NavConsumer<Report = NavReport>>,
}

/// How many worker threads: an explicit count, or 0 for the run's automatic choice.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Workers {
    /// Replay: `0` is one per core.
    Replay(usize),
    /// On board: `0` is one per core too (see [`crate::pipeline::runner::resolve_workers`]).
    Live(usize),
}

/// Puts a run together from its opened `input`: prepares the configured stages for it (the
/// input's facts, the DEM, whether the outputs write returns; a stage that cannot be built is a
/// configuration error), shapes the
/// pipeline, and builds the outputs with `outputs` (replay's or the daemon's,
/// [`super::outputs`]).
pub fn assemble(
    input: Input,
    config: &RunConfig,
    learned: Option<std::sync::Arc<crate::signal::learned_response::ResponseFile>>,
    workers: Workers,
    outputs: impl FnOnce(&Chain, &Input) -> Result<Vec<Box<DynSink>>, RunError>,
) -> Result<Assembled, RunError> {
    let facts = input.source.facts();
    let writes_returns = match workers {
        Workers::Replay(_) => super::outputs::replay_writes_returns(config),
        Workers::Live(_) => super::outputs::daemon_writes_returns(config),
    };
    let ctx = RunContext {
        facts: &facts,
        dem: input.dem.as_ref(),
        writes_returns,
        learned_response: learned.as_ref(),
    };
    let chain = Chain::prepare(&config.pipeline.stages, &ctx).map_err(RunError::usage)?;
    let p = &config.pipeline;
    let workers = match workers {
        // 0 is resolved by the pipeline: one per core (live too, since the UDP input's large
        // receive buffer keeps every frame when the chain takes every core).
        Workers::Replay(n) | Workers::Live(n) => n,
    };
    let spec = chain.spec(workers, p.queue_capacity, p.input_edge);
    let sinks = outputs(&chain, &input)?;
    Ok(Assembled {
        chain,
        spec,
        source: input.source,
        sinks: Box::new(FanOut(sinks)),
        nav: Box::new(nav_consumer(config)),
    })
}

/// The navigation consumer of a run: decodes the navigation bytes for the summary.
pub fn nav_consumer(config: &RunConfig) -> NavDecode {
    NavDecode::new(
        config.georeference.leap_seconds,
        config.navigation.earliest_days(),
    )
}
