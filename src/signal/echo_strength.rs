//! How strongly the received data show an echo found in a deconvolved estimate: a detection
//! test in units of the data's noise, the same for every method.
//!
//! A deconvolution sharpens noise as well as echoes, so a fixed share of the output's maximum
//! (the seed's floor) keeps the noise spikes a long run sharpens and drops weak true echoes of
//! a record with one strong return. The data decide instead: the *echo* of a maximum of the
//! estimate `x` is its bump — the samples between its two *saddles* (on each side the lowest
//! sample before the nearest higher one, as in a summit's topographic prominence), above the
//! higher saddle — and what it adds to the
//! received waveform is that bump blurred by the system pulse, `k * b`. Its norm `‖k * b‖₂`
//! over the data's noise σ is the echo's signal-to-noise ratio as a matched filter sees it: a
//! noise spike of the estimate explains little of the data (a small bump), a true echo
//! explains its share. The highest maximum of a wide echo that a deconvolution splits into two
//! with a shallow dip keeps the whole echo's strength; the lower one is tested on its dip. The norm is exact, from the kernel's autocorrelation:
//! `‖k * b‖₂² = Σᵢ Σⱼ bᵢ bⱼ R(i − j)`, `R(l) = Σₜ kₜ kₜ₊ₗ` (`O(w · min(w, m))` for a bump of `w`
//! samples and `m` taps).
//!
//! [`EchoDetector`] is the detector built on it: the local maxima of the estimate whose echo
//! reaches a multiple of σ (`fwlidar process --peaks`, `--peak-snr`; `fwlidar tradeoff
//! --peak-snr` scores it). Measured on the tradeoff sweep (docs/accuracy.md, issue 37): at 5 σ
//! it drops most of the false peaks late Richardson-Lucy iterations sharpen out of noise (RL
//! 200 at 3 % noise: 1.32 → 0.39 per pulse for 83.7 → 80.4 % of the peaks; at 6 %: 3.46 →
//! 0.60, 81.1 → 75.6 %) and leaves NNLS's split extended echoes, which are strong, in place.
//! The saddles reach across lower maxima, so a long stretch of noise lends its highest wiggle
//! a wide bump: on a raw waveform at 6 % noise 7.3 false peaks per pulse stay at 5 σ.
//!
//! Units: `x` in the unit of the data (a unit-sum kernel keeps areas); the strength in the same
//! unit; σ is the caller's (for example [`crate::signal::denoise::robust_level_and_sigma`] on
//! the received samples).

use crate::signal::peaks::{Peak, PeakFinder, PeakRule, PeakSettings};

/// The echo-strength test of one system pulse: the pulse's autocorrelation, sized once.
#[derive(Clone, Debug, Default)]
pub struct EchoStrength {
    /// `R(l)` for lags `0..m`, unit² of the taps.
    autocorr: Vec<f32>,
}

impl EchoStrength {
    /// The test for a pulse of these taps (a delta, `[1.0]`, scores an estimate that is
    /// already as blurred as the data, e.g. the raw or low-passed waveform).
    pub fn new(taps: &[f32]) -> Self {
        let mut s = EchoStrength {
            autocorr: Vec::with_capacity(taps.len()),
        };
        s.set_kernel(taps);
        s
    }

    /// Replaces the pulse (no allocation when it has no more taps than the buffer holds).
    pub fn set_kernel(&mut self, taps: &[f32]) {
        self.autocorr.clear();
        let m = taps.len();
        self.autocorr.extend((0..m).map(|l| {
            taps[..m - l]
                .iter()
                .zip(&taps[l..])
                .map(|(&a, &b)| a as f64 * b as f64)
                .sum::<f64>() as f32
        }));
    }

    /// `‖k * b‖₂` of the echo of the maximum at `index` of `x`, in the unit of `x` (0 when
    /// `index` is out of range or the bump has no height).
    pub fn of(&self, x: &[f32], index: usize) -> f32 {
        let Some(&top) = x.get(index) else {
            return 0.0;
        };
        let (mut lo, mut hi) = saddles(x, index);
        let level = x[lo].max(x[hi]);
        if top.partial_cmp(&level) != Some(std::cmp::Ordering::Greater) {
            return 0.0;
        }
        // Trim the flat stretches at the level (zeros of a sparse estimate).
        while x[lo] <= level {
            lo += 1;
        }
        while x[hi] <= level {
            hi -= 1;
        }
        let b = |i: usize| (x[i] - level).max(0.0) as f64;
        let m = self.autocorr.len();
        if m == 0 {
            return 0.0;
        }
        let mut sum = 0.0;
        for i in lo..=hi {
            let bi = b(i);
            sum += bi * bi * self.autocorr[0] as f64;
            for j in (i + 1)..=hi.min(i + m - 1) {
                sum += 2.0 * bi * b(j) * self.autocorr[j - i] as f64;
            }
        }
        sum.max(0.0).sqrt() as f32
    }
}

