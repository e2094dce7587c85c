//! The system response used for deconvolution: a short kernel of taps with a declared centre.
//!
//! Convolution convention (used by every method): `(k ⊛ x)[i] = Σ_j taps[j] · x[i + center − j]`
//! over the indices that exist (samples outside the segment are zero). A kernel whose peak is at
//! `center` therefore does not shift anything in time: deconvolving with it keeps returns where
//! they are. Correlation (convolution with the flipped kernel) is
//! `(k ⋆ x)[i] = Σ_j taps[j] · x[i − center + j]`.
//!
//! Per-shot kernels come from the outgoing pulse, cut to its support (the contiguous run of
//! samples around the peak standing above the record's noise, [`pulse_support`]), baseline
//! removed, normalised to unit sum, centred on the peak sample
//! ([`Kernel::set_from_outgoing_support`]); a calibrated system impulse response can
//! come from configuration as plain taps, or be measured on a flat target
//! ([`crate::signal::deconvolve::response`]).
//!
//! **Zero-phase alignment on the peak, not the centroid.** The zero-delay tap of a kernel built
//! from a recorded pulse is its highest sample. A point target at two-way time `t` then returns
//! `k ⊛ δ_t`, whose highest sample is at `t`, and deconvolution puts the target back at `t`: the
//! deconvolved return lies where the raw echo peaked, the convention of discrete-return ranging
//! and of the NEON geolocation (`geo.csv` references the outgoing pulse at its peak bin). The
//! centroid was rejected: for the asymmetric pulses of real digitizers (NEON: a 1-2 ns rise, a
//! long tail) it lies 1.5-2 bins after the peak, so every return would move by that much
//! relative to the raw peak; it is not a sample, so it needs rounding (±0.5 bin) or a
//! fractional shift; and it depends on where the recording truncates the tail and on the
//! baseline estimate (a 1 % baseline error over a 60-sample tail moves it by about a bin),
//! while the peak depends on neither. See `docs/signal.md`.

/// Number of leading samples whose median is taken as the baseline of a recorded pulse
/// ([`remove_baseline`]).
pub const KERNEL_BASELINE_SAMPLES: usize = 8;

/// A recorded pulse (digitizer counts or volts on a pedestal) minus its baseline, the median
/// of its first [`KERNEL_BASELINE_SAMPLES`] samples (the pre-trigger samples). Empty in, empty
/// out.
pub fn remove_baseline(row: &[f32]) -> Vec<f32> {
    if row.is_empty() {
        return Vec::new();
    }
    let mut head = row[..row.len().min(KERNEL_BASELINE_SAMPLES)].to_vec();
    head.sort_unstable_by(f32::total_cmp);
    let n = head.len();
    let base = if n % 2 == 1 {
        head[n / 2]
    } else {
        0.5 * (head[n / 2 - 1] + head[n / 2])
    };
    row.iter().map(|v| v - base).collect()
}

/// Index of the first maximum of `x` (the peak sample of a recorded pulse: the zero-delay tap
/// of a kernel, the emission reference of the `calibrate` stage); `None` when `x` is empty or
/// holds no number above `f32::MIN` (NaN samples are never a maximum).
pub fn peak_index(x: &[f32]) -> Option<usize> {
    let mut peak = None;
    let mut best = f32::MIN;
    for (i, &v) in x.iter().enumerate() {
        if v > best {
            best = v;
            peak = Some(i);
        }
    }
    peak
}

/// Noise multiple `k` bounding the support of a recorded outgoing pulse: the support is the
/// contiguous run of samples around the peak that stand more than `k` noise standard deviations
/// above the baseline ([`pulse_support`], `docs/signal.md`). Gaussian noise exceeds 3 σ on one
/// side in 0.13 % of samples, so a run of noise alone rarely continues the support.
pub const KERNEL_SUPPORT_NOISE_K: f32 = 3.0;

/// Floor of the support threshold as a fraction of the peak height above the baseline: a
/// noise-free record (synthetic pulses, a quantised record whose baseline samples are all equal)
/// keeps the samples above 1e-3 of its peak, as the flat-target response is cut.
pub const KERNEL_SUPPORT_FLOOR: f32 = 1e-3;

/// Fewest samples an end window of a recorded pulse must hold to estimate its baseline and
/// noise ([`pulse_support`]).
pub const KERNEL_NOISE_MIN_SAMPLES: usize = 3;

