//! The robust noise level and σ of a waveform whose echoes may fill much of it (the metrics'
//! noise estimate, `forest/measure.rs` and `forest/table_metrics.rs`), from one sorted copy.
//!
//! The estimate is [`robust_level_and_sigma`]'s (the upper-clipped median and 1.4826 × the
//! median absolute deviation of the kept samples, in the unit of the samples), bit for bit:
//! that function selects anew in every clipping round, [`RobustNoise`] sorts once and reads
//! every round off the sorted copy:
//!
//! - the kept samples are always the samples at or below a limit, so a prefix of the sorted
//!   copy, and their median is read at its middle;
//! - the absolute deviations of a sorted prefix from its median fall from the prefix's start to
//!   the median and rise after it (`f32` subtraction and `abs` are monotonic), so the
//!   deviation of rank `kept / 2` is the element of that rank of two sorted runs, found by
//!   bisection without computing the other deviations.
//!
//! The order statistics are values, whatever the algorithm that finds them, and the sort uses
//! the same total order (`f32::total_cmp`, as integer keys); the median of an even count, the
//! deviations and the clipping limit are the same `f32` expressions. Samples that are not
//! finite or beyond ±10³⁰ (where a deviation could overflow) take [`robust_level_and_sigma`]
//! itself.

use crate::signal::denoise::{CLIP_ITERATIONS, CLIP_SIGMAS, MAD_TO_SIGMA, robust_level_and_sigma};

/// Largest sample magnitude sorted as keys (beyond, the selection of the reference).
const MAX_SORTED_MAGNITUDE: f32 = 1e30;

/// Widest range of counts (`max − min + 1`) sorted by counting.
const MAX_COUNT_RANGE: usize = 4096;

/// Work buffers of the robust noise estimate: no allocation once they have held the longest
/// waveform.
#[derive(Debug, Default)]
pub struct RobustNoise {
    /// The samples as keys in `f32::total_cmp` order, then sorted.
    keys: Vec<u32>,
    /// The sorted samples.
    sorted: Vec<f32>,
    /// Work buffers of the reference's selection (samples not finite).
    work: Vec<f32>,
    deviations: Vec<f32>,
    /// Histogram of the counts and the samples in signal units ([`RobustNoise::level_and_sigma_of_counts`]).
    histogram: Vec<u32>,
    values: Vec<f32>,
}

impl RobustNoise {
    /// Buffers for waveforms of up to `samples` samples (they grow if needed).
    pub fn with_capacity(samples: usize) -> Self {
        RobustNoise {
            keys: Vec::with_capacity(samples),
            sorted: Vec::with_capacity(samples),
            work: Vec::new(),
            deviations: Vec::new(),
            histogram: Vec::with_capacity(MAX_COUNT_RANGE),
            values: Vec::with_capacity(samples),
        }
    }

    /// Noise level and σ of `values` (in their unit): [`robust_level_and_sigma`]'s result;
    /// `(NaN, NaN)` when `values` is empty.
    pub fn level_and_sigma(&mut self, values: &[f32]) -> (f32, f32) {
        if values.is_empty() {
            return (f32::NAN, f32::NAN);
        }
        self.keys.clear();
        let mut plain = true;
        for &v in values {
            plain &= v.abs() <= MAX_SORTED_MAGNITUDE;
            self.keys.push(order_key(v));
        }
        if !plain {
            return robust_level_and_sigma(values, &mut self.work, &mut self.deviations);
        }
        self.keys.sort_unstable();
        self.sorted.clear();
        self.sorted
            .extend(self.keys.iter().map(|&k| from_order_key(k)));
        clipped_level_and_sigma(&self.sorted)
    }
}

impl RobustNoise {
    /// [`RobustNoise::level_and_sigma`] of the samples `to_volts(c)` of the digitizer counts
    /// `counts`, sorted by counting: the counts' histogram read in order, each count's value
    /// taken once. When the values so read are in order (any non-decreasing `to_volts`, as
    /// `offset + gain × counts` with a positive gain) they are the sorted samples; otherwise, or
    /// for counts spanning more than 4096 values, the samples are sorted as in
    /// [`RobustNoise::level_and_sigma`].
    pub fn level_and_sigma_of_counts(
        &mut self,
        counts: &[u16],
        to_volts: impl Fn(u16) -> f32,
    ) -> (f32, f32) {
        if counts.is_empty() {
            return (f32::NAN, f32::NAN);
        }
        // One pass of plain `min`/`max` (vectorised; the iterator's `min()` and `max()` were
        // two scalar passes).
        let (mut lo, mut hi) = (u16::MAX, u16::MIN);
        for &c in counts {
            lo = lo.min(c);
            hi = hi.max(c);
        }
        let range = usize::from(hi - lo) + 1;
        if range <= MAX_COUNT_RANGE {
            self.histogram.clear();
            self.histogram.resize(range, 0);
            for &c in counts {
                self.histogram[usize::from(c - lo)] += 1;
            }
            self.sorted.clear();
            let mut in_order = true;
            let mut previous = f32::NEG_INFINITY;
            for (i, &h) in self.histogram.iter().enumerate() {
                if h > 0 {
                    let v = to_volts(lo + i as u16);
                    in_order &= v.abs() <= MAX_SORTED_MAGNITUDE && previous.total_cmp(&v).is_le();
                    previous = v;
                    self.sorted.extend(std::iter::repeat_n(v, h as usize));
                }
            }
            if in_order {
                return clipped_level_and_sigma(&self.sorted);
            }
        }
        let mut values = std::mem::take(&mut self.values);
        values.clear();
        values.extend(counts.iter().map(|&c| to_volts(c)));
        let result = self.level_and_sigma(&values);
        self.values = values;
        result
    }
}

