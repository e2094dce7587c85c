//! Short naps instead of a wake-up per item on the live input path.
//!
//! A thread that blocks on an empty queue (or socket) is woken by the producer for every item
//! that arrives: a futex wake and two context switches each, which at 100,000 digitizer frames a
//! second cost more CPU than decoding the frames (measured: ~26,000 switches/s on the frame
//! receiver and ~16,000 on the live source, 0.4 of a core between them, docs/performance.md).
//! A consumer that finds its input empty naps for [`NAP`] instead while items keep coming, so
//! that they gather and are taken in a batch, and nobody has to be woken; after [`MAX_NAPS`]
//! empty naps in a row (the input has gone quiet) it goes back to blocking, so an idle daemon
//! costs nothing. A nap adds at most [`NAP`] (plus the timer's slack) to a frame's latency.

use std::time::Duration;

/// One nap, µs: short against the 50 ms end-to-end latency budget, long against the 10 µs
/// between frames at 100 kHz.
pub const NAP: Duration = Duration::from_micros(500);

/// Empty naps in a row before the consumer blocks again (40 × 0.5 ms = 20 ms of quiet).
pub const MAX_NAPS: u32 = 40;

/// Counts the empty naps of one consumer (see the module documentation).
#[derive(Debug, Default, Clone)]
pub struct Napper {
    empty: u32,
}

impl Napper {
    /// A consumer that has just seen its input active.
    pub fn new() -> Self {
        Self::default()
    }

    /// The input had something: the next empty look naps again.
    pub fn active(&mut self) {
        self.empty = 0;
    }

    /// The input was empty: naps [`NAP`] and returns true while the input has been quiet for
    /// fewer than [`MAX_NAPS`] naps; returns false (without sleeping) when the caller should
    /// block instead.
    pub fn nap(&mut self) -> bool {
        if self.empty >= MAX_NAPS {
            return false;
        }
        self.empty += 1;
        std::thread::sleep(NAP);
        true
    }

    /// Whether the input has been quiet long enough that the consumer blocks.
    pub fn quiet(&self) -> bool {
        self.empty >= MAX_NAPS
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn naps_until_quiet_then_lets_the_caller_block() {
        let mut n = Napper::new();
        let t = std::time::Instant::now();
        let mut naps = 0;
        while n.nap() {
            naps += 1;
        }
        assert_eq!(naps, MAX_NAPS);
        assert!(n.quiet());
        assert!(t.elapsed() >= NAP * MAX_NAPS);
        // Once quiet, the caller blocks.
        assert!(!n.nap());
        // Activity starts the count again.
        n.active();
        assert!(!n.quiet());
        assert!(n.nap());
    }
}