/// Where a recorded pulse stands out of its noise ([`pulse_support`]). Amplitudes in the units
/// of the samples.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PulseSupport {
    /// Index of the peak sample (the first maximum).
    pub peak: usize,
    /// Baseline: the median of the end window (0 when neither end has a window).
    pub baseline: f32,
    /// Noise standard deviation in that window, `√(π/2)` × the mean absolute deviation from
    /// its median (0 when neither end has a window).
    pub noise: f32,
    /// Distance from the baseline a sample must exceed to be in the support:
    /// `max(KERNEL_SUPPORT_NOISE_K · noise, KERNEL_SUPPORT_FLOOR · height)`.
    pub threshold: f32,
    /// First sample of the support.
    pub start: usize,
    /// One past its last sample.
    pub end: usize,
}

impl PulseSupport {
    /// Samples in the support (at least 1: the peak).
    pub fn len(&self) -> usize {
        self.end - self.start
    }

    /// Never true: the support holds the peak.
    pub fn is_empty(&self) -> bool {
        self.end == self.start
    }
}

/// Median and noise standard deviation (`√(π/2)` × mean absolute deviation from the median) of
/// at most [`KERNEL_BASELINE_SAMPLES`] finite samples; no allocation.
fn level_and_noise(w: &[f32]) -> (f32, f32) {
    let mut buf = [0.0f32; KERNEL_BASELINE_SAMPLES];
    let n = w.len().min(KERNEL_BASELINE_SAMPLES);
    buf[..n].copy_from_slice(&w[..n]);
    let head = &mut buf[..n];
    head.sort_unstable_by(f32::total_cmp);
    let median = if n % 2 == 1 {
        head[n / 2]
    } else {
        0.5 * (head[n / 2 - 1] + head[n / 2])
    };
    let mad: f32 = head.iter().map(|v| (v - median).abs()).sum::<f32>() / n as f32;
    (median, mad * std::f32::consts::FRAC_PI_2.sqrt())
}

/// The baseline, noise and support of a recorded pulse (an outgoing segment).
///
/// - **Baseline and noise** come from one end window of up to [`KERNEL_BASELINE_SAMPLES`]
///   samples: the leading one (the digitizer's pre-trigger samples, at most half-way to the
///   peak so the rise stays out of it) when it holds at least [`KERNEL_NOISE_MIN_SAMPLES`],
///   else the trailing one (at least half-way from the peak to the end; a pulse peaking at the
///   start of its record). Its median is the baseline; its noise is `√(π/2)` × the mean
///   absolute deviation from that median (the standard deviation for Gaussian noise). With no
///   usable window both are 0. What `known` states replaces the estimate ([`RecordLevels`]).
/// - **Support**: the contiguous run of samples around the peak standing out of the noise, more
///   than `max(KERNEL_SUPPORT_NOISE_K · noise, KERNEL_SUPPORT_FLOOR · height)` away from the
///   baseline (`height` the peak above the baseline). A long low tail stays in while it is
///   above the noise, and so do undershoots and the ringing lobes of a low-passed pulse (the
///   returns went through the same filter); a tail of noise, or an after-pulse beyond samples
///   back in the noise, does not.
///
/// Errors: [`KernelError::NonFinite`] for a NaN or infinite sample; [`KernelError::NoEnergy`]
/// when the record is empty or its peak is not above the baseline (a flat record);
/// [`KernelError::BelowNoise`] when the peak does not stand above `k` noise deviations.
pub fn pulse_support(x: &[f32], known: RecordLevels) -> Result<PulseSupport, KernelError> {
    if x.iter().any(|v| !v.is_finite()) {
        return Err(KernelError::NonFinite);
    }
    let peak = peak_index(x).ok_or(KernelError::NoEnergy)?;
    let n = x.len();
    let lead = &x[..KERNEL_BASELINE_SAMPLES.min(peak / 2)];
    let trail_start = n
        .saturating_sub(KERNEL_BASELINE_SAMPLES)
        .max(peak + 1 + (n - 1 - peak) / 2);
    let trail = &x[trail_start.min(n)..];
    let lead_usable = lead.len() >= KERNEL_NOISE_MIN_SAMPLES;
    let (mut baseline, mut noise) = if lead_usable {
        level_and_noise(lead)
    } else if trail.len() >= KERNEL_NOISE_MIN_SAMPLES {
        level_and_noise(trail)
    } else {
        (0.0, 0.0)
    };
    if known.baseline_removed && lead_usable {
        baseline = 0.0;
    }
    if let Some(n) = known.noise.filter(|n| n.is_finite() && *n >= 0.0) {
        noise = n;
    }
    let height = x[peak] - baseline;
    // Finite: every sample and the baseline are.
    if height <= 0.0 {
        return Err(KernelError::NoEnergy);
    }
    let noise_level = KERNEL_SUPPORT_NOISE_K * noise;
    if height <= noise_level {
        return Err(KernelError::BelowNoise { height, noise });
    }
    let threshold = noise_level.max(KERNEL_SUPPORT_FLOOR * height);
    let above = |i: usize| (x[i] - baseline).abs() > threshold;
    let mut start = peak;
    while start > 0 && above(start - 1) {
        start -= 1;
    }
    let mut end = peak + 1;
    while end < n && above(end) {
        end += 1;
    }
    Ok(PulseSupport {
        peak,
        baseline,
        noise,
        threshold,
        start,
        end,
    })
}

