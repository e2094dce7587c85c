//! The stage contract: take a pulse, emit zero or more, flush at the end.
//!
//! A stage owns its scratch buffers (allocated once, when it is built) and does a bounded amount
//! of work per pulse. It never panics on a pulse's content: a pulse it cannot use is dropped with
//! a counted reason ([`Emitter::drop_pulse`]) or counted as an error ([`Emitter::reject`]); only a
//! condition that makes every further pulse meaningless is a fatal [`StageError`].

use crate::pulse::{Pulse, PulsePool, Verdict};

/// A fatal stage failure: the pipeline stops and reports it.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// The stage cannot continue.
    #[error("stage `{stage}` failed: {message}")]
    Fatal {
        /// Name of the stage.
        stage: &'static str,
        /// What went wrong.
        message: String,
    },
}

/// Counts of pulses a stage dropped, by reason (a reason is a short static code, e.g.
/// `"empty_segment"`). Allocates only when a reason is first seen.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DropCounts {
    counts: Vec<(&'static str, u64)>,
}

impl DropCounts {
    /// Adds `n` to the count of `reason`.
    pub fn add(&mut self, reason: &'static str, n: u64) {
        match self.counts.iter_mut().find(|(r, _)| *r == reason) {
            Some((_, c)) => *c += n,
            None => self.counts.push((reason, n)),
        }
    }

    /// Count for one reason.
    pub fn get(&self, reason: &str) -> u64 {
        self.counts
            .iter()
            .find(|(r, _)| *r == reason)
            .map_or(0, |(_, c)| *c)
    }

    /// Total over all reasons.
    pub fn total(&self) -> u64 {
        self.counts.iter().map(|(_, c)| c).sum()
    }

    /// `(reason, count)` pairs in order of first occurrence.
    pub fn iter(&self) -> impl Iterator<Item = (&'static str, u64)> + '_ {
        self.counts.iter().copied()
    }

    /// Adds every count of `other` to this.
    pub fn merge(&mut self, other: &DropCounts) {
        for (r, c) in other.iter() {
            self.add(r, c);
        }
    }
}

/// Where a stage puts what it emits, drops or rejects.
pub struct Emitter<'a> {
    out: &'a mut Vec<Box<Pulse>>,
    pool: &'a PulsePool,
    dropped: &'a mut DropCounts,
    errors: &'a mut u64,
    notes: Option<&'a mut DropCounts>,
}

impl<'a> Emitter<'a> {
    /// An emitter writing into `out`, recycling dropped pulses into `pool`.
    pub fn new(
        out: &'a mut Vec<Box<Pulse>>,
        pool: &'a PulsePool,
        dropped: &'a mut DropCounts,
        errors: &'a mut u64,
    ) -> Self {
        Emitter {
            out,
            pool,
            dropped,
            errors,
            notes: None,
        }
    }

    /// Also counts the notes of [`Emitter::emit_noted`] into `notes`.
    pub fn with_notes(mut self, notes: &'a mut DropCounts) -> Self {
        self.notes = Some(notes);
        self
    }

    /// Passes a pulse on that the stage left (partly) unprocessed on purpose, counted under
    /// `note` (e.g. a deconvolution stage passing a pulse without an outgoing segment through
    /// when configured to): the pulse is not lost, and the run report says how many were
    /// passed and why.
    pub fn emit_noted(&mut self, pulse: Box<Pulse>, note: &'static str) {
        if let Some(n) = self.notes.as_deref_mut() {
            n.add(note, 1);
        }
        self.out.push(pulse);
    }

    /// Counts `note` for a pulse the stage will still emit (with [`Emitter::emit`]): for a
    /// pulse left partly unprocessed for more than one reason, each counted once.
    pub fn note(&mut self, note: &'static str) {
        if let Some(n) = self.notes.as_deref_mut() {
            n.add(note, 1);
        }
    }

    /// Hands a pulse on as a method's [`Verdict`] says: passed on (its notes counted),
    /// dropped or rejected under the reason.
    pub fn give(&mut self, pulse: Box<Pulse>, verdict: Verdict) {
        match verdict {
            Verdict::Keep(notes) => {
                for note in notes.into_iter().flatten() {
                    self.note(note);
                }
                self.emit(pulse);
            }
            Verdict::Drop(reason) => self.drop_pulse(pulse, reason),
            Verdict::Reject(reason) => self.reject(pulse, reason),
        }
    }

    /// Passes a pulse on to the next stage.
    pub fn emit(&mut self, pulse: Box<Pulse>) {
        self.out.push(pulse);
    }

    /// Drops a pulse on purpose (e.g. it has no return segment), counted under `reason`.
    pub fn drop_pulse(&mut self, pulse: Box<Pulse>, reason: &'static str) {
        self.dropped.add(reason, 1);
        self.pool.give(pulse);
    }

    /// Drops a pulse because processing it failed (bad content), counted as an error and under
    /// `reason`.
    pub fn reject(&mut self, pulse: Box<Pulse>, reason: &'static str) {
        *self.errors += 1;
        self.drop_pulse(pulse, reason);
    }
}

/// One processing step of the per-pulse chain.
///
/// Contract:
/// - `process` receives each pulse exactly once and must, before returning or at a later
///   `process`/`flush`, hand it to exactly one of [`Emitter::emit`], [`Emitter::drop_pulse`] or
///   [`Emitter::reject`];
/// - work per pulse is bounded for a given configuration and does not allocate after the first
///   pulses (buffers are sized once and reused);
/// - `flush` is called once at the end of the stream and emits anything still held;
/// - an `Err` is fatal: the pipeline stops.
pub trait Stage: Send {
    /// The stage's kind name as it appears in configuration and telemetry (e.g. `"denoise"`).
    fn name(&self) -> &'static str;

    /// Processes one pulse.
    fn process(&mut self, pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError>;

    /// Emits anything still held at the end of the stream.
    fn flush(&mut self, _out: &mut Emitter<'_>) -> Result<(), StageError> {
        Ok(())
    }
}