/// The upper-clipped median and σ of the finite samples `s`, sorted ascending (non-empty).
fn clipped_level_and_sigma(s: &[f32]) -> (f32, f32) {
    let mut kept = s.len();
    let mut level = median_sorted(&s[..kept]);
    let mut rounds = 0;
    loop {
        let mad = deviation_of_rank(&s[..kept], level, kept / 2);
        if rounds == CLIP_ITERATIONS {
            return (level, MAD_TO_SIGMA * mad);
        }
        rounds += 1;
        let limit = level + CLIP_SIGMAS * MAD_TO_SIGMA * mad;
        let new_kept = s[..kept].partition_point(|&v| v <= limit).max(1);
        if new_kept == kept {
            return (level, MAD_TO_SIGMA * mad);
        }
        kept = new_kept;
        level = median_sorted(&s[..kept]);
    }
}

/// Median of sorted samples (non-empty): the middle one, or for an even count half the sum
/// of the two middle ones (as [`robust_level_and_sigma`] writes it).
fn median_sorted(s: &[f32]) -> f32 {
    let (len, mid) = (s.len(), s.len() / 2);
    if len % 2 == 1 {
        s[mid]
    } else {
        0.5 * (s[mid - 1] + s[mid])
    }
}

/// The absolute deviation from `level` of rank `rank` (0: the smallest) of the sorted finite
/// samples `s` (`rank < s.len()`). The deviations of the samples below `level`, read from
/// `level` down, and of the others, read up, are two ascending runs; the answer is the larger
/// of the last elements taken from each when the `rank + 1` smallest are split between them,
/// and the split is found by bisection on how many come from the lower run.
fn deviation_of_rank(s: &[f32], level: f32, rank: usize) -> f32 {
    let p = s.partition_point(|&v| v < level);
    let (below, above) = (&s[..p], &s[p..]);
    // Deviation of the `i`-th (0-based) sample of each run, nearest `level` first.
    let low = |i: usize| (below[p - 1 - i] - level).abs();
    let high = |j: usize| (above[j] - level).abs();
    let take = rank + 1;
    // `i` from the lower run and `take − i` from the upper one: the smallest `i` such that
    // the lower run's next deviation is not below the upper run's last one taken.
    let mut lo = take.saturating_sub(above.len());
    let mut hi = take.min(below.len());
    while lo < hi {
        let i = lo + (hi - lo) / 2;
        let j = take - i;
        // Taking `i` is too few when the lower run's `i`-th is smaller than the upper run's
        // `(j − 1)`-th (the last one this split takes from it).
        if low(i) < high(j - 1) {
            lo = i + 1;
        } else {
            hi = i;
        }
    }
    let i = lo;
    let j = take - i;
    match (i, j) {
        (0, _) => high(j - 1),
        (_, 0) => low(i - 1),
        _ => low(i - 1).max(high(j - 1)),
    }
}

/// An `f32` as a `u32` whose unsigned order is `f32::total_cmp`'s.
fn order_key(v: f32) -> u32 {
    let b = v.to_bits();
    if b >> 31 == 1 { !b } else { b | 0x8000_0000 }
}

