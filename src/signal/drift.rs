//! The baseline and noise of a record from the record itself, assuming no noise model: a
//! **drifting baseline** (a straight line, not a level) and the **saturated samples** (runs
//! clipped at the digitizer's top), for `fwlidar process` ahead of deconvolution (issue 37,
//! docs/accuracy.md "Deconvolution over noise models", third step).
//!
//! # Baseline line
//!
//! Echoes only add to the baseline, so the baseline is the lower part of the record. The noise
//! σ is taken from the first differences (`1.4826 × MAD(Δy) / √2`), which the echoes barely
//! touch when they are wider than a few samples and which a pedestal or a slow drift does not
//! change at all; then a straight line is fitted by least squares to the samples within
//! [`CLIP_SIGMAS`] σ above the current line (all samples at first), and the fit repeats on the
//! samples it keeps until they no longer change (at most [`MAX_ROUNDS`] rounds). With fewer
//! than [`MIN_KEPT`] samples kept (a record that is nearly all echo), the last line with at
//! least that many stands. A constant pedestal gives a flat line at its level, a linear drift
//! the drift; neither needs a pre-trigger window.
//!
//! # Saturated samples
//!
//! A run of [`MIN_SATURATED_RUN`] or more consecutive samples equal to the record's maximum is
//! read as clipped: their true value is unknown (only known to be at least the maximum), so a
//! fit must leave them out rather than match the flat top. On a record of *counts* (whole
//! numbers, as digitizers deliver them) two equal samples at the top are what quantisation
//! makes of an echo whose peak falls between two bins, so there the run must be
//! [`MIN_SATURATED_RUN_QUANTISED`] long: on the NEON Harvard
//! Forest records (integer counts, none at the converter's top) 99 of 500 have two equal
//! samples at their maximum, 2 have three or four.
//!
//! Units: the record's own (volts, counts, any signal unit); positions in samples. No
//! allocation once the buffers have held the longest record.

use crate::signal::denoise::median_in_place;

/// Samples more than this many σ above the line are echo, not baseline.
pub const CLIP_SIGMAS: f32 = 2.0;
/// Most rounds of the clipped line fit.
pub const MAX_ROUNDS: usize = 8;
/// Fewest samples a line is fitted to.
pub const MIN_KEPT: usize = 8;
/// Shortest run of samples at the record's maximum read as clipped.
pub const MIN_SATURATED_RUN: usize = 2;
/// Shortest run at the maximum read as clipped on a record of counts ([`is_counts`]).
pub const MIN_SATURATED_RUN_QUANTISED: usize = 3;

/// A straight baseline: `offset + slope × i` at sample `i` (units of the record; slope per
/// sample).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BaselineLine {
    /// Baseline at sample 0, the record's unit.
    pub offset: f64,
    /// Change of the baseline per sample, the record's unit per sample.
    pub slope: f64,
    /// Noise standard deviation from the first differences, the record's unit.
    pub sigma: f64,
}

impl BaselineLine {
    /// The baseline at sample `i`.
    #[inline]
    pub fn at(&self, i: usize) -> f64 {
        self.offset + self.slope * i as f64
    }
}

/// Work buffers of the baseline line fit.
#[derive(Debug, Default)]
pub struct DriftBaseline {
    /// First differences, then their absolute deviations.
    diffs: Vec<f32>,
    /// Samples kept in the current round.
    kept: Vec<bool>,
}

impl DriftBaseline {
    /// Buffers for records of up to `samples` samples (they grow if needed).
    pub fn with_capacity(samples: usize) -> Self {
        DriftBaseline {
            diffs: Vec::with_capacity(samples),
            kept: Vec::with_capacity(samples),
        }
    }

    /// The noise σ of `y` from its first differences (`1.4826 × MAD(Δy) / √2`, the record's
    /// unit); 0 for fewer than 3 samples.
    pub fn difference_sigma(&mut self, y: &[f32]) -> f64 {
        if y.len() < 3 {
            return 0.0;
        }
        self.diffs.clear();
        self.diffs.extend(y.windows(2).map(|w| w[1] - w[0]));
        let med = median_in_place(&mut self.diffs);
        for d in self.diffs.iter_mut() {
            *d = (*d - med).abs();
        }
        let mad = median_in_place(&mut self.diffs) as f64;
        1.4826 * mad / std::f64::consts::SQRT_2
    }

