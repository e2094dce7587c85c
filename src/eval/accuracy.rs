//! The seed's three accuracy metrics (J. Wu 2012, §2.1.3.1) between a truth waveform and a
//! processed (raw, denoised or deconvolved) waveform of the same length:
//!
//! 1. **RMSE** (eq. 14): `sqrt( Σ_waveforms Σ_bins (P_2ns(t) − P̃_w(t))² / (m·n) )`, pooled over
//!    every bin (`m` per waveform) of every waveform (`n`). The seed compares the two in their
//!    simulated units, without normalising either: both come from pulses of the same energy, and
//!    deconvolution by a unit-sum kernel conserves it. We do the same (every kernel has unit sum,
//!    so truth and processed waveforms share one unit) and only divide *both* waveforms of a pulse
//!    by one common factor, the truth's peak, so that the figure reads as a fraction of the
//!    truth's highest peak (dimensionless) and pulses with strong and weak scatterers weigh alike.
//!    A common factor changes no shape: a method that loses or invents energy is still penalised.
//! 2. **Peak detections** (eq. 15): local peaks are where the first derivative changes sign from
//!    positive to negative (a flat top counts once, at its first bin). A detected peak is *true*
//!    when its bin agrees with a peak of the truth waveform, one-to-one (a truth peak confirms at
//!    most one detection); every other detection is *false*. Two departures from the seed's
//!    wording, both parameters: agreement within `tolerance_bins` (the seed says "agrees", i.e.
//!    the same bin: tolerance 0), and peaks below `floor_fraction` × the waveform's own maximum
//!    are not counted, in the truth and in the processed waveform alike (the seed counts every
//!    sign change: floor 0). See `docs/accuracy.md` for the defaults and why.
//! 3. **Spectral angle** (SAM, seed figure 2.16): the angle between the two waveforms seen as
//!    vectors with one band per bin, `acos(a·b / (|a|·|b|))`, **in degrees** (0° = same shape,
//!    insensitive to scale; 90° = orthogonal). A zero waveform has no direction: its angle to
//!    anything is taken as 90°.

/// Pooled RMSE of eq. 14 over many waveforms, each scaled by its truth's peak.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RmseAccumulator {
    sum_sq: f64,
    bins: u64,
}

impl RmseAccumulator {
    /// Adds one waveform: squared differences of `truth` and `processed` (same length), both
    /// divided by the truth's largest value (skipped when the truth has no positive value).
    pub fn add(&mut self, truth: &[f32], processed: &[f32]) {
        let peak = truth.iter().fold(0.0f32, |m, &v| m.max(v));
        if !(peak > 0.0 && peak.is_finite()) {
            return;
        }
        let inv = 1.0 / peak as f64;
        let mut s = 0.0f64;
        for (&t, &p) in truth.iter().zip(processed) {
            let d = (t as f64 - p as f64) * inv;
            s += d * d;
        }
        self.sum_sq += s;
        self.bins += truth.len().min(processed.len()) as u64;
    }

    /// Merges another accumulator (pooling its waveforms with these).
    pub fn merge(&mut self, other: &RmseAccumulator) {
        self.sum_sq += other.sum_sq;
        self.bins += other.bins;
    }

    /// The RMSE (fraction of the truth's peak), NaN when nothing was added.
    pub fn rmse(&self) -> f64 {
        if self.bins == 0 {
            f64::NAN
        } else {
            (self.sum_sq / self.bins as f64).sqrt()
        }
    }
}

/// RMSE of one waveform (eq. 14 with `n = 1`), as a fraction of the truth's peak.
pub fn rmse(truth: &[f32], processed: &[f32]) -> f64 {
    let mut acc = RmseAccumulator::default();
    acc.add(truth, processed);
    acc.rmse()
}