/// The `f32` of an [`order_key`].
fn from_order_key(k: u32) -> f32 {
    f32::from_bits(if k >> 31 == 1 { k & 0x7fff_ffff } else { !k })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The reference's result, bit for bit, on `values`.
    fn check(values: &[f32]) -> Result<(), TestCaseError> {
        let (mut work, mut dev) = (Vec::new(), Vec::new());
        let want = robust_level_and_sigma(values, &mut work, &mut dev);
        let got = RobustNoise::default().level_and_sigma(values);
        prop_assert_eq!(got.0.to_bits(), want.0.to_bits(), "level of {:?}", values);
        prop_assert_eq!(got.1.to_bits(), want.1.to_bits(), "σ of {:?}", values);
        Ok(())
    }

    /// Keys order as `f32::total_cmp` and map back.
    #[test]
    fn order_keys_follow_the_total_order() {
        let xs = [
            f32::NEG_INFINITY,
            -3.5,
            -1e-40,
            -0.0,
            0.0,
            1e-40,
            2.0,
            f32::INFINITY,
        ];
        for w in xs.windows(2) {
            assert!(order_key(w[0]) < order_key(w[1]), "{w:?}");
        }
        for x in xs {
            assert_eq!(from_order_key(order_key(x)).to_bits(), x.to_bits());
        }
    }

    /// Edge cases: one sample, ties, signed zeros, non-finite samples (the reference's path).
    #[test]
    fn small_and_odd_inputs_match_the_reference() {
        for v in [
            vec![1.0f32],
            vec![2.0, 1.0],
            vec![0.0, -0.0, 0.0, -0.0],
            vec![-0.0, 0.0, 5.0],
            vec![3.0; 17],
            vec![1.0, 1.0, 1.0, 9.0, 9.0, 9.0],
            vec![1.0, f32::NAN, 2.0],
            vec![1.0, f32::INFINITY, 2.0, 3.0],
            vec![1e31, -1e31, 0.5],
        ] {
            check(&v).unwrap();
        }
        assert!(RobustNoise::default().level_and_sigma(&[]).0.is_nan());
    }

    /// The samples of `counts` through `to_volts`, by counting and as `f32` samples.
    fn check_counts(counts: &[u16], to_volts: impl Fn(u16) -> f32) -> Result<(), TestCaseError> {
        let volts: Vec<f32> = counts.iter().map(|&c| to_volts(c)).collect();
        let (mut work, mut dev) = (Vec::new(), Vec::new());
        let want = robust_level_and_sigma(&volts, &mut work, &mut dev);
        let got = RobustNoise::default().level_and_sigma_of_counts(counts, to_volts);
        prop_assert_eq!(got.0.to_bits(), want.0.to_bits(), "level of {:?}", counts);
        prop_assert_eq!(got.1.to_bits(), want.1.to_bits(), "σ of {:?}", counts);
        Ok(())
    }

    proptest! {
        /// Counts with echoes through `offset + gain × counts` of either sign of gain (a
        /// negative one is out of order: the sort's path), and a wide range.
        #[test]
        fn counts_by_counting_match_the_reference(
            counts in proptest::collection::vec(0u16..60, 1..400),
            echo_at in 0usize..400,
            echo_len in 0usize..300,
            echo_height in prop_oneof![0u16..500, Just(10_000u16)],
            gain in prop_oneof![Just(1.0f32), 0.001f32..0.1, -0.1f32..-0.001, Just(0.0f32)],
            offset in prop_oneof![-2.0f32..2.0, Just(0.0f32), Just(-0.0f32)],
        ) {
            let counts: Vec<u16> = counts
                .iter()
                .enumerate()
                .map(|(i, &c)| {
                    let echo = if i >= echo_at && i < echo_at + echo_len { echo_height } else { 0 };
                    c + echo
                })
                .collect();
            check_counts(&counts, |c| offset + gain * c as f32)?;
        }

        /// Noise on integer counts (ties everywhere) with an echo filling part of the window,
        /// converted to volts with a gain and an offset, as the metrics see raw waveforms.
        #[test]
        fn counts_with_echoes_match_the_reference(
            counts in proptest::collection::vec(0u16..40, 1..400),
            echo_at in 0usize..400,
            echo_len in 0usize..300,
            echo_height in 0u16..500,
            gain in prop_oneof![Just(1.0f32), 0.001f32..0.1, -0.1f32..-0.001],
            offset in -2.0f32..2.0,
        ) {
            let volts: Vec<f32> = counts
                .iter()
                .enumerate()
                .map(|(i, &c)| {
                    let echo = if i >= echo_at && i < echo_at + echo_len { echo_height } else { 0 };
                    offset + gain * f32::from(c + echo)
                })
                .collect();
            check(&volts)?;
        }

        /// Arbitrary finite samples of any spread and sign.
        #[test]
        fn finite_samples_match_the_reference(
            values in proptest::collection::vec(-1e6f32..1e6, 1..300),
        ) {
            check(&values)?;
        }

        /// Few distinct values (long ties across the median and the clipping limit).
        #[test]
        fn few_values_match_the_reference(
            picks in proptest::collection::vec(0usize..4, 1..200),
            values in proptest::array::uniform4(-10.0f32..10.0),
        ) {
            let v: Vec<f32> = picks.iter().map(|&i| values[i]).collect();
            check(&v)?;
        }
    }
}