/// What a caller already knows about a record's levels ([`pulse_support`]), in its units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RecordLevels {
    /// The record is already relative to the baseline of its leading (pre-trigger) samples
    /// (the denoise stage removed it): with a usable leading window the baseline is 0, not
    /// estimated again from samples that may hold the low-passed pulse's tail. When the peak is
    /// too close to the start for a leading window, the trailing window's median is taken
    /// all the same (the pre-trigger estimate then held the pulse).
    pub baseline_removed: bool,
    /// The noise standard deviation when known (the denoise stage's `noise_v`, measured over
    /// all return samples); otherwise estimated from the end window.
    pub noise: Option<f32>,
}

/// What [`Kernel::set_from_outgoing_support`] built from a recorded outgoing pulse.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KernelFit {
    /// The pulse's baseline, noise and support.
    pub support: PulseSupport,
    /// Samples from the support's first to its last sample above the baseline: the kernel's
    /// length before any cut.
    pub span: usize,
    /// First sample of the record taken as a tap.
    pub start: usize,
    /// Taps kept: `span`, or at most `max_taps` when `span` was longer.
    pub taps: usize,
}

impl KernelFit {
    /// True when the span was longer than `max_taps` and the kernel was cut to it.
    pub fn was_cut(&self) -> bool {
        self.span > self.taps
    }
}

/// Why a kernel could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KernelError {
    /// No taps, or every tap zero or negative.
    #[error("kernel has no positive energy")]
    NoEnergy,
    /// A tap is NaN or infinite.
    #[error("kernel has a non-finite tap")]
    NonFinite,
    /// The peak does not stand above the noise of the record ([`pulse_support`]).
    #[error("pulse peak {height} is not above {KERNEL_SUPPORT_NOISE_K} x its noise {noise}")]
    BelowNoise {
        /// Peak above the baseline.
        height: f32,
        /// Noise standard deviation.
        noise: f32,
    },
    /// A Gaussian pulse's FWHM or sample interval is not a positive finite number, or the
    /// pulse spans more than 1000 samples per FWHM.
    #[error("a Gaussian pulse of FWHM {fwhm_ns} ns at {sample_ns} ns per sample is not usable")]
    BadGaussian {
        /// FWHM, ns.
        fwhm_ns: f64,
        /// Sample interval, ns.
        sample_ns: f64,
    },
    /// More taps than the buffers were sized for.
    #[error("kernel of {len} taps exceeds the maximum of {max}")]
    TooLong {
        /// Taps given.
        len: usize,
        /// Maximum.
        max: usize,
    },
}

/// A normalised system response: taps summing to 1 with the zero-delay tap at `center`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Kernel {
    /// The taps (unit sum, non-negative for kernels from outgoing pulses).
    pub taps: Vec<f32>,
    /// Index of the zero-delay tap (the peak for kernels from outgoing pulses).
    pub center: usize,
}

impl Kernel {
    /// An empty kernel whose buffer holds `max_taps` without reallocating.
    pub fn with_capacity(max_taps: usize) -> Self {
        Kernel {
            taps: Vec::with_capacity(max_taps),
            center: 0,
        }
    }

    /// Rebuilds the kernel from an outgoing pulse already in volts above its baseline:
    /// negative samples clipped to zero, normalised to unit sum, centred on the peak sample (the
    /// zero-phase alignment: the peak is the emission reference t0 of the digitizer, so a return
    /// deconvolved with it stays at its two-way time). Does not allocate within capacity.
    pub fn set_from_outgoing(
        &mut self,
        outgoing: &[f32],
        max_taps: usize,
    ) -> Result<(), KernelError> {
        if outgoing.len() > max_taps {
            return Err(KernelError::TooLong {
                len: outgoing.len(),
                max: max_taps,
            });
        }
        if outgoing.iter().any(|v| !v.is_finite()) {
            return Err(KernelError::NonFinite);
        }
        self.taps.clear();
        self.taps.extend(outgoing.iter().map(|v| v.max(0.0)));
        let sum: f64 = self.taps.iter().map(|&v| v as f64).sum();
        if sum <= 0.0 || !sum.is_finite() {
            return Err(KernelError::NoEnergy);
        }
        let inv = (1.0 / sum) as f32;
        for v in self.taps.iter_mut() {
            *v *= inv;
        }
        self.center = peak_index(&self.taps).unwrap_or(0);
        Ok(())
    }