    /// The baseline line of `y` (module documentation); samples flagged in `excluded` (when
    /// given, as long as `y`) take no part. A record shorter than [`MIN_KEPT`] samples gets a
    /// flat line at its mean (0 when empty).
    pub fn fit(&mut self, y: &[f32], excluded: Option<&[bool]>) -> BaselineLine {
        let n = y.len();
        let sigma = self.difference_sigma(y);
        self.kept.clear();
        self.kept
            .extend((0..n).map(|i| excluded.is_none_or(|e| !e.get(i).copied().unwrap_or(false))));
        let Some(mut line) = line_through(y, &self.kept) else {
            let mean = if n == 0 {
                0.0
            } else {
                y.iter().map(|&v| v as f64).sum::<f64>() / n as f64
            };
            return BaselineLine {
                offset: mean,
                slope: 0.0,
                sigma,
            };
        };
        let limit = CLIP_SIGMAS as f64 * sigma;
        for _ in 0..MAX_ROUNDS {
            let mut changed = false;
            let mut count = 0;
            for (i, k) in self.kept.iter_mut().enumerate() {
                let keep = excluded.is_none_or(|e| !e.get(i).copied().unwrap_or(false))
                    && (y[i] as f64 - (line.0 + line.1 * i as f64)) < limit;
                changed |= keep != *k;
                count += keep as usize;
                *k = keep;
            }
            if !changed || count < MIN_KEPT {
                break;
            }
            match line_through(y, &self.kept) {
                Some(l) => line = l,
                None => break,
            }
        }
        BaselineLine {
            offset: line.0,
            slope: line.1,
            sigma,
        }
    }
}

/// Least-squares line `(offset, slope per sample)` through the kept samples of `y`; `None` with
/// fewer than [`MIN_KEPT`] of them.
fn line_through(y: &[f32], kept: &[bool]) -> Option<(f64, f64)> {
    let (mut n, mut sx, mut sy, mut sxx, mut sxy) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    for (i, (&v, &k)) in y.iter().zip(kept).enumerate() {
        if k {
            let x = i as f64;
            let v = v as f64;
            n += 1.0;
            sx += x;
            sy += v;
            sxx += x * x;
            sxy += x * v;
        }
    }
    if n < MIN_KEPT as f64 {
        return None;
    }
    let det = n * sxx - sx * sx;
    if det <= 0.0 {
        return Some((sy / n, 0.0));
    }
    let slope = (n * sxy - sx * sy) / det;
    Some(((sy - slope * sx) / n, slope))
}

/// True when every sample of `y` is a whole number (digitizer counts) and there is at least
/// one: the records whose ties at the top quantisation explains.
pub fn is_counts(y: &[f32]) -> bool {
    !y.is_empty() && y.iter().all(|v| v.is_finite() && v.fract() == 0.0)
}

