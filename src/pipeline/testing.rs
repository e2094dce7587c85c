//! Running one stage alone on given pulses, for unit tests (the "mocker").

use crate::pipeline::stage::{DropCounts, Emitter, Stage, StageError};
use crate::pulse::{Pulse, PulsePool};

/// What a stage did with the pulses it was given.
#[derive(Debug)]
pub struct StageRun {
    /// Pulses emitted, in emission order (including those emitted at flush).
    pub emitted: Vec<Box<Pulse>>,
    /// Pulses dropped, by reason.
    pub dropped: DropCounts,
    /// Pulses rejected as errors.
    pub errors: u64,
}

/// Feeds `pulses` to `stage` one by one, then flushes it, and checks the stage contract:
/// every pulse given is emitted, dropped or rejected exactly once (for 1:1 and filtering stages).
pub fn run_stage(
    stage: &mut dyn Stage,
    pulses: impl IntoIterator<Item = Pulse>,
) -> Result<StageRun, StageError> {
    let pool = PulsePool::new(16);
    let mut emitted = Vec::new();
    let mut dropped = DropCounts::default();
    let mut errors = 0u64;
    let mut n_in = 0u64;
    for (seq, mut p) in pulses.into_iter().enumerate() {
        p.seq = seq as u64;
        n_in += 1;
        let mut em = Emitter::new(&mut emitted, &pool, &mut dropped, &mut errors);
        stage.process(Box::new(p), &mut em)?;
    }
    let mut em = Emitter::new(&mut emitted, &pool, &mut dropped, &mut errors);
    stage.flush(&mut em)?;
    assert_eq!(
        emitted.len() as u64 + dropped.total(),
        n_in,
        "stage `{}` broke the contract: {} in, {} emitted, {} dropped",
        stage.name(),
        n_in,
        emitted.len(),
        dropped.total()
    );
    Ok(StageRun {
        emitted,
        dropped,
        errors,
    })
}