/// The saddles of the maximum at `index` (in range): on each side, the lowest sample between
/// it and the nearest strictly higher sample (or the edge), the one nearest the maximum where
/// several are as low. Returns their positions (left, right).
pub fn saddles(x: &[f32], index: usize) -> (usize, usize) {
    let top = x[index];
    let mut lo = index;
    let mut i = index;
    while i > 0 && x[i - 1] <= top {
        i -= 1;
        if x[i] < x[lo] {
            lo = i;
        }
    }
    let mut hi = index;
    let mut i = index;
    while i + 1 < x.len() && x[i + 1] <= top {
        i += 1;
        if x[i] < x[hi] {
            hi = i;
        }
    }
    (lo, hi)
}

/// One echo the detector kept: the local maximum and how strongly the data show it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DetectedEcho {
    /// The maximum (index, position in bins, amplitude in the unit of the estimate).
    pub peak: Peak,
    /// [`EchoStrength::of`] over the data's noise σ (dimensionless).
    pub snr: f32,
}

/// The noise-aware peak detector: the local maxima of a deconvolved estimate (rise and fall,
/// a plateau at its middle) whose echo adds at least `min_snr` × σ to the received waveform.
/// Buffers sized at construction: detection does not allocate for estimates of up to
/// `max_samples` samples and pulses of up to `max_taps` taps.
pub struct EchoDetector {
    finder: PeakFinder,
    maxima: Vec<Peak>,
    strength: EchoStrength,
}

impl EchoDetector {
    /// A detector for estimates of up to `max_samples` samples, with a delta pulse until
    /// [`EchoDetector::set_pulse`].
    pub fn new(max_samples: usize, max_taps: usize) -> Self {
        let mut strength = EchoStrength {
            autocorr: Vec::with_capacity(max_taps.max(1)),
        };
        strength.set_kernel(&[1.0]);
        EchoDetector {
            finder: PeakFinder::new(max_samples),
            maxima: Vec::with_capacity(max_samples / 2 + 1),
            strength,
        }
    }

    /// The system pulse the estimate was deconvolved by (a delta, `[1.0]`, for an estimate
    /// as blurred as the data).
    pub fn set_pulse(&mut self, taps: &[f32]) {
        self.strength.set_kernel(taps);
    }