/// Flags in `excluded` (resized to `y.len()`) the samples of `y` in runs of at least
/// [`MIN_SATURATED_RUN`] consecutive samples equal to the record's maximum
/// ([`MIN_SATURATED_RUN_QUANTISED`] on a record of counts, [`is_counts`]); returns how many.
pub fn flag_saturated(y: &[f32], excluded: &mut Vec<bool>) -> usize {
    excluded.clear();
    excluded.resize(y.len(), false);
    let min_run = if is_counts(y) {
        MIN_SATURATED_RUN_QUANTISED
    } else {
        MIN_SATURATED_RUN
    };
    let top = y.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut flagged = 0;
    let mut i = 0;
    while i < y.len() {
        if y[i] == top {
            let start = i;
            while i < y.len() && y[i] == top {
                i += 1;
            }
            if i - start >= min_run {
                excluded[start..i].fill(true);
                flagged += i - start;
            }
        } else {
            i += 1;
        }
    }
    flagged
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A record of `n` samples: `base(i)` plus Gaussian echoes `(centre, amplitude, σ)` plus
    /// uniform noise of half-width `noise`.
    fn record(
        n: usize,
        base: impl Fn(f64) -> f64,
        echoes: &[(f64, f64, f64)],
        noise: f32,
    ) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        (0..n)
            .map(|i| {
                let x = i as f64;
                let e: f64 = echoes
                    .iter()
                    .map(|&(c, a, s)| a * (-0.5 * ((x - c) / s).powi(2)).exp())
                    .sum();
                (base(x) + e) as f32 + rng.random_range(-noise..=noise)
            })
            .collect()
    }

    #[test]
    fn a_drift_under_echoes_is_found() {
        let echoes = [
            (60.0, 0.4, 3.4),
            (64.0, 0.3, 3.4),
            (130.0, 0.3, 3.4),
            (220.0, 1.0, 3.4),
        ];
        let y = record(256, |x| 0.05 + 0.1 * x / 255.0, &echoes, 0.01);
        let mut d = DriftBaseline::with_capacity(256);
        let line = d.fit(&y, None);
        assert!((line.offset - 0.05).abs() < 0.01, "{line:?}");
        assert!((line.slope * 255.0 - 0.1).abs() < 0.01, "{line:?}");
        // Uniform ±0.01 has σ = 0.0058; the echoes' flanks (a quarter of the samples here)
        // widen the differences' MAD somewhat.
        assert!(line.sigma > 0.004 && line.sigma < 0.012, "{line:?}");
    }

    #[test]
    fn a_pedestal_gives_a_flat_line_and_a_constant_record_zero_noise() {
        let y = record(256, |_| 0.1, &[(100.0, 1.0, 3.0), (180.0, 0.5, 3.0)], 0.03);
        let line = DriftBaseline::default().fit(&y, None);
        assert!(
            (line.offset - 0.1).abs() < 0.01 && (line.slope * 255.0).abs() < 0.01,
            "{line:?}"
        );
        let flat = DriftBaseline::default().fit(&[2.0; 40], None);
        assert_eq!((flat.offset, flat.slope, flat.sigma), (2.0, 0.0, 0.0));
    }

    #[test]
    fn short_empty_and_excluded_records_do_not_panic() {
        let mut d = DriftBaseline::default();
        assert_eq!(d.fit(&[], None), BaselineLine::default());
        let l = d.fit(&[1.0, 3.0], None);
        assert_eq!((l.offset, l.slope), (2.0, 0.0));
        // Every sample excluded: the mean, flat.
        let y = [1.0f32; 20];
        let l = d.fit(&y, Some(&[true; 20]));
        assert_eq!((l.offset, l.slope), (1.0, 0.0));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(128))]
        #[test]
        fn never_panics_and_gives_a_finite_line(
            y in proptest::collection::vec(-1e6f32..1e6, 0..300),
            every in 1usize..8,
        ) {
            let mut d = DriftBaseline::default();
            let excluded: Vec<bool> = (0..y.len()).map(|i| i % every == 0).collect();
            for ex in [None, Some(&excluded[..])] {
                let l = d.fit(&y, ex);
                proptest::prop_assert!(l.offset.is_finite() && l.slope.is_finite());
                proptest::prop_assert!(l.sigma.is_finite() && l.sigma >= 0.0);
            }
            let mut flags = Vec::new();
            let n = flag_saturated(&y, &mut flags);
            proptest::prop_assert!(flags.len() == y.len() && n == flags.iter().filter(|&&f| f).count());
        }
    }

    #[test]
    fn saturated_runs_are_flagged_and_single_maxima_are_not() {
        let mut ex = Vec::new();
        assert_eq!(flag_saturated(&[0.0, 1.0, 0.5, 0.2], &mut ex), 0);
        assert_eq!(ex, vec![false; 4]);
        assert_eq!(
            // Not whole numbers: runs of two count.
            flag_saturated(&[0.0, 0.7, 0.7, 0.7, 0.3, 0.7, 0.7, 0.1], &mut ex),
            5
        );
        assert_eq!(ex, [false, true, true, true, false, true, true, false]);
        assert_eq!(flag_saturated(&[], &mut ex), 0);
    }

    #[test]
    fn on_counts_two_equal_samples_at_the_top_are_not_clipping() {
        let mut ex = Vec::new();
        // Integer counts: a peak between two bins; then a clipped run of three.
        let counts = [210.0f32, 260.0, 388.0, 388.0, 300.0, 220.0];
        assert!(is_counts(&counts));
        assert_eq!(flag_saturated(&counts, &mut ex), 0);
        let clipped = [210.0f32, 300.0, 1023.0, 1023.0, 1023.0, 400.0, 215.0];
        assert_eq!(flag_saturated(&clipped, &mut ex), 3);
        assert!(!is_counts(&[0.5, 1.0]) && !is_counts(&[]) && !is_counts(&[f32::NAN]));
    }
}