    /// Rebuilds the kernel from a recorded outgoing pulse (volts, or counts, on a baseline),
    /// cut to its support ([`pulse_support`]): the taps are the support's samples minus the
    /// baseline, negative ones (undershoots, ringing) clipped to zero and zero taps at either
    /// end left out, normalised to unit sum, the zero-delay tap on the peak sample (so returns
    /// do not move). A span longer than `max_taps` is cut to the `max_taps` samples around the
    /// peak holding the most energy (the window, among those containing the peak, with the
    /// largest sum), and the result says so ([`KernelFit::was_cut`]). Does not allocate
    /// within capacity.
    pub fn set_from_outgoing_support(
        &mut self,
        outgoing: &[f32],
        known: RecordLevels,
        max_taps: usize,
    ) -> Result<KernelFit, KernelError> {
        let support = pulse_support(outgoing, known)?;
        if max_taps == 0 {
            return Err(KernelError::TooLong {
                len: support.len(),
                max: 0,
            });
        }
        let (b, peak) = (support.baseline, support.peak);
        // The taps: the samples above the baseline (negative lobes of the support clipped to
        // zero), without the zero taps at either end.
        let tap = |i: usize| (outgoing[i] - b).max(0.0) as f64;
        let (mut start, mut end) = (support.start, support.end);
        while start < peak && tap(start) == 0.0 {
            start += 1;
        }
        while end - 1 > peak && tap(end - 1) == 0.0 {
            end -= 1;
        }
        let span = end - start;
        if span > max_taps {
            // Windows of `max_taps` inside the span that contain the peak start from `lo` to
            // `hi`; slide a running sum and keep the first largest, then drop its end zeros.
            let lo = start.max((peak + 1).saturating_sub(max_taps));
            let hi = peak.min(end - max_taps);
            let mut sum: f64 = (lo..lo + max_taps).map(tap).sum();
            let (mut best, mut best_sum) = (lo, sum);
            for s in lo + 1..=hi {
                sum += tap(s + max_taps - 1) - tap(s - 1);
                if sum > best_sum {
                    best = s;
                    best_sum = sum;
                }
            }
            (start, end) = (best, best + max_taps);
            while start < peak && tap(start) == 0.0 {
                start += 1;
            }
            while end - 1 > peak && tap(end - 1) == 0.0 {
                end -= 1;
            }
        }
        let sum: f64 = (start..end).map(tap).sum();
        if !(sum > 0.0 && sum.is_finite()) {
            return Err(KernelError::NoEnergy);
        }
        let inv = 1.0 / sum;
        self.taps.clear();
        self.taps
            .extend((start..end).map(|i| (tap(i) * inv) as f32));
        self.center = peak - start;
        Ok(KernelFit {
            support,
            span,
            start,
            taps: end - start,
        })
    }

    /// Sets the kernel from calibrated taps with an explicit centre, normalised to unit sum
    /// (taps may be negative, e.g. a ringing receiver response, but the sum must be positive).
    pub fn set_from_taps(
        &mut self,
        taps: &[f32],
        center: usize,
        max_taps: usize,
    ) -> Result<(), KernelError> {
        if taps.len() > max_taps {
            return Err(KernelError::TooLong {
                len: taps.len(),
                max: max_taps,
            });
        }
        if taps.iter().any(|v| !v.is_finite()) {
            return Err(KernelError::NonFinite);
        }
        let sum: f64 = taps.iter().map(|&v| v as f64).sum();
        if taps.is_empty() || sum <= 0.0 || center >= taps.len() {
            return Err(KernelError::NoEnergy);
        }
        self.taps.clear();
        self.taps
            .extend(taps.iter().map(|&v| (v as f64 / sum) as f32));
        self.center = center;
        Ok(())
    }

    /// Sets the kernel to a sampled Gaussian pulse of full width at half maximum `fwhm_ns`
    /// (ns) at `sample_ns` (ns per sample): taps `exp(−½ (j/s)²)` for `|j| ≤ ⌈3.5 s⌉`
    /// (`s = fwhm / (2√(2 ln 2))` in samples, at least one tap either side), normalised to unit
    /// sum (in f64), centred on the middle tap. The simulator's pulses and the target pulse of
    /// [`target`](crate::signal::deconvolve::target) are this kernel. Allocates only when the
    /// pulse needs more taps than the buffer holds.
    pub fn set_gaussian(&mut self, fwhm_ns: f64, sample_ns: f64) -> Result<(), KernelError> {
        if !(fwhm_ns.is_finite() && fwhm_ns > 0.0 && sample_ns.is_finite() && sample_ns > 0.0)
            || fwhm_ns / sample_ns > 1000.0
        {
            return Err(KernelError::BadGaussian { fwhm_ns, sample_ns });
        }
        let sigma = fwhm_ns / sample_ns / (2.0 * (2.0 * std::f64::consts::LN_2).sqrt());
        let half = (3.5 * sigma).ceil().max(1.0) as usize;
        self.taps.clear();
        self.taps.extend((0..=2 * half).map(|j| {
            let x = j as f64 - half as f64;
            (-0.5 * (x / sigma).powi(2)).exp() as f32
        }));
        let sum: f64 = self.taps.iter().map(|&v| v as f64).sum();
        for v in self.taps.iter_mut() {
            *v = (*v as f64 / sum) as f32;
        }
        self.center = half;
        Ok(())
    }