    /// The echoes of `x` the data show at `min_snr` × `sigma` or more, in order of position,
    /// into `out` (cleared first). `sigma`: the received waveform's noise σ, unit of `x`; not
    /// positive or not finite: every maximum is kept with an infinite ratio.
    pub fn detect(&mut self, x: &[f32], sigma: f32, min_snr: f32, out: &mut Vec<DetectedEcho>) {
        out.clear();
        let settings = PeakSettings {
            threshold: f32::MIN_POSITIVE,
            min_separation_bins: 1,
            max_peaks: x.len(),
            shoulders: false,
            shoulder_curvature: 0.0,
            min_prominence: 0.0,
            rule: PeakRule::RiseAndFall,
        };
        self.finder.find(x, &settings, &mut self.maxima);
        for &peak in &self.maxima {
            let strength = self.strength.of(x, peak.index);
            let snr = if sigma.is_finite() && sigma > 0.0 {
                strength / sigma
            } else {
                f32::INFINITY
            };
            if snr >= min_snr {
                out.push(DetectedEcho { peak, snr });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// `‖k * b‖₂` by the full convolution, f64.
    fn blurred_norm(b: &[f64], k: &[f32]) -> f64 {
        let mut out = vec![0.0; b.len() + k.len()];
        for (i, &bi) in b.iter().enumerate() {
            for (t, &kt) in k.iter().enumerate() {
                out[i + t] += bi * kt as f64;
            }
        }
        out.iter().map(|v| v * v).sum::<f64>().sqrt()
    }

    #[test]
    fn a_spike_scores_its_height_times_the_pulse_norm() {
        let k = [0.25f32, 0.5, 0.25];
        let s = EchoStrength::new(&k);
        let x = [0.0f32, 0.0, 2.0, 0.0, 0.0];
        let norm_k = (0.25f64 * 0.25 + 0.25 + 0.0625).sqrt();
        assert!((s.of(&x, 2) as f64 - 2.0 * norm_k).abs() < 1e-6);
        // A delta pulse scores the bump's own norm.
        assert!((EchoStrength::new(&[1.0]).of(&x, 2) - 2.0).abs() < 1e-6);
    }

    #[test]
    fn the_bump_stands_on_the_higher_saddle_and_includes_its_flanks() {
        // Maximum at 3; saddles at 1 (0.5, before the edge) and 6 (1.0, before 3.5 at 8): the
        // bump is [2, 3, 4, 5] above 1.0.
        let x = [1.0f32, 0.5, 1.5, 3.0, 2.0, 1.2, 1.0, 2.5, 3.5];
        let k = [0.2f32, 0.6, 0.2];
        let b = [0.5, 2.0, 1.0, 0.2];
        let want = blurred_norm(&b, &k);
        assert!((EchoStrength::new(&k).of(&x, 3) as f64 - want).abs() < 1e-5);
    }

    #[test]
    fn no_height_out_of_range_or_empty_pulse_scores_zero() {
        let s = EchoStrength::new(&[0.5, 0.5]);
        assert_eq!(s.of(&[1.0, 1.0, 1.0], 1), 0.0);
        assert_eq!(s.of(&[1.0, 2.0, 1.0], 7), 0.0);
        assert_eq!(EchoStrength::new(&[]).of(&[0.0, 1.0, 0.0], 1), 0.0);
    }

    proptest! {
        /// The autocorrelation sum equals the norm of the explicit convolution, and the score
        /// scales with the estimate.
        #[test]
        fn matches_the_explicit_convolution(
            x in proptest::collection::vec(0.0f32..10.0, 3..60),
            k in proptest::collection::vec(0.0f32..1.0, 1..20),
            pick in 0usize..60,
        ) {
            let i = pick % x.len();
            let s = EchoStrength::new(&k);
            let got = s.of(&x, i) as f64;
            // The saddles by brute force: the lowest sample before the first higher one.
            let top = x[i];
            let left = (0..i).rev().take_while(|&j| x[j] <= top).chain([i]);
            let lo = left.fold(i, |a, j| if x[j] < x[a] || (x[j] == x[a] && j > a) { j } else { a });
            let right = (i + 1..x.len()).take_while(|&j| x[j] <= top).chain([i]);
            let hi = right.fold(i, |a, j| if x[j] < x[a] || (x[j] == x[a] && j < a) { j } else { a });
            let level = x[lo].max(x[hi]);
            let b: Vec<f64> = x[lo..=hi].iter().map(|&v| (v - level).max(0.0) as f64).collect();
            let want = blurred_norm(&b, &k);
            prop_assert!((got - want).abs() <= 1e-4 * (1.0 + want), "{got} vs {want}");
            let doubled: Vec<f32> = x.iter().map(|v| 2.0 * v).collect();
            let g2 = s.of(&doubled, i) as f64;
            prop_assert!((g2 - 2.0 * got).abs() <= 1e-4 * (1.0 + g2));
        }
    }

    #[test]
    fn the_detector_keeps_echoes_and_drops_noise_spikes() {
        // Two echoes (spikes 1.0 and 0.3) and a small spike of 0.02 in a sparse estimate;
        // a 5-tap pulse; σ = 0.01.
        let k = [0.1f32, 0.2, 0.4, 0.2, 0.1];
        let mut x = vec![0.0f32; 60];
        x[10] = 1.0;
        x[30] = 0.3;
        x[31] = 0.1; // one echo between two bins: one maximum
        x[50] = 0.02;
        let mut d = EchoDetector::new(60, 5);
        d.set_pulse(&k);
        let mut out = Vec::new();
        d.detect(&x, 0.01, 3.0, &mut out);
        let at: Vec<usize> = out.iter().map(|e| e.peak.index).collect();
        assert_eq!(at, [10, 30]);
        let nk = k.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((out[0].snr - nk / 0.01).abs() < 1e-3);
        // The small spike adds 0.02 · ‖k‖ ≈ 1.0 σ: kept only at a lower ratio.
        d.detect(&x, 0.01, 0.5, &mut out);
        assert_eq!(out.len(), 3);
        d.detect(&x, 0.0, 1e9, &mut out);
        assert_eq!(out.len(), 3, "no noise estimate: every maximum");
    }
}