/// Spectral angle between `a` and `b` (same length), degrees in `[0, 180]`; 90 when either is
/// zero.
pub fn spectral_angle_deg(a: &[f32], b: &[f32]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0.0f64, 0.0f64, 0.0f64);
    for (&x, &y) in a.iter().zip(b) {
        let (x, y) = (x as f64, y as f64);
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    if !(aa > 0.0 && bb > 0.0) {
        return 90.0;
    }
    (ab / (aa.sqrt() * bb.sqrt()))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Writes into `out` (cleared first) the bins of the local peaks of `x`: where the first
/// derivative changes sign from positive to negative, a flat top counted once at its first bin
/// (a rise, a flat run and a further rise is no peak). Peaks whose value is not above
/// `floor_fraction × max(x)` (and not above zero) are left out. Does not allocate when `out` has
/// capacity for `x.len() / 2 + 1` peaks.
pub fn local_peaks(x: &[f32], floor_fraction: f32, out: &mut Vec<usize>) {
    out.clear();
    let max = x.iter().fold(0.0f32, |m, &v| m.max(v));
    let floor = (floor_fraction * max).max(0.0);
    // `rise_at`: first bin of the current flat run, when the run was entered by a rise.
    let mut rise_at: Option<usize> = None;
    for i in 1..x.len() {
        let d = x[i] - x[i - 1];
        if d > 0.0 {
            rise_at = Some(i);
        } else if d < 0.0
            && let Some(p) = rise_at.take()
            && x[p] > floor
        {
            out.push(p);
        }
        // d == 0 (or NaN): the flat run continues; `rise_at` keeps its first bin.
    }
}

/// True and false detections of one waveform (eq. 15).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PeakMatch {
    /// Detected peaks that agree with a truth peak (one-to-one).
    pub true_detections: u32,
    /// Detected peaks that agree with none.
    pub false_detections: u32,
}