    /// Number of taps.
    pub fn len(&self) -> usize {
        self.taps.len()
    }

    /// True when the kernel has no taps.
    pub fn is_empty(&self) -> bool {
        self.taps.is_empty()
    }

    /// Full width at half maximum of the taps, samples (linear interpolation at the two
    /// half-maximum crossings around the largest tap; a side without a crossing counts from
    /// half a sample beyond the end). `None` for an empty kernel or one without a positive tap.
    pub fn fwhm_samples(&self) -> Option<f64> {
        let (k, peak) = self
            .taps
            .iter()
            .enumerate()
            .fold((0, 0.0f32), |b, (i, &v)| if v > b.1 { (i, v) } else { b });
        if !(peak > 0.0 && peak.is_finite()) {
            return None;
        }
        let half = f64::from(peak) / 2.0;
        let v = |i: usize| f64::from(self.taps[i]);
        let (left, right) = crate::core::half_max::crossings(self.taps.len(), v, k, half);
        let left = left.unwrap_or(-0.5);
        let right = right.unwrap_or_else(|r| r as f64 + 0.5);
        Some(right - left)
    }
}

/// `out = k ⊛ x` (same length as `x`; see the module's convention). `out.len()` must equal
/// `x.len()`.
pub fn convolve_same(x: &[f32], k: &Kernel, out: &mut [f32]) {
    let n = x.len() as isize;
    let c = k.center as isize;
    for (i, o) in out.iter_mut().enumerate() {
        let mut acc = 0.0f32;
        for (j, &t) in k.taps.iter().enumerate() {
            let src = i as isize + c - j as isize;
            if src >= 0 && src < n {
                acc += t * x[src as usize];
            }
        }
        *o = acc;
    }
}

