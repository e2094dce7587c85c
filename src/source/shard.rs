//! One shard of an input (`fwlidar replay --shard i/n`): the `i`-th of `n` contiguous ranges of
//! its pulses, for a flight line too long for one node. Every navigation record still passes
//! (the georeferencing above needs the whole trajectory around the shard's pulses); the pulses
//! outside the range go back to the pool unprocessed. Every per-pulse stage depends on its own
//! pulse only and voxel accumulators are integers, so the stores of a line's `n` shards merge
//! into the very bytes of the whole line's store (`tests/campaign.rs`).

use crate::source::DynSource;
use crate::source::report::{ShardReport, SourceReport};
use std::path::Path;

use crate::core::facts::SourceFacts;
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;

/// Which shard: the `index`-th (1-based) of `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Shard {
    /// 1..=count.
    pub index: u32,
    /// Shards of the input, ≥ 1.
    pub count: u32,
}

impl std::str::FromStr for Shard {
    type Err = String;
    /// `i/n` with 1 ≤ i ≤ n, e.g. `2/4`.
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("{s:?} is not a shard i/n with 1 <= i <= n (e.g. 2/4)");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let index: u32 = i.trim().parse().map_err(|_| bad())?;
        let count: u32 = n.trim().parse().map_err(|_| bad())?;
        if index == 0 || count == 0 || index > count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl Shard {
    /// The shard's pulses among `total`: `[lo, hi)` by pulse number (0-based, in input
    /// order); the `n` shards tile `0..total` without gap or overlap.
    pub fn range(&self, total: u64) -> (u64, u64) {
        let at = |k: u64| (u128::from(total) * u128::from(k) / u128::from(self.count)) as u64;
        (at(u64::from(self.index) - 1), at(u64::from(self.index)))
    }
}

/// An input with only the pulses numbered `lo..hi` passed on.
pub struct ShardSource {
    inner: Box<DynSource>,
    lo: u64,
    hi: u64,
    /// Pulses read from the input so far.
    seen: u64,
}

impl ShardSource {
    /// Passes the pulses numbered `lo..hi` of `inner` (and all its navigation).
    pub fn new(inner: Box<DynSource>, lo: u64, hi: u64) -> Self {
        ShardSource {
            inner,
            lo,
            hi,
            seen: 0,
        }
    }
}

impl Source for ShardSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        loop {
            match self.inner.next(pool)? {
                SourceEvent::Pulse(p) => {
                    let k = self.seen;
                    self.seen += 1;
                    if (self.lo..self.hi).contains(&k) {
                        return Ok(SourceEvent::Pulse(p));
                    }
                    pool.give(p);
                }
                e => return Ok(e),
            }
        }
    }

    fn progress(&self) -> Option<(u64, u64)> {
        self.inner.progress()
    }

    fn report(&self) -> SourceReport {
        let mut r = self.inner.report();
        r.shard = Some(ShardReport {
            first_pulse: self.lo,
            end_pulse: self.hi,
            pulses_read: self.seen,
        });
        r
    }

    fn facts(&self) -> SourceFacts {
        self.inner.facts()
    }

    fn held_pulses(&self) -> usize {
        self.inner.held_pulses()
    }
}

/// Pulses in the input file `path` (read through once; navigation and damage are skipped as
/// the replay skips them). The error names the file.
pub fn count_pulses(path: &Path) -> Result<u64, String> {
    let mut s = crate::source::open_file(path)?;
    let pool = PulsePool::new(4);
    let mut n = 0u64;
    loop {
        match s
            .next(&pool)
            .map_err(|e| format!("{}: counting pulses: {e}", path.display()))?
        {
            SourceEvent::Pulse(p) => {
                n += 1;
                pool.give(p);
            }
            SourceEvent::End => return Ok(n),
            SourceEvent::Nav(_) | SourceEvent::Idle => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_and_tile_the_pulses() {
        assert_eq!("2/4".parse::<Shard>(), Ok(Shard { index: 2, count: 4 }));
        for bad in ["0/4", "5/4", "1/0", "x/2", "3", "", "1/2/3"] {
            let e = bad.parse::<Shard>().unwrap_err();
            assert!(e.contains("i/n"), "{bad}: {e}");
        }
        for total in [0u64, 1, 7, 10, 12_001, u64::MAX / 3] {
            for count in [1u32, 2, 3, 7] {
                let mut next = 0;
                for index in 1..=count {
                    let (lo, hi) = Shard { index, count }.range(total);
                    assert_eq!(lo, next, "{total} {index}/{count}");
                    assert!(hi >= lo && hi - lo <= total / u64::from(count) + 1);
                    next = hi;
                }
                assert_eq!(next, total);
            }
        }
    }
}
