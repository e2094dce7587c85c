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
    /// Pulses emitted with a note ([`Emitter::emit_noted`], [`Emitter::note`]), by note.
    pub notes: DropCounts,
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
    let mut notes = DropCounts::default();
    let mut n_in = 0u64;
    for (seq, mut p) in pulses.into_iter().enumerate() {
        p.seq = seq as u64;
        n_in += 1;
        let mut em =
            Emitter::new(&mut emitted, &pool, &mut dropped, &mut errors).with_notes(&mut notes);
        stage.process(Box::new(p), &mut em)?;
    }
    let mut em =
        Emitter::new(&mut emitted, &pool, &mut dropped, &mut errors).with_notes(&mut notes);
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
        notes,
    })
}

/// A source of `count` identical small pulses (one 64-sample outgoing and one 256-sample return
/// segment), for runtime tests and benchmarks. Pulse ids count from 0.
pub struct SyntheticSource {
    count: u64,
    produced: u64,
    with_samples: bool,
}

impl SyntheticSource {
    /// A source of `count` pulses.
    pub fn new(count: u64) -> Self {
        SyntheticSource {
            count,
            produced: 0,
            with_samples: true,
        }
    }

    /// The `count` pulses such a source produces, as owned pulses (for [`run_stage`]).
    pub fn pulses(count: u64) -> Vec<Pulse> {
        let pool = PulsePool::new(4);
        let mut source = SyntheticSource::new(count);
        let mut out = Vec::new();
        while let Ok(crate::pipeline::ports::SourceEvent::Pulse(p)) =
            crate::pipeline::ports::Source::next(&mut source, &pool)
        {
            out.push(*p);
        }
        out
    }

    /// A source of `count` pulses without segments: measures the runtime alone.
    pub fn empty(count: u64) -> Self {
        SyntheticSource {
            with_samples: false,
            ..Self::new(count)
        }
    }
}

impl crate::pipeline::ports::Source for SyntheticSource {
    type Report = ();

    fn name(&self) -> &'static str {
        "synthetic"
    }

    fn next(
        &mut self,
        pool: &PulsePool,
    ) -> Result<crate::pipeline::ports::SourceEvent, crate::pipeline::ports::SourceError> {
        use crate::pulse::SegmentKind;
        if self.produced == self.count {
            return Ok(crate::pipeline::ports::SourceEvent::End);
        }
        let mut p = pool.take();
        p.pulse_id = self.produced;
        p.gps_time = self.produced as f64 * 1e-5;
        if self.with_samples {
            p.push_segment(SegmentKind::Outgoing, 0, -32.0, (0..64u16).map(|i| i % 50));
            p.push_segment(
                SegmentKind::Return,
                0,
                6600.0,
                (0..256u16).map(|i| 10 + i % 7),
            );
        }
        self.produced += 1;
        Ok(crate::pipeline::ports::SourceEvent::Pulse(p))
    }

    fn progress(&self) -> Option<(u64, u64)> {
        Some((self.produced, self.count))
    }
}

/// A sink that remembers the pulse ids it was given, in order.
#[derive(Default)]
pub struct IdSink {
    /// Shared list of ids written.
    pub ids: std::sync::Arc<std::sync::Mutex<Vec<u64>>>,
    /// Set when `flush` was called.
    pub flushed: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl crate::pipeline::ports::PulseSink for IdSink {
    type Report = ();

    fn name(&self) -> &'static str {
        "ids"
    }
    fn write(&mut self, pulse: &Pulse) -> Result<(), crate::pipeline::ports::SinkError> {
        self.ids
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(pulse.pulse_id);
        Ok(())
    }
    fn flush(&mut self) -> Result<(), crate::pipeline::ports::SinkError> {
        self.flushed
            .store(true, std::sync::atomic::Ordering::SeqCst);
        Ok(())
    }
}