/// `out = k ⋆ x`, the adjoint of [`convolve_same`] (convolution with the flipped kernel).
pub fn correlate_same(x: &[f32], k: &Kernel, out: &mut [f32]) {
    let n = x.len() as isize;
    let c = k.center as isize;
    for (i, o) in out.iter_mut().enumerate() {
        let mut acc = 0.0f32;
        for (j, &t) in k.taps.iter().enumerate() {
            let src = i as isize - c + j as isize;
            if src >= 0 && src < n {
                acc += t * x[src as usize];
            }
        }
        *o = acc;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fwhm_of_a_sampled_gaussian_is_its_width() {
        for (fwhm, dt) in [(8.0, 1.0), (4.0, 0.5), (16.0, 2.0), (2.5, 1.0)] {
            let mut k = Kernel::with_capacity(256);
            k.set_gaussian(fwhm, dt).unwrap();
            let got = k.fwhm_samples().unwrap() * dt;
            // Linear interpolation between samples: within a tenth of a sample of the width.
            assert!(
                (got - fwhm).abs() < 0.1 * dt + 0.02 * fwhm,
                "{fwhm} at {dt}: {got}"
            );
        }
        assert_eq!(Kernel::default().fwhm_samples(), None);
        let one = Kernel {
            taps: vec![1.0],
            center: 0,
        };
        assert_eq!(one.fwhm_samples(), Some(1.0));
    }

    #[test]
    fn outgoing_kernel_is_normalised_and_centred_on_its_peak() {
        let mut k = Kernel::with_capacity(16);
        k.set_from_outgoing(&[0.0, -0.1, 1.0, 3.0, 1.0, 0.0], 16)
            .unwrap();
        assert_eq!(k.center, 3);
        assert!((k.taps.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert_eq!(k.taps[1], 0.0);
    }

    #[test]
    fn a_centred_kernel_does_not_shift_a_spike() {
        let mut k = Kernel::with_capacity(16);
        k.set_from_outgoing(&[1.0, 2.0, 4.0, 2.0, 1.0], 16).unwrap();
        let mut x = vec![0.0f32; 20];
        x[9] = 1.0;
        let mut y = vec![0.0f32; 20];
        convolve_same(&x, &k, &mut y);
        let peak = y
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap()
            .0;
        assert_eq!(peak, 9);
        assert!((y.iter().sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn correlation_is_the_adjoint_of_convolution() {
        // <k ⊛ x, y> == <x, k ⋆ y> for an asymmetric, off-centre kernel.
        let mut k = Kernel::default();
        k.set_from_taps(&[0.5, 2.0, -0.3, 0.8], 1, 8).unwrap();
        let x: Vec<f32> = (0..13).map(|i| ((i * 7) % 5) as f32 - 1.0).collect();
        let y: Vec<f32> = (0..13).map(|i| ((i * 3) % 4) as f32 + 0.5).collect();
        let mut kx = vec![0.0; 13];
        let mut ky = vec![0.0; 13];
        convolve_same(&x, &k, &mut kx);
        correlate_same(&y, &k, &mut ky);
        let a: f32 = kx.iter().zip(&y).map(|(a, b)| a * b).sum();
        let b: f32 = x.iter().zip(&ky).map(|(a, b)| a * b).sum();
        assert!((a - b).abs() < 1e-4, "{a} vs {b}");
    }

    #[test]
    fn bad_kernels_are_errors() {
        let mut k = Kernel::with_capacity(4);
        assert_eq!(
            k.set_from_outgoing(&[0.0, -1.0], 4),
            Err(KernelError::NoEnergy)
        );
        assert_eq!(
            k.set_from_outgoing(&[f32::NAN], 4),
            Err(KernelError::NonFinite)
        );
        assert!(matches!(
            k.set_from_outgoing(&[1.0; 5], 4),
            Err(KernelError::TooLong { .. })
        ));
    }

    /// Deterministic noise: uniform in ±`a` from a small LCG (σ = a / √3).
    fn noise(n: usize, a: f32, seed: u32) -> Vec<f32> {
        let mut x = seed;
        (0..n)
            .map(|_| {
                x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                a * ((x >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0)
            })
            .collect()
    }

    /// The instrument pulse: 98 samples, peak 200 at sample 15, a fast fall and a long
    /// low tail (15 % of the peak decaying over 25 samples), on a baseline of 3 with ±1 noise.
    fn long_tail_pulse() -> Vec<f32> {
        let clean = |i: usize| {
            let t = i as f32 - 15.0;
            if t < 0.0 {
                200.0 * (-0.5 * (t / 2.0).powi(2)).exp()
            } else {
                200.0 * (0.85 * (-t / 3.0).exp() + 0.15 * (-t / 25.0).exp())
            }
        };
        let n = noise(98, 1.0, 7);
        (0..98).map(|i| 3.0 + clean(i) + n[i]).collect()
    }

    fn assert_unit_sum(k: &Kernel) {
        let sum: f64 = k.taps.iter().map(|&v| v as f64).sum();
        assert!((sum - 1.0).abs() < 1e-5, "sum {sum}");
        assert!(k.taps.iter().all(|v| *v > 0.0), "{:?}", k.taps);
    }

    #[test]
    fn a_long_low_tail_is_kept_while_above_the_noise_and_fits_max_taps() {
        let x = long_tail_pulse();
        let s = pulse_support(&x, RecordLevels::default()).unwrap();
        assert_eq!(s.peak, 15);
        assert!((s.baseline - 3.0).abs() < 0.8, "baseline {}", s.baseline);
        assert!(s.noise > 0.2 && s.noise < 1.5, "noise {}", s.noise);
        // The tail 0.15·200·exp(−t/25) meets 3 σ (≈ 1.7) about 70 samples after the peak.
        assert!(s.end > 60 && s.end < 98, "support {}..{}", s.start, s.end);
        assert!(
            s.start > 5 && s.start < 12,
            "support {}..{}",
            s.start,
            s.end
        );
        assert!(
            x[s.start..s.end]
                .iter()
                .all(|v| v - s.baseline > s.threshold)
        );
        assert!(s.end == x.len() || (x[s.end] - s.baseline).abs() <= s.threshold);
        assert!((x[s.start - 1] - s.baseline).abs() <= s.threshold);
        let mut k = Kernel::with_capacity(96);
        let fit = k
            .set_from_outgoing_support(&x, RecordLevels::default(), 96)
            .unwrap();
        assert!(!fit.was_cut());
        assert_eq!(k.len(), s.len());
        assert_eq!(k.center, 15 - s.start, "the zero-delay tap is the peak");
        assert_unit_sum(&k);
        // The whole 98-sample record would not fit: the old rule dropped it.
        assert!(matches!(
            Kernel::default().set_from_outgoing(&x, 96),
            Err(KernelError::TooLong { len: 98, max: 96 })
        ));
    }

    #[test]
    fn a_tail_of_noise_is_cut_off() {
        // A Gaussian pulse (σ 2) at 20 then 78 samples of noise alone.
        let n = noise(98, 1.0, 3);
        let x: Vec<f32> = (0..98)
            .map(|i| 100.0 * (-0.5 * ((i as f32 - 20.0) / 2.0).powi(2)).exp() + n[i])
            .collect();
        let s = pulse_support(&x, RecordLevels::default()).unwrap();
        assert_eq!(s.peak, 20);
        // 100·exp(−d²/8) > 3σ ≈ 1.7 for |d| < 5.7.
        assert!(
            s.start >= 13 && s.end <= 28,
            "support {}..{}",
            s.start,
            s.end
        );
        let mut k = Kernel::with_capacity(16);
        k.set_from_outgoing_support(&x, RecordLevels::default(), 16)
            .unwrap();
        assert_eq!(k.center, 20 - s.start);
        assert_unit_sum(&k);
    }

    #[test]
    fn a_peak_at_either_edge_takes_its_baseline_from_the_other_end() {
        // Peak at sample 0 on a baseline of 5 (the pre-trigger samples are the pulse itself).
        let mut x: Vec<f32> = (0..40)
            .map(|i| 5.0 + 80.0 * (-(i as f32) / 2.5).exp())
            .collect();
        x.iter_mut()
            .zip(noise(40, 0.5, 11))
            .for_each(|(v, n)| *v += n);
        let s = pulse_support(&x, RecordLevels::default()).unwrap();
        assert_eq!((s.peak, s.start), (0, 0));
        assert!((s.baseline - 5.0).abs() < 0.5, "baseline {}", s.baseline);
        assert!(s.end > 5 && s.end < 20, "end {}", s.end);
        let mut k = Kernel::with_capacity(32);
        k.set_from_outgoing_support(&x, RecordLevels::default(), 32)
            .unwrap();
        assert_eq!(k.center, 0);
        assert_unit_sum(&k);
        // Peak at the last sample: the leading samples give the baseline.
        x.reverse();
        let s = pulse_support(&x, RecordLevels::default()).unwrap();
        assert_eq!((s.peak, s.end), (39, 40));
        assert!((s.baseline - 5.0).abs() < 0.5, "baseline {}", s.baseline);
        k.set_from_outgoing_support(&x, RecordLevels::default(), 32)
            .unwrap();
        assert_eq!(k.center, k.len() - 1);
        assert_unit_sum(&k);
    }

    #[test]
    fn flat_records_have_no_pulse_and_a_flat_top_is_kept_whole() {
        let mut k = Kernel::with_capacity(32);
        for level in [0.0f32, 3.0, -2.0] {
            assert_eq!(
                k.set_from_outgoing_support(&[level; 20], RecordLevels::default(), 32),
                Err(KernelError::NoEnergy),
                "{level}"
            );
        }
        // A clipped (saturated) pulse: five equal samples; the zero-delay tap is the first
        // maximum, as before.
        let mut x = vec![1.0f32; 24];
        x[10..15].fill(9.0);
        x[9] = 4.0;
        x[15] = 4.0;
        let fit = k
            .set_from_outgoing_support(&x, RecordLevels::default(), 32)
            .unwrap();
        assert_eq!((fit.support.start, fit.support.end), (9, 16));
        assert_eq!(k.center, 1);
        assert_unit_sum(&k);
    }

    #[test]
    fn negative_lobes_are_in_the_support_but_not_in_the_taps() {
        // A dip before the pulse and an undershoot after it (AC-coupled receiver): they stand
        // out of the noise, so the support runs through them, but as taps they are clipped to
        // zero (and left out at the ends); an after-pulse beyond samples back in the noise is
        // not part of it.
        let mut x = vec![0.0f32; 60];
        for (i, v) in [(18, 2.0), (19, -8.0), (20, 10.0), (21, 60.0), (22, 100.0)] {
            x[i] = v;
        }
        for (i, v) in [(23, 70.0), (24, 30.0), (25, 8.0), (26, -20.0), (27, -10.0)] {
            x[i] = v;
        }
        x[30] = 40.0; // after-pulse beyond the undershoot
        x.iter_mut()
            .zip(noise(60, 0.2, 5))
            .for_each(|(v, n)| *v += n);
        let s = pulse_support(&x, RecordLevels::default()).unwrap();
        assert_eq!((s.peak, s.start, s.end), (22, 18, 28));
        let mut k = Kernel::with_capacity(16);
        let fit = k
            .set_from_outgoing_support(&x, RecordLevels::default(), 16)
            .unwrap();
        assert_eq!((fit.start, fit.span, k.len(), k.center), (18, 8, 8, 4));
        assert_eq!(k.taps[1], 0.0, "the dip is a zero tap");
        assert!((k.taps.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        assert!(k.taps.iter().all(|v| *v >= 0.0) && k.taps[7] > 0.0);
        // Cut to 6 taps: the window holding the most energy keeps the peak, drops the dip.
        let fit = k
            .set_from_outgoing_support(&x, RecordLevels::default(), 6)
            .unwrap();
        assert!(fit.was_cut());
        assert_eq!((fit.start, k.len(), k.center), (20, 6, 2));
        assert_unit_sum(&k);
    }

    #[test]
    fn non_finite_samples_and_pulses_under_the_noise_are_errors() {
        let mut k = Kernel::with_capacity(128);
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            // Far in the tail or at the peak: a record holding one is not trusted.
            for at in [15, 90] {
                let mut x = long_tail_pulse();
                x[at] = bad;
                assert_eq!(
                    k.set_from_outgoing_support(&x, RecordLevels::default(), 128),
                    Err(KernelError::NonFinite),
                    "{bad} at {at}"
                );
            }
        }
        assert_eq!(
            k.set_from_outgoing_support(&[], RecordLevels::default(), 128),
            Err(KernelError::NoEnergy)
        );
        // Noise alone (±0.6 in the leading samples), its largest sample 0.9: not a pulse.
        let mut x = vec![0.5f32, -0.5, 0.6, -0.6, 0.4, -0.4, 0.5, -0.5];
        x.extend((0..40).map(|i| if i % 2 == 0 { 0.5 } else { -0.5 }));
        x[30] = 0.9;
        assert!(matches!(
            k.set_from_outgoing_support(&x, RecordLevels::default(), 128),
            Err(KernelError::BelowNoise { .. })
        ));
    }

    #[test]
    fn a_support_longer_than_max_taps_is_cut_around_the_peak_to_the_most_energy() {
        let x = long_tail_pulse();
        let s = pulse_support(&x, RecordLevels::default()).unwrap();
        let mut k = Kernel::with_capacity(96);
        let cap = k.taps.capacity();
        for max in [1usize, 2, 8, 20, 40] {
            let fit = k
                .set_from_outgoing_support(&x, RecordLevels::default(), max)
                .unwrap();
            assert!(fit.was_cut(), "{max}");
            assert_eq!(k.len(), max);
            assert_eq!(
                fit.start + k.center,
                15,
                "{max}: the peak stays the zero-delay tap"
            );
            assert_unit_sum(&k);
            // Among the windows of `max` samples inside the support that hold the peak, none
            // holds more energy.
            let energy = |a: usize| {
                x[a..a + max]
                    .iter()
                    .map(|v| (v - s.baseline).max(0.0))
                    .sum::<f32>()
            };
            let got = energy(fit.start);
            for a in s.start..=s.end - max {
                if (a..a + max).contains(&15) {
                    assert!(energy(a) <= got + 1e-3, "{max}: window at {a} holds more");
                }
            }
        }
        assert_eq!(k.taps.capacity(), cap, "no reallocation within capacity");
        assert!(matches!(
            k.set_from_outgoing_support(&x, RecordLevels::default(), 0),
            Err(KernelError::TooLong { max: 0, .. })
        ));
    }

    #[test]
    fn what_the_caller_knows_replaces_the_estimates() {
        // A short record (±5 σ) whose leading samples hold the pulse's own tail, already above
        // its baseline: estimated, the tail would count as baseline and noise and cut the
        // kernel; known (the denoise stage's baseline and noise_v), the kernel keeps it.
        let x: Vec<f32> = (0..17)
            .map(|i| (-0.5 * ((i as f32 - 8.0) / 1.7).powi(2)).exp())
            .collect();
        let guessed = pulse_support(&x, RecordLevels::default()).unwrap();
        assert!(
            guessed.baseline > 0.0 && guessed.noise > 0.001,
            "{guessed:?}"
        );
        let known = RecordLevels {
            baseline_removed: true,
            noise: Some(1e-4),
        };
        let s = pulse_support(&x, known).unwrap();
        assert_eq!((s.baseline, s.noise), (0.0, 1e-4));
        assert_eq!((s.start, s.end), (2, 15), "samples above 1e-3 of the peak");
        assert!(guessed.len() < s.len(), "{guessed:?}");
        // A peak at the start: the removed baseline was the pulse; the trailing samples say.
        let mut y: Vec<f32> = (0..40).map(|i| 80.0 * (-(i as f32) / 2.5).exp()).collect();
        y.iter_mut().for_each(|v| *v -= 20.0);
        let s = pulse_support(&y, known).unwrap();
        assert!((s.baseline + 20.0).abs() < 0.01, "{s:?}");
        assert_eq!(s.start, 0);
    }

    #[test]
    fn a_support_kernel_does_not_shift_a_spike() {
        let mut k = Kernel::with_capacity(96);
        k.set_from_outgoing_support(&long_tail_pulse(), RecordLevels::default(), 96)
            .unwrap();
        let mut x = vec![0.0f32; 200];
        x[60] = 1.0;
        let mut y = vec![0.0f32; 200];
        convolve_same(&x, &k, &mut y);
        assert_eq!(peak_index(&y), Some(60));
    }
}