/// Matches `detected` against `truth` peaks (both ascending bins): a detection is true when an
/// unmatched truth peak lies within `tolerance_bins` of it. Scans both in order and pairs each
/// detection with the earliest unmatched truth peak in range, which gives the largest possible
/// number of one-to-one pairs on a line.
pub fn match_peaks(truth: &[usize], detected: &[usize], tolerance_bins: usize) -> PeakMatch {
    let mut m = PeakMatch::default();
    let mut t = 0usize;
    for &d in detected {
        // Truth peaks too far left of this detection can match no later detection either.
        while t < truth.len() && truth[t] + tolerance_bins < d {
            t += 1;
        }
        if t < truth.len() && truth[t] <= d + tolerance_bins {
            m.true_detections += 1;
            t += 1;
        } else {
            m.false_detections += 1;
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rmse_of_identical_waveforms_is_zero() {
        let t = [0.0f32, 1.0, 3.0, 2.0, 0.5];
        assert_eq!(rmse(&t, &t), 0.0);
    }

    #[test]
    fn rmse_by_hand() {
        // Truth peak 2: scaled truth [0, 1, 0.5, 0]; processed scaled [0.5, 1, 0, 0];
        // differences 0.5, 0, 0.5, 0 -> sqrt((0.25 + 0.25) / 4) = sqrt(0.125).
        let truth = [0.0f32, 2.0, 1.0, 0.0];
        let processed = [1.0f32, 2.0, 0.0, 0.0];
        assert!((rmse(&truth, &processed) - 0.125f64.sqrt()).abs() < 1e-12);
        // Pooled over two waveforms: the second identical -> sqrt(0.5 / 8) = 0.25.
        let mut acc = RmseAccumulator::default();
        acc.add(&truth, &processed);
        acc.add(&truth, &truth);
        assert!((acc.rmse() - 0.25).abs() < 1e-12);
        // A common scale changes nothing.
        let t10: Vec<f32> = truth.iter().map(|v| v * 10.0).collect();
        let p10: Vec<f32> = processed.iter().map(|v| v * 10.0).collect();
        assert!((rmse(&t10, &p10) - rmse(&truth, &processed)).abs() < 1e-12);
        assert!(RmseAccumulator::default().rmse().is_nan());
    }

    #[test]
    fn spectral_angle_of_scaled_copy_is_zero_and_orthogonal_is_ninety() {
        let a = [0.0f32, 1.0, 4.0, 2.0];
        let b: Vec<f32> = a.iter().map(|v| v * 3.5).collect();
        assert!(spectral_angle_deg(&a, &b).abs() < 1e-3);
        assert!((spectral_angle_deg(&[1.0, 0.0], &[0.0, 2.0]) - 90.0).abs() < 1e-9);
        // [1, 1] against [1, 0]: 45°.
        assert!((spectral_angle_deg(&[1.0, 1.0], &[1.0, 0.0]) - 45.0).abs() < 1e-9);
        assert_eq!(spectral_angle_deg(&[0.0, 0.0], &[1.0, 0.0]), 90.0);
        assert!((spectral_angle_deg(&[1.0, 0.0], &[-1.0, 0.0]) - 180.0).abs() < 1e-9);
    }

    #[test]
    fn local_peaks_by_hand() {
        let mut out = Vec::with_capacity(8);
        // Peaks at 2 and 6 (flat top 6..=7 counts once at 6); the rise-flat-rise at 9..11 is
        // not a peak until its top at 11; the edge values (bins 0, 12) are no peaks.
        let x = [
            5.0f32, 1.0, 3.0, 1.0, 0.0, 2.0, 4.0, 4.0, 1.0, 2.0, 2.0, 3.0, 1.5,
        ];
        local_peaks(&x, 0.0, &mut out);
        assert_eq!(out, vec![2, 6, 11]);
        // Floor at half the maximum (2.5): the peak at 11 (3.0) and 6 (4.0) stay, 2 (3.0) too.
        local_peaks(&x, 0.5, &mut out);
        assert_eq!(out, vec![2, 6, 11]);
        local_peaks(&x, 0.7, &mut out);
        assert_eq!(out, vec![6]);
        // Monotone and empty inputs have none.
        local_peaks(&[1.0, 2.0, 3.0], 0.0, &mut out);
        assert!(out.is_empty());
        local_peaks(&[], 0.0, &mut out);
        assert!(out.is_empty());
    }

    #[test]
    fn peak_matching_counts_true_and_false() {
        let truth = [10usize, 20, 30];
        // 11 matches 10 (within 1); 12 cannot reuse 10 and is too far from 20 -> false;
        // 19 matches 20; 40 false. 30 is missed (not a detection at all).
        let m = match_peaks(&truth, &[11, 12, 19, 40], 1);
        assert_eq!(
            m,
            PeakMatch {
                true_detections: 2,
                false_detections: 2
            }
        );
        // Exact agreement (the seed's literal reading): only 30 matches.
        let m = match_peaks(&truth, &[11, 19, 30], 0);
        assert_eq!(m.true_detections, 1);
        assert_eq!(m.false_detections, 2);
        // Two truth peaks close together, two detections between them: both pair up.
        let m = match_peaks(&[5, 7], &[6, 7], 1);
        assert_eq!(m.true_detections, 2);
        assert_eq!(match_peaks(&[], &[3], 2).false_detections, 1);
    }

    #[test]
    fn peaks_then_matching_on_a_constructed_waveform() {
        // Truth with peaks at 3 and 9; processed has them at 4 and 9 plus a noise bump at 14.
        let truth = [
            0., 1., 2., 5., 2., 1., 0., 1., 3., 6., 3., 1., 0., 0., 0., 0.,
        ];
        let processed = [
            0., 0., 1., 2., 5., 2., 0., 1., 3., 6., 3., 1., 0., 0.5, 0.8, 0.,
        ];
        let (mut tp, mut dp) = (Vec::new(), Vec::new());
        local_peaks(&truth, 0.05, &mut tp);
        local_peaks(&processed, 0.05, &mut dp);
        assert_eq!(tp, vec![3, 9]);
        assert_eq!(dp, vec![4, 9, 14]);
        let m = match_peaks(&tp, &dp, 1);
        assert_eq!((m.true_detections, m.false_detections), (2, 1));
        // With a 20 % floor the bump (0.8 < 1.2) is no longer detected.
        local_peaks(&processed, 0.2, &mut dp);
        assert_eq!(dp, vec![4, 9]);
    }
}
