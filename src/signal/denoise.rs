//! Noise reduction (the `denoise` stage's method): digitizer counts to volts, baseline and noise level per pulse, the seed's
//! level shift, and a low-pass (seed default cut-off 0.2 GHz at 1 ns sampling): the seed's FFT
//! brick wall (the default) or a short FIR.
//!
//! Per pulse and per segment (outgoing and returns alike), in this order:
//!
//! 1. **Baseline** (noise floor), estimated on the raw counts: the median of the first
//!    [`DenoiseConfig::pretrigger_samples`] samples when the segment holds at least four times
//!    that many samples; otherwise an *upper-clipped median*: the median of the segment, then
//!    repeatedly the median of the samples not above `median + 3 × 1.4826 × MAD` (at most
//!    [`CLIP_ITERATIONS`] rounds). Returns are positive-going, so clipping only the upper side
//!    strips them while leaving the symmetric noise around the floor, whose median is unbiased
//!    (a plain "median of the lower half" would sit half a noise amplitude below the floor).
//!    Counts spanning at most [`HISTOGRAM_RANGE`] values (and no more than eight per sample)
//!    get the clipped median from a histogram, in O(n + range) per round, other segments from
//!    a sorted copy; both give the same value bit for bit (integer counts, integer or
//!    half-integer medians and deviations are exact in `f32`).
//! 2. **Counts to volts** (`offset_v + gain × counts`); with [`DenoiseConfig::level_shift`] the
//!    baseline is subtracted *before* the FFT (the seed's level shift).
//! 3. **Low-pass**: the segment is zero-padded to twice its length (so the FFT's circular
//!    convolution does not wrap the end of the record onto its start), transformed with a real
//!    FFT, every bin with frequency `k / (m × sample_ns)` GHz above the cut-off is zeroed
//!    (`m` = padded length), transformed back and normalised by `m`. The real FFTs are
//!    `realfft`'s even-length algorithm (a complex FFT of the `m/2` packed sample pairs and a
//!    twiddle pass over the bin pairs), with its two twiddle passes and the zeroing fused into
//!    one pass here; the result is bit for bit the same. The zero padding is what
//!    makes the level shift matter, exactly as in the seed: the recording's on/off edge is a
//!    step from the pedestal to zero that rings (Gibbs) unless the pedestal was removed first.
//!    With `filter = "fir"` the low-pass is instead a symmetric (zero-phase) Kaiser-windowed
//!    sinc, −6 dB at the cut-off, ≥ 50 dB down beyond a transition band of full width
//!    `0.45 × min(fc, 0.5 − fc)` cycles per sample centred on it (35 taps at 0.2 GHz and
//!    1 ns), designed once per sample interval and convolved directly with the segment
//!    extended by zeros (the same edge convention as the zero-padded FFT, hence the same role
//!    of the level shift). It keeps the noise level's meaning (white noise keeps the fraction
//!    `2·fc` of its power, as behind the brick wall) and costs less than the FFT path (about
//!    40 % of it before the FFT's twiddle passes were fused, about half to three quarters
//!    since: bench `denoise_fir_outgoing64_return256_1ns`, 2026-11-25), but it is not the
//!    same filter: its transition band attenuates 0.155–0.2 GHz and leaks
//!    0.2–0.245 GHz. Measured with `fwlidar tradeoff` it moves true detections by up to −2.4 %
//!    (denoise only, extended 16 ns), so the FFT stays the default.
//! 4. Without the level shift the baseline is subtracted *after* filtering, so
//!    [`Pulse::signal`] is always in volts above the noise floor.
//! 5. **Noise figures** ([`Pulse::noise`]): `baseline_v` is the baseline of the return segments
//!    (their sample-weighted mean; the outgoing segment's when the pulse has no return samples),
//!    `noise_v` the mean of `|raw − baseline − smoothed|` over all return samples, in volts.
//!    This is the seed's noise level; it measures the part of the noise above the cut-off only
//!    (for white noise of standard deviation σ and cut-off fc below Nyquist fN it is about
//!    `sqrt(2/π) × σ × sqrt(1 − fc/fN)`). When the input states its noise
//!    ([`Pulse::stated_noise`], GEDI), `noise_v` is that formula applied to the stated σ
//!    instead: GEDI's received noise is band-limited before it is digitised (neighbouring
//!    samples are correlated), so the part above the cut-off is almost nothing (0.02-0.03
//!    counts for a stated σ of 3 counts) and every threshold in noise levels downstream
//!    (decomposition, the deconvolution gate) would take noise for echoes.
//!
//! Pulses the stage cannot use are dropped with a counted reason:
//! `no_segments` (dropped), `segment_too_long` (dropped: longer than
//! [`DenoiseConfig::max_samples`]), `cutoff_above_nyquist` (dropped: the pulse's sample interval
//! puts the Nyquist frequency at or below the cut-off, so the filter would be the identity; a
//! configuration/sensor mismatch, not bad data), `bad_digitizer_parameters` (rejected: a
//! non-finite gain or offset, or a non-finite or non-positive sample interval) and
//! `segment_out_of_bounds` (rejected: a segment indexes past the raw samples).
//! A cut-off that is not a positive finite number makes every pulse meaningless: the pipeline
//! refuses such a configuration when it is loaded, and [`Denoise::try_new`] (what the stage,
//! `stages/denoise.rs`, builds with) refuses it; [`Denoise::new`] takes a configuration the
//! caller has checked.
//!
//! Work per pulse is bounded (two FFTs of twice the segment length, or one FIR of at most
//! `2 × MAX_FIR_HALF + 1` taps, a sort of at most `max_samples` counts or a histogram of at
//! most [`HISTOGRAM_RANGE`] bins, and a fixed number of clipping rounds per segment) and, after the first
//! pulse of each segment length, does not allocate: FFT plans are cached by length and every
//! buffer is a field sized from `max_samples` when the stage is built (the FIR's taps too,
//! redesigned in place when the sample interval changes).

use std::sync::Arc;

use realfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};
use serde::{Deserialize, Serialize};

use crate::pulse::{Pulse, SegmentKind, Verdict};
use crate::signal::deconvolve::direct::convolve_padded;

/// Maximum number of upper-clipping rounds of the robust baseline estimate.
pub const CLIP_ITERATIONS: usize = 5;

/// Largest value range (`max − min + 1` counts) of a segment whose upper-clipped median is taken
/// from a histogram of its counts instead of a sorted copy (the same result: see
/// [`clipped_median_histogram`]).
pub const HISTOGRAM_RANGE: usize = 4096;

/// Clipping threshold of the robust baseline estimate, in robust standard deviations
/// (1.4826 × MAD).
pub(crate) const CLIP_SIGMAS: f32 = 3.0;

/// Scale from the median absolute deviation to the standard deviation of a normal distribution.
pub(crate) const MAD_TO_SIGMA: f32 = 1.4826;

/// Largest half-length of the FIR low-pass, taps (the filter has at most `2 × 128 + 1` taps).
pub const MAX_FIR_HALF: usize = 128;

/// Stop-band attenuation the FIR is designed for, dB (Kaiser's formulas).
const FIR_ATTENUATION_DB: f64 = 50.0;

/// Full width of the FIR's transition band as a fraction of the distance from the cut-off to
/// the nearer of 0 and the Nyquist frequency (centred on the cut-off).
const FIR_TRANSITION: f64 = 0.45;

/// Errors of the denoise configuration.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DenoiseError {
    /// The cut-off frequency is zero, negative or not a number.
    #[error("cutoff_ghz must be a positive finite frequency in GHz, got {cutoff_ghz}")]
    NonPositiveCutoff {
        /// The configured cut-off, GHz.
        cutoff_ghz: f64,
    },
    /// [`Denoise::denoise_segment`] was given a segment it cannot filter.
    #[error("cannot denoise segment: {reason}")]
    BadSegment {
        /// What is wrong (length, sample interval, non-finite sample, cut-off above Nyquist).
        reason: String,
    },
}

/// Configuration of the denoise stage (`type = "denoise"` in `[[pipeline.stages]]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DenoiseConfig {
    /// Low-pass cut-off frequency, GHz. Components above it are zeroed. Must lie below the
    /// Nyquist frequency 1 / (2 × sample interval). Default 0.2 (the seed's, at 1 ns sampling).
    #[serde(default = "default_cutoff_ghz")]
    pub cutoff_ghz: f64,
    /// Number of leading samples of each segment taken as pre-trigger noise for the baseline
    /// estimate when the segment is long enough; otherwise robust statistics of the whole
    /// segment are used. Default 8.
    #[serde(default = "default_pretrigger_samples")]
    pub pretrigger_samples: usize,
    /// Apply the seed's level shift: subtract the baseline before the FFT so the on/off edge of
    /// the recording does not leak into high frequencies. Default true.
    #[serde(default = "yes")]
    pub level_shift: bool,
    /// Longest segment the stage accepts, samples; FFT plans and buffers are sized for it once.
    /// Longer segments drop the pulse with reason `segment_too_long`. Default 4096.
    #[serde(default = "default_max_samples")]
    pub max_samples: usize,
    /// How the low-pass is applied: `"fft"` (the seed's zero-padded FFT with every bin above
    /// the cut-off zeroed; the default) or `"fir"` (a 35-tap Kaiser-windowed sinc at 0.2 GHz
    /// and 1 ns, designed once per sample interval and convolved in the time domain: about
    /// 1.5–2 × cheaper, but not the same filter). See the module documentation.
    #[serde(default)]
    pub filter: LowPass,
}

/// The low-pass implementation of the denoise stage (`filter = "fir"` or `"fft"`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LowPass {
    /// Kaiser-windowed sinc FIR, cut-off (−6 dB) at `cutoff_ghz`, at most
    /// `2 × MAX_FIR_HALF + 1` taps, convolved directly with the zero-extended segment.
    Fir,
    /// The seed's FFT brick wall: zero-padded to twice the segment, bins above the cut-off
    /// zeroed. The default.
    #[default]
    Fft,
}

fn default_cutoff_ghz() -> f64 {
    0.2
}
fn default_pretrigger_samples() -> usize {
    8
}
fn yes() -> bool {
    true
}
fn default_max_samples() -> usize {
    4096
}

impl Default for DenoiseConfig {
    fn default() -> Self {
        DenoiseConfig {
            cutoff_ghz: default_cutoff_ghz(),
            pretrigger_samples: default_pretrigger_samples(),
            level_shift: true,
            max_samples: default_max_samples(),
            filter: LowPass::default(),
        }
    }
}

impl DenoiseConfig {
    /// Checks what can be checked without a pulse: the cut-off must be a positive finite
    /// frequency. (Whether it lies below a pulse's Nyquist frequency depends on the pulse's
    /// sample interval and is checked per pulse.)
    pub fn validate(&self) -> Result<(), DenoiseError> {
        if self.cutoff_ghz.is_finite() && self.cutoff_ghz > 0.0 {
            Ok(())
        } else {
            Err(DenoiseError::NonPositiveCutoff {
                cutoff_ghz: self.cutoff_ghz,
            })
        }
    }
}

/// The real FFT pair (forward and inverse) planned for one padded length `m`, as the classic
/// even-length real FFT: the `m` real samples packed pairwise into `m / 2` complex values, a
/// complex FFT of that length, and a twiddle pass over the bin pairs `(k, m/2 − k)` that turns
/// the packed transform into the real signal's spectrum (forward) or back (inverse). The
/// twiddles and the order of every operation are those of `realfft` 3.5 (`RealToComplexEven`
/// and `ComplexToRealEven`), so the results are bit for bit what `realfft` gives (checked by
/// a test); owning the twiddle pass lets the stage fuse forward post-processing, brick wall and
/// inverse pre-processing into one vectorisable pass ([`brick_wall_packed`]).
struct Plan {
    /// Real length of the transform (twice the segment length), samples.
    len: usize,
    /// Complex FFTs of `len / 2` points.
    forward: Arc<dyn Fft<f32>>,
    inverse: Arc<dyn Fft<f32>>,
    /// Scratch length needed by either direction (out of place), complex values.
    scratch_len: usize,
    /// Twiddles of the bin pair `(k, len/2 − k)` at index `k − 1`, `k = 1 ..= (len/2 − 1)/2`.
    twiddles: PairTwiddles,
}

/// Twiddles of the real-FFT pair passes, structure of arrays (index `k − 1` for bin pair
/// `(k, m/2 − k)`, `m` the real length): `w_k = exp(−2πi·k/m)` rounded to `f32`, halved for
/// the forward pass, conjugated for the inverse pass (as `realfft` computes them).
struct PairTwiddles {
    fwd_re: Vec<f32>,
    fwd_im: Vec<f32>,
    inv_re: Vec<f32>,
    inv_im: Vec<f32>,
}

impl PairTwiddles {
    fn new(m: usize) -> Self {
        let pairs = (m / 2).saturating_sub(1) / 2;
        let w = |k: usize| {
            let angle = -2.0 * std::f64::consts::PI / m as f64 * k as f64;
            (angle.cos() as f32, angle.sin() as f32)
        };
        let (mut t, k) = (
            PairTwiddles {
                fwd_re: Vec::with_capacity(pairs),
                fwd_im: Vec::with_capacity(pairs),
                inv_re: Vec::with_capacity(pairs),
                inv_im: Vec::with_capacity(pairs),
            },
            1..=pairs,
        );
        for (re, im) in k.map(w) {
            t.fwd_re.push(re * 0.5);
            t.fwd_im.push(im * 0.5);
            t.inv_re.push(re);
            t.inv_im.push(-im);
        }
        t
    }
}

/// Baseline and noise sums of one filtered segment.
struct SegmentResult {
    /// Baseline, volts.
    baseline_v: f32,
    /// Sum of |raw − baseline − smoothed| over the segment, volts.
    abs_residual_sum_v: f64,
}

/// The denoise stage.
pub struct Denoise {
    config: DenoiseConfig,
    planner: FftPlanner<f32>,
    /// Plans cached by padded length (few distinct lengths per sensor: a linear search).
    plans: Vec<Plan>,
    /// Time-domain work buffer, `2 × max_samples` values (segment plus zero padding), volts.
    time: Vec<f32>,
    /// Spectrum work buffer, `max_samples + 1` bins (the packed complex FFT's output, then the
    /// inverse's prepared input).
    spectrum: Vec<Complex<f32>>,
    /// FFT scratch, grown (only) when a newly planned length needs more.
    scratch: Vec<Complex<f32>>,
    /// Sorted copy of a segment's counts for the baseline, `max_samples` values.
    sorted: Vec<u16>,
    /// Absolute deviations for the MAD, `max_samples` values, counts.
    deviations: Vec<f32>,
    /// Histogram of a segment's counts for the upper-clipped median, [`HISTOGRAM_RANGE`] bins.
    histogram: Vec<u32>,
    /// Sorted copy of a segment in volts for [`Denoise::denoise_segment`]; empty until its
    /// first call (the pipeline stage never needs it), then `max_samples` values.
    sorted_v: Vec<f32>,
    /// FIR taps (odd count, centre tap in the middle) for the sample interval `fir_sample_ns`;
    /// capacity `2 × MAX_FIR_HALF + 1`, redesigned (never grown) when the interval changes.
    fir: Vec<f32>,
    /// Sample interval the FIR was designed for, ns (NaN before the first design).
    fir_sample_ns: f64,
}

impl Denoise {
    /// Builds the denoiser and sizes its buffers once for [`DenoiseConfig::max_samples`], for
    /// a configuration the caller has checked ([`Denoise::try_new`] checks it).
    pub fn new(config: DenoiseConfig) -> Self {
        let max = config.max_samples;
        Denoise {
            planner: FftPlanner::new(),
            plans: Vec::with_capacity(8),
            // FFT: segment plus as many zeros; FIR: the filter's length of zeros on both sides.
            time: vec![0.0; (2 * max).max(max + 2 * (2 * MAX_FIR_HALF + 1))],
            spectrum: vec![Complex::new(0.0, 0.0); max + 1],
            scratch: vec![Complex::new(0.0, 0.0); 2 * max],
            sorted: vec![0; max],
            deviations: vec![0.0; max],
            histogram: vec![0; HISTOGRAM_RANGE],
            sorted_v: Vec::new(),
            fir: Vec::with_capacity(2 * MAX_FIR_HALF + 1),
            fir_sample_ns: f64::NAN,
            config,
        }
    }

    /// Builds the stage after [`DenoiseConfig::validate`].
    pub fn try_new(config: DenoiseConfig) -> Result<Self, DenoiseError> {
        config.validate()?;
        Ok(Denoise::new(config))
    }

    /// The configuration in force.
    pub fn config(&self) -> &DenoiseConfig {
        &self.config
    }

    /// Capacities of the internal buffers and the number of cached plans (for the no-allocation
    /// test).
    #[cfg(test)]
    fn buffer_capacities(&self) -> [usize; 8] {
        [
            self.histogram.capacity(),
            self.fir.capacity(),
            self.time.capacity(),
            self.spectrum.capacity(),
            self.scratch.capacity(),
            self.sorted.capacity(),
            self.deviations.capacity(),
            self.plans.capacity(),
        ]
    }

    /// Index of the plan for padded length `len`, planning it on first use.
    fn plan_index(&mut self, len: usize) -> usize {
        if let Some(i) = self.plans.iter().position(|p| p.len == len) {
            return i;
        }
        let forward = self.planner.plan_fft_forward(len / 2);
        let inverse = self.planner.plan_fft_inverse(len / 2);
        let scratch_len = forward
            .get_outofplace_scratch_len()
            .max(inverse.get_outofplace_scratch_len());
        if self.scratch.len() < scratch_len {
            self.scratch.resize(scratch_len, Complex::new(0.0, 0.0));
        }
        self.plans.push(Plan {
            len,
            forward,
            inverse,
            scratch_len,
            twiddles: PairTwiddles::new(len),
        });
        self.plans.len() - 1
    }

    /// Robust baseline of `counts` (non-empty, at most `max_samples` long), counts. The
    /// upper-clipped median comes from a histogram when the counts span at most
    /// [`HISTOGRAM_RANGE`] values and no more than eight per sample (otherwise sorting is
    /// cheaper); either way the result is the same.
    fn baseline_counts(&mut self, counts: &[u16]) -> f32 {
        let p = self.config.pretrigger_samples;
        let n = counts.len();
        if !(p > 0 && n >= p.saturating_mul(4)) {
            let (lo, hi) = counts
                .iter()
                .fold((u16::MAX, 0u16), |(lo, hi), &c| (lo.min(c), hi.max(c)));
            let range = (hi - lo) as usize + 1;
            if range <= HISTOGRAM_RANGE && range <= 8 * n {
                return clipped_median_histogram(counts, lo, &mut self.histogram[..range]);
            }
        }
        robust_baseline(
            counts,
            &mut self.sorted,
            &mut self.deviations,
            self.config.pretrigger_samples,
            <[u16]>::sort_unstable,
        )
    }

    /// Low-passes `self.time[..n]` into `out[..n]` (`self.time[n..2n]` must be zero): real
    /// FFT of the zero-padded `2n` samples, bins above the cut-off zeroed, inverse FFT and
    /// `1/(2n)` normalisation. `sample_ns` in ns. `self.time[..2n]` is overwritten.
    fn lowpass_time(&mut self, n: usize, sample_ns: f64, out: &mut [f32]) {
        let m = 2 * n;
        let plan_i = self.plan_index(m);
        let plan = &self.plans[plan_i];
        let packed = as_complex(&mut self.time[..m]);
        let bins = m / 2 + 1;
        let spectrum = &mut self.spectrum[..bins];
        let scratch = &mut self.scratch[..plan.scratch_len];
        plan.forward
            .process_outofplace_with_scratch(packed, &mut spectrum[..n], scratch);

        // Keep bin k while k / (m * sample_ns) <= cutoff_ghz.
        let keep = (self.config.cutoff_ghz * m as f64 * sample_ns).floor();
        let first_zeroed = if keep >= (bins - 1) as f64 {
            bins
        } else {
            keep as usize + 1
        };
        brick_wall_packed(spectrum, &plan.twiddles, first_zeroed);
        plan.inverse
            .process_outofplace_with_scratch(&mut spectrum[..n], packed, scratch);
        let scale = 1.0 / m as f32;
        for (o, &t) in out[..n].iter_mut().zip(&self.time[..n]) {
            *o = t * scale;
        }
    }

    /// Where the segment's samples go in `self.time` before [`Denoise::smooth`]: 0 for the
    /// FFT, the FIR's length (its zero padding) for the FIR, designing the FIR for `sample_ns`
    /// if needed.
    fn input_offset(&mut self, sample_ns: f64) -> usize {
        match self.config.filter {
            LowPass::Fft => 0,
            LowPass::Fir => {
                if self.fir_sample_ns != sample_ns {
                    design_fir(self.config.cutoff_ghz * sample_ns, &mut self.fir);
                    self.fir_sample_ns = sample_ns;
                }
                self.fir.len()
            }
        }
    }

    /// Low-passes the `n` samples placed at `self.time[offset..offset + n]` (offset from
    /// [`Denoise::input_offset`], same `sample_ns`) into `out[..n]`, the record taken as zero
    /// outside the segment (both implementations).
    fn smooth(&mut self, n: usize, sample_ns: f64, out: &mut [f32]) {
        match self.config.filter {
            LowPass::Fft => {
                self.time[n..2 * n].fill(0.0);
                self.lowpass_time(n, sample_ns, out);
            }
            LowPass::Fir => {
                let pad = self.fir.len();
                let half = pad / 2;
                let time = &mut self.time[..n + 2 * pad];
                time[..pad].fill(0.0);
                time[pad + n..].fill(0.0);
                convolve_padded(time, pad, &self.fir, half, &mut out[..n]);
            }
        }
    }

    /// Filters one non-empty segment of at most `max_samples` counts into `out` (same length,
    /// volts above the baseline). `gain` in V/DN, `offset` in V, `sample_ns` in ns. The
    /// residual sum is only computed with `residual` (return segments; 0 otherwise).
    fn filter_segment(
        &mut self,
        counts: &[u16],
        out: &mut [f32],
        gain: f32,
        offset: f32,
        sample_ns: f64,
        residual: bool,
    ) -> SegmentResult {
        let n = counts.len();
        let baseline_dn = self.baseline_counts(counts);
        let baseline_v = offset + gain * baseline_dn;
        let shift = if self.config.level_shift {
            baseline_v
        } else {
            0.0
        };
        let at = self.input_offset(sample_ns);
        for (t, &c) in self.time[at..at + n].iter_mut().zip(counts) {
            *t = offset + gain * c as f32 - shift;
        }
        self.smooth(n, sample_ns, out);

        let post_shift = baseline_v - shift;
        let mut abs_sum = 0.0f32;
        if residual {
            // A sequential f32 sum (its rounding is part of the output).
            for (o, &c) in out.iter_mut().zip(counts) {
                let smoothed = *o - post_shift;
                let raw = offset + gain * c as f32 - baseline_v;
                abs_sum += (raw - smoothed).abs();
                *o = smoothed;
            }
        } else {
            for o in out.iter_mut() {
                *o -= post_shift;
            }
        }
        let abs_sum = abs_sum as f64;
        SegmentResult {
            baseline_v,
            abs_residual_sum_v: abs_sum,
        }
    }

    /// Denoises one segment already in volts (or any signal unit: the output is in the unit of
    /// the input), outside the pipeline (`fwlidar process`): the same baseline estimate, level
    /// shift and low-pass as a pulse's segment, with `sample_ns` the sample interval in ns.
    /// Writes the smoothed samples above the baseline into `out` (same length as `volts`) and
    /// returns the segment's baseline and noise level (mean `|raw − baseline − smoothed|`), in
    /// the input's unit. An empty segment gives an empty output and a zero estimate.
    pub fn denoise_segment(
        &mut self,
        volts: &[f32],
        sample_ns: f64,
        out: &mut [f32],
    ) -> Result<crate::pulse::NoiseEstimate, DenoiseError> {
        self.config.validate()?;
        let bad = |reason: String| Err(DenoiseError::BadSegment { reason });
        let n = volts.len();
        if out.len() != n {
            return bad(format!(
                "output length {} differs from input length {n}",
                out.len()
            ));
        }
        if n > self.config.max_samples {
            return bad(format!(
                "{n} samples exceed the maximum of {}",
                self.config.max_samples
            ));
        }
        if !(sample_ns.is_finite() && sample_ns > 0.0) {
            return bad(format!(
                "sample interval {sample_ns} ns is not a positive number"
            ));
        }
        if self.config.cutoff_ghz * sample_ns >= 0.5 {
            return bad(format!(
                "cut-off {} GHz is not below the Nyquist frequency {} GHz",
                self.config.cutoff_ghz,
                0.5 / sample_ns
            ));
        }
        if let Some(i) = volts.iter().position(|v| !v.is_finite()) {
            return bad(format!("sample {i} is {}", volts[i]));
        }
        if n == 0 {
            return Ok(crate::pulse::NoiseEstimate::default());
        }
        if self.sorted_v.len() < self.config.max_samples {
            self.sorted_v.resize(self.config.max_samples, 0.0);
        }
        let baseline_v = robust_baseline(
            volts,
            &mut self.sorted_v,
            &mut self.deviations,
            self.config.pretrigger_samples,
            |s: &mut [f32]| s.sort_unstable_by(f32::total_cmp),
        );
        let shift = if self.config.level_shift {
            baseline_v
        } else {
            0.0
        };
        let at = self.input_offset(sample_ns);
        for (t, &v) in self.time[at..at + n].iter_mut().zip(volts) {
            *t = v - shift;
        }
        self.smooth(n, sample_ns, out);
        let post_shift = baseline_v - shift;
        let mut abs_sum = 0.0f32;
        for (o, &v) in out.iter_mut().zip(volts) {
            let smoothed = *o - post_shift;
            abs_sum += (v - baseline_v - smoothed).abs();
            *o = smoothed;
        }
        let abs_sum = abs_sum as f64;
        Ok(crate::pulse::NoiseEstimate {
            baseline_v,
            noise_v: (abs_sum / n as f64) as f32,
        })
    }
}

/// `values` (even length) as `values.len() / 2` complex values, pairs `(re, im)`.
fn as_complex(values: &mut [f32]) -> &mut [Complex<f32>] {
    assert!(values.len().is_multiple_of(2));
    // SAFETY: `Complex<f32>` is `#[repr(C)]` with fields `re, im`, the alignment of `f32`; the
    // new slice covers exactly the same memory and borrows it mutably for the same lifetime.
    unsafe {
        std::slice::from_raw_parts_mut(values.as_mut_ptr().cast::<Complex<f32>>(), values.len() / 2)
    }
}

/// Bin pairs of [`brick_wall_packed`] handled together (vectorised by the compiler).
const PAIR_LANES: usize = 8;

/// One pass over the spectrum of a packed real FFT of real length `m` (`spec` holds `m/2 + 1`
/// values, the first `m/2` being the complex FFT of the packed samples): the forward real-FFT
/// post-processing (the real signal's spectrum), every bin from `first_zeroed` on set to zero
/// (the brick wall), and the inverse real-FFT pre-processing, so that `spec[..m/2]` is ready
/// for the inverse complex FFT. Each bin pair `(k, m/2 − k)` goes through exactly the
/// operations of `realfft` 3.5's two passes (and a zeroed bin is a `+0` value, as after
/// `fill`), so the result is bit for bit that of the separate passes; fused, each value is
/// loaded and stored once and the pairs are processed [`PAIR_LANES`] at a time.
fn brick_wall_packed(spec: &mut [Complex<f32>], tw: &PairTwiddles, first_zeroed: usize) {
    let h = spec.len() - 1;
    let zero = Complex::new(0.0f32, 0.0);
    // DC and Nyquist bins (both real), from the packed DC value.
    let z0 = spec[0];
    let mut x0 = Complex::new(z0.re + z0.im, 0.0);
    let mut xh = Complex::new(z0.re - z0.im, 0.0);
    if first_zeroed == 0 {
        x0 = zero;
    }
    if h >= first_zeroed {
        xh = zero;
    }
    let sum = x0 + xh;
    let diff = x0 - xh;
    spec[0] = Complex::new(sum.re - sum.im, diff.re - diff.im);
    spec[h] = xh;
    let pairs = h.saturating_sub(1) / 2;
    let mut k = 1;
    while k + PAIR_LANES <= pairs + 1 {
        pair_block::<PAIR_LANES>(spec, tw, k, first_zeroed);
        k += PAIR_LANES;
    }
    while k <= pairs {
        pair_block::<1>(spec, tw, k, first_zeroed);
        k += 1;
    }
    if h.is_multiple_of(2) && h > 0 {
        // The centre bin pairs with itself.
        let c = h / 2;
        let mut x = Complex::new(spec[c].re, -spec[c].im);
        if c >= first_zeroed {
            x = zero;
        }
        let doubled = x + x;
        spec[c] = doubled.conj();
    }
}

/// The bin pairs `(k, h − k)` for `k` in `k0 .. k0 + L` of [`brick_wall_packed`] (`h` =
/// `spec.len() − 1`).
#[inline(always)]
fn pair_block<const L: usize>(
    spec: &mut [Complex<f32>],
    tw: &PairTwiddles,
    k0: usize,
    first_zeroed: usize,
) {
    let h = spec.len() - 1;
    let (mut ar, mut ai, mut br, mut bi) = ([0.0f32; L], [0.0f32; L], [0.0f32; L], [0.0f32; L]);
    // Low bins ascending, their partners descending.
    let lo = &spec[k0..k0 + L];
    let hi = &spec[h + 1 - k0 - L..=h - k0];
    for l in 0..L {
        ar[l] = lo[l].re;
        ai[l] = lo[l].im;
        br[l] = hi[L - 1 - l].re;
        bi[l] = hi[L - 1 - l].im;
    }
    let (fr, fi) = (
        &tw.fwd_re[k0 - 1..k0 - 1 + L],
        &tw.fwd_im[k0 - 1..k0 - 1 + L],
    );
    let (ir, ii) = (
        &tw.inv_re[k0 - 1..k0 - 1 + L],
        &tw.inv_im[k0 - 1..k0 - 1 + L],
    );
    for l in 0..L {
        let k = k0 + l;
        // Forward post-processing (realfft RealToComplexEven).
        let (sum_re, sum_im) = (ar[l] + br[l], ai[l] + bi[l]);
        let (diff_re, diff_im) = (ar[l] - br[l], ai[l] - bi[l]);
        let half_sum_re = 0.5 * sum_re;
        let half_diff_im = 0.5 * diff_im;
        let out_re = sum_im * fr[l] + diff_re * fi[l];
        let out_im = sum_im * fi[l] - diff_re * fr[l];
        let (mut xk_re, mut xk_im) = (half_sum_re + out_re, half_diff_im + out_im);
        let (mut xj_re, mut xj_im) = (half_sum_re - out_re, out_im - half_diff_im);
        // Brick wall.
        if k >= first_zeroed {
            (xk_re, xk_im) = (0.0, 0.0);
        }
        if h - k >= first_zeroed {
            (xj_re, xj_im) = (0.0, 0.0);
        }
        // Inverse pre-processing (realfft ComplexToRealEven).
        let (sum_re, sum_im) = (xk_re + xj_re, xk_im + xj_im);
        let (diff_re, diff_im) = (xk_re - xj_re, xk_im - xj_im);
        let out_re = sum_im * ir[l] + diff_re * ii[l];
        let out_im = sum_im * ii[l] - diff_re * ir[l];
        ar[l] = sum_re - out_re;
        ai[l] = diff_im - out_im;
        br[l] = sum_re + out_re;
        bi[l] = -out_im - diff_im;
    }
    let lo = &mut spec[k0..k0 + L];
    for l in 0..L {
        lo[l] = Complex::new(ar[l], ai[l]);
    }
    let hi = &mut spec[h + 1 - k0 - L..=h - k0];
    for l in 0..L {
        hi[L - 1 - l] = Complex::new(br[l], bi[l]);
    }
}

/// Designs the FIR low-pass for the cut-off `fc` in cycles per sample (`0 < fc < 0.5`) into
/// `taps` (cleared first; at most `2 × MAX_FIR_HALF + 1` taps, unit sum, symmetric, so zero
/// phase): the ideal low-pass `2·fc·sinc(2·fc·j)` times a Kaiser window designed (Kaiser's
/// formulas) for [`FIR_ATTENUATION_DB`] of stop-band attenuation over a transition band of
/// full width `Δf = FIR_TRANSITION × min(fc, 0.5 − fc)` centred on `fc`: the response is −6 dB
/// at the cut-off and the pass and stop bands mirror each other around it, so white noise
/// keeps the same fraction `2·fc` of its power as behind the brick wall. Half-length
/// `⌈(A − 8) / (2.285 · 2π · Δf) / 2⌉` (17 at 0.2 GHz and 1 ns: 35 taps), capped at
/// [`MAX_FIR_HALF`] (cut-offs below about 0.03 cycles per sample then get a wider transition).
fn design_fir(fc: f64, taps: &mut Vec<f32>) {
    let a = FIR_ATTENUATION_DB;
    let df = FIR_TRANSITION * fc.min(0.5 - fc);
    let order = (a - 8.0) / (2.285 * 2.0 * std::f64::consts::PI * df);
    let half = ((order / 2.0).ceil() as usize).clamp(1, MAX_FIR_HALF);
    let beta = if a > 50.0 {
        0.1102 * (a - 8.7)
    } else {
        0.5842 * (a - 21.0).powf(0.4) + 0.07886 * (a - 21.0)
    };
    let i0_beta = bessel_i0(beta);
    taps.clear();
    let mut sum = 0.0f64;
    let mut values = [0.0f64; 2 * MAX_FIR_HALF + 1];
    for (i, v) in values[..2 * half + 1].iter_mut().enumerate() {
        let j = i as f64 - half as f64;
        let x = 2.0 * fc * j;
        let sinc = if j == 0.0 {
            1.0
        } else {
            (std::f64::consts::PI * x).sin() / (std::f64::consts::PI * x)
        };
        let r = j / half as f64;
        let window = bessel_i0(beta * (1.0 - r * r).max(0.0).sqrt()) / i0_beta;
        *v = 2.0 * fc * sinc * window;
        sum += *v;
    }
    taps.extend(values[..2 * half + 1].iter().map(|v| (v / sum) as f32));
}

/// Modified Bessel function of the first kind, order 0 (power series; `x` up to ~20).
fn bessel_i0(x: f64) -> f64 {
    let q = 0.25 * x * x;
    let (mut term, mut sum) = (1.0f64, 1.0f64);
    for k in 1..64 {
        term *= q / (k * k) as f64;
        sum += term;
        if term < 1e-17 * sum {
            break;
        }
    }
    sum
}

/// Robust baseline of `values` (non-empty, at most `sorted.len()` long) in their own unit: the
/// median of the first `pretrigger` samples when there are at least four times that many,
/// otherwise the upper-clipped median described in the module documentation. `sort` sorts
/// ascending; `sorted` and `deviations` are work buffers.
fn robust_baseline<T: Copy + Into<f32>>(
    values: &[T],
    sorted: &mut [T],
    deviations: &mut [f32],
    pretrigger: usize,
    sort: impl Fn(&mut [T]),
) -> f32 {
    let p = pretrigger;
    if p > 0 && values.len() >= p.saturating_mul(4) {
        let s = &mut sorted[..p];
        s.copy_from_slice(&values[..p]);
        sort(s);
        return median_sorted(s);
    }
    let n = values.len();
    let s = &mut sorted[..n];
    s.copy_from_slice(values);
    sort(s);
    // The kept samples are always a prefix of the sorted values (upper clipping only).
    let mut kept = n;
    let mut median = median_sorted(&s[..kept]);
    for _ in 0..CLIP_ITERATIONS {
        let dev = &mut deviations[..kept];
        for (d, &c) in dev.iter_mut().zip(&s[..kept]) {
            *d = (c.into() - median).abs();
        }
        let mid = kept / 2;
        let (_, &mut mad, _) = dev.select_nth_unstable_by(mid, f32::total_cmp);
        let limit = median + CLIP_SIGMAS * MAD_TO_SIGMA * mad;
        let new_kept = s[..kept].partition_point(|&c| c.into() <= limit).max(1);
        if new_kept == kept {
            break;
        }
        kept = new_kept;
        median = median_sorted(&s[..kept]);
    }
    median
}

/// Level and noise standard deviation of a waveform whose signal may fill much of it (no
/// pre-trigger samples to trust): the upper-clipped median of the module documentation (samples
/// more than [`CLIP_SIGMAS`] robust deviations above the median dropped and the median taken
/// again, at most [`CLIP_ITERATIONS`] times) as the level, and 1.4826 × the median absolute
/// deviation of the kept samples from it as σ. The same estimate as [`robust_baseline`] by
/// selection instead of a sort (linear time per round). Both in the unit of `values`; `(NaN,
/// NaN)` when `values` is empty. `work` and `deviations` are work buffers, grown to
/// `values.len()` if shorter (no allocation once they are long enough).
pub fn robust_level_and_sigma(
    values: &[f32],
    work: &mut Vec<f32>,
    deviations: &mut Vec<f32>,
) -> (f32, f32) {
    let n = values.len();
    if n == 0 {
        return (f32::NAN, f32::NAN);
    }
    work.clear();
    work.extend_from_slice(values);
    if deviations.len() < n {
        deviations.resize(n, 0.0);
    }
    let median = median_in_place;
    let mut kept = n;
    let mut level = median(&mut work[..kept]);
    let mut mad;
    let mut rounds = 0;
    loop {
        let dev = &mut deviations[..kept];
        for (d, &v) in dev.iter_mut().zip(&work[..kept]) {
            *d = (v - level).abs();
        }
        let (_, &mut m, _) = dev.select_nth_unstable_by(kept / 2, f32::total_cmp);
        mad = m;
        if rounds == CLIP_ITERATIONS {
            break;
        }
        rounds += 1;
        let limit = level + CLIP_SIGMAS * MAD_TO_SIGMA * mad;
        // Keep the samples at or below the limit at the front, in place.
        let mut new_kept = 0;
        for i in 0..kept {
            if work[i] <= limit {
                work.swap(i, new_kept);
                new_kept += 1;
            }
        }
        let new_kept = new_kept.max(1);
        if new_kept == kept {
            break;
        }
        kept = new_kept;
        level = median(&mut work[..kept]);
    }
    (level, MAD_TO_SIGMA * mad)
}

/// The median of `v` (non-empty; reorders it): the middle value by selection, the mean of the
/// two middle values for an even count.
pub(crate) fn median_in_place(v: &mut [f32]) -> f32 {
    let (len, mid) = (v.len(), v.len() / 2);
    let (below, &mut m, _) = v.select_nth_unstable_by(mid, f32::total_cmp);
    if len % 2 == 1 {
        m
    } else {
        let lower = below.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        0.5 * (lower + m)
    }
}

/// The upper-clipped median of `counts` (non-empty, every count in `lo .. lo + hist.len()`)
/// as [`robust_baseline`] computes it from a sorted copy, from a histogram instead (`hist` is
/// the work buffer): the sorted copy is the histogram read in order, so the value of rank `r`
/// is the first bin whose cumulative count exceeds `r`; the kept samples (a prefix of the
/// sorted copy) are the histogram up to a bin, that bin possibly in part; the MAD (rank
/// `kept / 2` of the absolute deviations) is found by walking outwards from the median, the
/// nearer side first, since the deviations grow away from it on both sides. Counts, medians
/// (integers or halves) and deviations are exact in `f32`, and the limit is the same `f32`
/// expression, so the result is bit for bit the sort's. O(n + range) per round.
fn clipped_median_histogram(counts: &[u16], lo: u16, hist: &mut [u32]) -> f32 {
    hist.fill(0);
    for &c in counts {
        hist[(c - lo) as usize] += 1;
    }
    let value = |i: usize| (lo as usize + i) as f32;
    // Bin of the value of rank `r` among all the counts.
    let rank_bin = |hist: &[u32], r: usize| {
        let mut cum = 0usize;
        for (i, &h) in hist.iter().enumerate() {
            cum += h as usize;
            if cum > r {
                return i;
            }
        }
        hist.len() - 1
    };
    let median_of = |hist: &[u32], kept: usize| {
        if kept % 2 == 1 {
            value(rank_bin(hist, kept / 2))
        } else {
            0.5 * (value(rank_bin(hist, kept / 2 - 1)) + value(rank_bin(hist, kept / 2)))
        }
    };
    let mut kept = counts.len();
    let mut median = median_of(hist, kept);
    for _ in 0..CLIP_ITERATIONS {
        // The kept samples: bins below `last` whole, `last_count` of bin `last`.
        let last = rank_bin(hist, kept - 1);
        let last_count = kept - hist[..last].iter().map(|&h| h as usize).sum::<usize>();
        let eff = |i: usize| match i.cmp(&last) {
            std::cmp::Ordering::Less => hist[i] as usize,
            std::cmp::Ordering::Equal => last_count,
            std::cmp::Ordering::Greater => 0,
        };
        // Walk outwards from the median: `left` down from the last bin not above it, `right`
        // up from the next one, taking the smaller deviation first.
        let wanted = kept / 2;
        let mut left = Some((median - lo as f32).floor() as usize);
        let mut right = left.map_or(0, |l| l + 1);
        let mut seen = 0usize;
        let mad = loop {
            let dl = left.map(|l| (value(l) - median).abs());
            let dr = (right <= last).then(|| (value(right) - median).abs());
            let (d, count) = match (dl, dr) {
                (Some(a), Some(b)) if b < a => {
                    right += 1;
                    (b, eff(right - 1))
                }
                (Some(a), _) => {
                    let l = left.expect("some");
                    left = l.checked_sub(1);
                    (a, eff(l))
                }
                (None, Some(b)) => {
                    right += 1;
                    (b, eff(right - 1))
                }
                (None, None) => unreachable!("the kept samples hold rank kept / 2"),
            };
            seen += count;
            if seen > wanted {
                break d;
            }
        };
        let limit = median + CLIP_SIGMAS * MAD_TO_SIGMA * mad;
        let mut at_most = 0usize;
        for (i, &h) in hist.iter().enumerate() {
            if value(i) > limit {
                break;
            }
            at_most += h as usize;
        }
        let new_kept = at_most.min(kept).max(1);
        if new_kept == kept {
            break;
        }
        kept = new_kept;
        median = median_of(hist, kept);
    }
    median
}

/// Median of sorted values (mean of the two middle values for an even count).
fn median_sorted<T: Copy + Into<f32>>(s: &[T]) -> f32 {
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2].into()
    } else {
        0.5 * (s[n / 2 - 1].into() + s[n / 2].into())
    }
}

impl Denoise {
    /// Denoises every segment of `pulse` into [`Pulse::signal`] and sets [`Pulse::noise`]
    /// (see the module documentation); what the pipeline stage (`stages/denoise.rs`) does to
    /// each pulse. A pulse it cannot use is dropped or rejected with the reasons listed in the
    /// module documentation.
    pub fn denoise_pulse(&mut self, pulse: &mut Pulse) -> Verdict {
        if pulse.segments.is_empty() {
            return Verdict::Drop("no_segments");
        }
        let sample_ns = pulse.sample_ns;
        if !pulse.gain_v_per_dn.is_finite()
            || !pulse.offset_v.is_finite()
            || !sample_ns.is_finite()
            || sample_ns <= 0.0
        {
            return Verdict::Reject("bad_digitizer_parameters");
        }
        if self.config.cutoff_ghz * sample_ns >= 0.5 {
            return Verdict::Drop("cutoff_above_nyquist");
        }
        let n_raw = pulse.raw.len();
        if pulse
            .segments
            .iter()
            .any(|s| s.first as usize + s.len as usize > n_raw)
        {
            return Verdict::Reject("segment_out_of_bounds");
        }
        if pulse
            .segments
            .iter()
            .any(|s| s.len as usize > self.config.max_samples)
        {
            return Verdict::Drop("segment_too_long");
        }
        let gain = pulse.gain_v_per_dn;
        let offset = pulse.offset_v;
        let p = pulse;
        p.signal.clear();
        p.signal.resize(n_raw, 0.0);
        let mut return_samples = 0usize;
        let mut return_baseline_sum = 0.0f64;
        let mut return_abs_sum = 0.0f64;
        let mut outgoing_baseline = None;
        for seg in &p.segments {
            if seg.len == 0 {
                continue;
            }
            let r = seg.range();
            let res = self.filter_segment(
                &p.raw[r.clone()],
                &mut p.signal[r],
                gain,
                offset,
                sample_ns,
                seg.kind == SegmentKind::Return,
            );
            match seg.kind {
                SegmentKind::Return => {
                    return_samples += seg.len as usize;
                    return_baseline_sum += res.baseline_v as f64 * seg.len as f64;
                    return_abs_sum += res.abs_residual_sum_v;
                }
                SegmentKind::Outgoing => {
                    outgoing_baseline.get_or_insert(res.baseline_v);
                }
            }
        }
        p.noise = if return_samples > 0 {
            let measured = (return_abs_sum / return_samples as f64) as f32;
            crate::pulse::NoiseEstimate {
                baseline_v: (return_baseline_sum / return_samples as f64) as f32,
                noise_v: p
                    .stated_noise
                    .and_then(|n| stated_noise_level(n.stddev, self.config.cutoff_ghz, sample_ns))
                    .unwrap_or(measured),
            }
        } else {
            crate::pulse::NoiseEstimate {
                baseline_v: outgoing_baseline.unwrap_or(0.0),
                noise_v: 0.0,
            }
        };
        Verdict::DONE
    }
}

/// The noise level `noise_v` that the estimate gives on white noise of standard deviation
/// `sigma` (signal units) behind a cut-off of `cutoff_ghz` at `sample_ns`:
/// `sqrt(2/π) × σ × sqrt(1 − 2·fc·Δt)`. `None` unless `sigma` is a positive finite number.
fn stated_noise_level(sigma: f32, cutoff_ghz: f64, sample_ns: f64) -> Option<f32> {
    let kept_above = (1.0 - 2.0 * cutoff_ghz * sample_ns).max(0.0);
    (sigma.is_finite() && sigma > 0.0).then(|| {
        (f64::from(sigma) * (2.0 / std::f64::consts::PI).sqrt() * kept_above.sqrt()) as f32
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::testing::apply;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A pulse with one return segment holding `values` (counts, rounded and clamped to u16).
    fn pulse_with_return(values: &[f64]) -> Pulse {
        let mut p = Pulse::default();
        p.push_segment(
            SegmentKind::Return,
            0,
            0.0,
            values.iter().map(|v| v.round().clamp(0.0, 65535.0) as u16),
        );
        p
    }

    /// The low-pass as the stage computed it through `realfft` (before the fused twiddle
    /// pass): `x` zero-padded to `2n`, real FFT, bins from the first above `cutoff_ghz`
    /// zeroed, inverse real FFT, `1/(2n)`.
    fn lowpass_realfft(x: &[f32], cutoff_ghz: f64, sample_ns: f64) -> Vec<f32> {
        use realfft::RealFftPlanner;
        let n = x.len();
        let m = 2 * n;
        let mut planner = RealFftPlanner::<f32>::new();
        let forward = planner.plan_fft_forward(m);
        let inverse = planner.plan_fft_inverse(m);
        let mut time = vec![0.0f32; m];
        time[..n].copy_from_slice(x);
        let mut spectrum = forward.make_output_vec();
        forward.process(&mut time, &mut spectrum).unwrap();
        let bins = n + 1;
        let keep = (cutoff_ghz * m as f64 * sample_ns).floor();
        let first_zeroed = if keep >= (bins - 1) as f64 {
            bins
        } else {
            keep as usize + 1
        };
        spectrum[first_zeroed..].fill(Complex::new(0.0, 0.0));
        spectrum[0].im = 0.0;
        spectrum[bins - 1].im = 0.0;
        inverse.process(&mut spectrum, &mut time).unwrap();
        let scale = 1.0 / m as f32;
        time[..n].iter().map(|&t| t * scale).collect()
    }

    /// The stage's FFT low-pass of `x` (through a stage built for `cutoff_ghz`).
    fn lowpass_stage(stage: &mut Denoise, x: &[f32], sample_ns: f64) -> Vec<f32> {
        let n = x.len();
        stage.time[..n].copy_from_slice(x);
        let mut out = vec![f32::NAN; n];
        stage.smooth(n, sample_ns, &mut out);
        out
    }

    fn assert_bits_equal(a: &[f32], b: &[f32], what: &str) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert_eq!(x.to_bits(), y.to_bits(), "{what}: sample {i}: {x} vs {y}");
        }
    }

    #[test]
    fn fused_fft_low_pass_is_bit_for_bit_the_realfft_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(41);
        // (cut-off GHz, sample interval ns): the survey line's, near Nyquist, low, coarser.
        let settings = [(0.2, 1.0), (0.49, 1.0), (0.03, 1.0), (0.1, 2.0), (0.5, 0.5)];
        let mut lengths: Vec<usize> = (1..=300).collect();
        lengths.extend([34, 256, 383, 512, 1000, 1023, 2048, 4096]);
        for &(cutoff_ghz, sample_ns) in &settings {
            let mut stage = Denoise::new(DenoiseConfig {
                cutoff_ghz,
                ..Default::default()
            });
            for &n in &lengths {
                for kind in 0..4 {
                    let x: Vec<f32> = (0..n)
                        .map(|i| match kind {
                            // Level-shifted digitizer noise with a return.
                            0 => {
                                let d = (i as f32 - n as f32 / 3.0) / 3.0;
                                0.004 * (rng.random_range(-3i32..=3) as f32)
                                    + 0.5 * (-0.5 * d * d).exp()
                            }
                            // Wide-range values.
                            1 => rng.random_range(-1e4f32..1e4),
                            // A constant (the pedestal without the level shift).
                            2 => 30.0,
                            // Steps and zeros.
                            _ => [0.0, -0.0, 1.0, 65535.0][rng.random_range(0..4usize)],
                        })
                        .collect();
                    let want = lowpass_realfft(&x, cutoff_ghz, sample_ns);
                    let got = lowpass_stage(&mut stage, &x, sample_ns);
                    assert_bits_equal(
                        &got,
                        &want,
                        &format!("n {n}, kind {kind}, {cutoff_ghz} GHz, {sample_ns} ns"),
                    );
                }
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        #[test]
        fn fused_fft_low_pass_matches_realfft_on_any_segment(
            x in proptest::collection::vec(-70000.0f32..70000.0, 1..700),
            cutoff_ghz in 0.001f64..0.499,
        ) {
            let mut stage = Denoise::new(DenoiseConfig { cutoff_ghz, ..Default::default() });
            let want = lowpass_realfft(&x, cutoff_ghz, 1.0);
            let got = lowpass_stage(&mut stage, &x, 1.0);
            for (a, b) in got.iter().zip(&want) {
                proptest::prop_assert_eq!(a.to_bits(), b.to_bits());
            }
        }
    }

    /// The selection-based level and σ equal the sort-based upper-clipped median on the same
    /// samples, and stay at the noise's when an echo fills half the window (grass under a short
    /// window), where the plain median and MAD of the window do not.
    #[test]
    fn robust_level_and_sigma_ignores_an_echo_filling_half_the_window() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (mut work, mut dev) = (Vec::new(), Vec::new());
        let mut plain_fails = 0;
        for trial in 0..50 {
            let n = 32 + trial * 7;
            let counts: Vec<u16> = (0..n)
                .map(|i| {
                    let noise = rng.random_range(-3i32..=3);
                    let u = (i as f64 - n as f64 / 2.0) / (n as f64 / 12.0);
                    (12 + noise + (70.0 * (-0.5 * u * u).exp()) as i32) as u16
                })
                .collect();
            let volts: Vec<f32> = counts.iter().map(|&c| f32::from(c)).collect();
            let (level, sigma) = robust_level_and_sigma(&volts, &mut work, &mut dev);
            assert_eq!(level, baseline_by_sorting(&counts, 0), "trial {trial}");
            // Uniform integers −3…3 around 12: σ 2 (the MAD's 1.48 × 2 = 3 on so few values).
            assert!(
                (10.0..=14.0).contains(&level),
                "trial {trial}: level {level}"
            );
            assert!((0.7..=4.5).contains(&sigma), "trial {trial}: σ {sigma}");
            // The window's plain median and MAD (no clipping) would put σ above the bar.
            let mut v = volts.clone();
            v.sort_by(f32::total_cmp);
            let med = v[n / 2];
            let mut d: Vec<f32> = v.iter().map(|x| (x - med).abs()).collect();
            d.sort_by(f32::total_cmp);
            plain_fails += usize::from(1.4826 * d[n / 2] > 4.5);
        }
        assert!(plain_fails >= 40, "only {plain_fails} of 50 windows hard");
        assert!(robust_level_and_sigma(&[], &mut work, &mut dev).0.is_nan());
    }

    /// The sort-based robust baseline of `counts` (the reference).
    fn baseline_by_sorting(counts: &[u16], pretrigger: usize) -> f32 {
        let mut sorted = vec![0u16; counts.len()];
        let mut deviations = vec![0.0f32; counts.len()];
        robust_baseline(
            counts,
            &mut sorted,
            &mut deviations,
            pretrigger,
            <[u16]>::sort_unstable,
        )
    }

    #[test]
    fn histogram_baseline_is_bit_for_bit_the_sorted_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(43);
        let mut stages: Vec<Denoise> = [0usize, 1, 8, 100_000]
            .iter()
            .map(|&pretrigger_samples| {
                Denoise::new(DenoiseConfig {
                    pretrigger_samples,
                    ..Default::default()
                })
            })
            .collect();
        let mut cases: Vec<Vec<u16>> = Vec::new();
        // Up to 300 samples, and long enough for a 4096-count span to use the histogram.
        for n in (1..=300usize).chain([512, 513, 1000, 4096]) {
            // 8-bit digitizer noise on a pedestal, with and without returns.
            let noise: Vec<u16> = (0..n).map(|_| rng.random_range(9u16..=15)).collect();
            let mut with_returns = noise.clone();
            for _ in 0..rng.random_range(0..4usize) {
                let at = rng.random_range(0..n);
                let a = rng.random_range(5.0..250.0f64);
                for (i, v) in with_returns.iter_mut().enumerate() {
                    let d = (i as f64 - at as f64) / 3.0;
                    *v = (*v as f64 + a * (-0.5 * d * d).exp()).min(255.0) as u16;
                }
            }
            cases.push(noise);
            cases.push(with_returns);
            cases.push(vec![rng.random_range(0..=u16::MAX); n]); // all equal
            cases.push(
                (0..n)
                    .map(|_| [7u16, 8][rng.random_range(0..2usize)])
                    .collect(),
            );
            // Wide ranges: the sort fallback, and either side of the histogram's limit.
            cases.push((0..n).map(|_| rng.random_range(0..=u16::MAX)).collect());
            for span in [4095u16, 4096] {
                let mut v: Vec<u16> = (0..n).map(|_| 60000 + rng.random_range(0..=20)).collect();
                v[0] = 60000;
                if n > 1 {
                    v[n - 1] = 60000 + span - 1;
                }
                cases.push(v);
            }
            // Saturated returns and extremes.
            cases.push(
                (0..n)
                    .map(|i| if i % 5 == 0 { u16::MAX } else { 3 })
                    .collect(),
            );
            cases.push((0..n).map(|i| (i % 2) as u16 * u16::MAX).collect());
        }
        for counts in &cases {
            for stage in stages.iter_mut() {
                let p = stage.config.pretrigger_samples;
                let want = baseline_by_sorting(counts, p);
                let got = stage.baseline_counts(counts);
                assert_eq!(
                    got.to_bits(),
                    want.to_bits(),
                    "pretrigger {p}, counts {counts:?}: {got} vs {want}"
                );
            }
        }
    }

    fn denoise_one(config: DenoiseConfig, pulse: Pulse) -> Box<Pulse> {
        let mut stage = Denoise::new(config);
        let mut run = apply([pulse], |p| stage.denoise_pulse(p));
        assert_eq!(run.emitted.len(), 1, "dropped: {:?}", run.dropped);
        run.emitted.pop().unwrap()
    }

    /// Amplitude of a sinusoid of `period` samples fitted over `y[range]` (the range must hold a
    /// whole number of periods), by projection after removing the mean.
    fn sine_amplitude(y: &[f32], range: std::ops::Range<usize>, period: f64) -> f64 {
        let n = range.len() as f64;
        let mean = y[range.clone()].iter().map(|&v| v as f64).sum::<f64>() / n;
        let (mut s, mut c) = (0.0, 0.0);
        for i in range {
            let ph = 2.0 * std::f64::consts::PI * i as f64 / period;
            s += (y[i] as f64 - mean) * ph.sin();
            c += (y[i] as f64 - mean) * ph.cos();
        }
        2.0 / n * s.hypot(c)
    }

    fn sine(n: usize, period: f64, amplitude: f64, dc: f64) -> Vec<f64> {
        (0..n)
            .map(|i| dc + amplitude * (2.0 * std::f64::consts::PI * i as f64 / period).sin())
            .collect()
    }

    #[test]
    fn sinusoid_below_cutoff_passes_with_its_amplitude() {
        // 0.05 GHz at 1 ns: period 20 samples, well inside the 0.2 GHz pass band.
        let out = denoise_one(
            DenoiseConfig::default(),
            pulse_with_return(&sine(1024, 20.0, 1000.0, 2000.0)),
        );
        let a = sine_amplitude(&out.signal, 256..756, 20.0);
        assert!((a / 1000.0 - 1.0).abs() < 0.01, "amplitude {a}");
    }

    #[test]
    fn sinusoid_above_cutoff_is_removed() {
        // 0.3 GHz at 1 ns: period 10/3 samples, above the 0.2 GHz cut-off.
        let out = denoise_one(
            DenoiseConfig::default(),
            pulse_with_return(&sine(1024, 10.0 / 3.0, 1000.0, 2000.0)),
        );
        let a = sine_amplitude(&out.signal, 256..756, 10.0 / 3.0);
        assert!(a < 10.0, "residual amplitude {a} of 1000");
        let mean = out.signal[256..756].iter().sum::<f32>() / 500.0;
        let max_dev = out.signal[256..756]
            .iter()
            .map(|v| (v - mean).abs())
            .fold(0.0, f32::max);
        assert!(max_dev < 10.0, "residual {max_dev} of 1000");
    }

    #[test]
    fn white_noise_is_reduced_by_the_square_root_of_the_kept_band() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let values: Vec<f64> = (0..4096)
            .map(|_| 1000.0 + rng.random_range(-100.0..=100.0))
            .collect();
        let out = denoise_one(DenoiseConfig::default(), pulse_with_return(&values));
        let std = |v: &mut dyn Iterator<Item = f64>| {
            let v: Vec<f64> = v.collect();
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
        };
        let before = std(&mut values[512..3584].iter().copied());
        let after = std(&mut out.signal[512..3584].iter().map(|&v| v as f64));
        let ratio = after / before;
        let expected = (0.2f64 / 0.5).sqrt();
        assert!(
            (ratio - expected).abs() < 0.06,
            "ratio {ratio}, expected about {expected}"
        );
    }

    /// Peak position of `y`, samples: the vertex of the parabola through the logarithms of the
    /// largest sample and its neighbours (exact for a sampled Gaussian).
    fn gaussian_peak<T: Copy + Into<f64>>(y: &[T]) -> f64 {
        let k = (1..y.len() - 1)
            .max_by(|&a, &b| y[a].into().total_cmp(&y[b].into()))
            .unwrap();
        let (l, c, r) = (y[k - 1].into().ln(), y[k].into().ln(), y[k + 1].into().ln());
        k as f64 + 0.5 * (l - r) / (l - 2.0 * c + r)
    }

    #[test]
    fn gaussian_return_keeps_its_position() {
        for &(mu, sigma) in &[(100.0, 2.0), (100.25, 2.0), (100.5, 1.5), (120.8, 3.0)] {
            let clean: Vec<f64> = (0..256)
                .map(|i| {
                    let d = (i as f64 - mu) / sigma;
                    3000.0 * (-0.5 * d * d).exp()
                })
                .collect();
            let values: Vec<f64> = clean.iter().map(|v| v + 500.0).collect();
            let out = denoise_one(DenoiseConfig::default(), pulse_with_return(&values));
            let before = gaussian_peak(&clean);
            let after = gaussian_peak(&out.signal);
            assert!(
                (after - before).abs() < 0.05,
                "centre {mu}, sigma {sigma}: peak {before} before, {after} after filtering"
            );
        }
    }

    fn gaussian_on_pedestal(
        rng: &mut ChaCha8Rng,
        n: usize,
        pedestal: f64,
        noise: f64,
        mu: f64,
        sigma: f64,
    ) -> Vec<f64> {
        (0..n)
            .map(|i| {
                let d = (i as f64 - mu) / sigma;
                pedestal + 500.0 * (-0.5 * d * d).exp() + rng.random_range(-noise..=noise)
            })
            .collect()
    }

    #[test]
    fn baseline_with_a_known_dc_offset_is_recovered() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (gain, offset) = (0.002f32, -0.1f32);
        let expected = offset + gain * 40.0;
        // Long segment: pre-trigger median of the first 8 samples.
        let mut p = pulse_with_return(&gaussian_on_pedestal(&mut rng, 256, 40.0, 5.0, 150.0, 4.0));
        p.gain_v_per_dn = gain;
        p.offset_v = offset;
        let out = denoise_one(DenoiseConfig::default(), p);
        assert!(
            (out.noise.baseline_v - expected).abs() < 3.0 * gain,
            "pre-trigger baseline {} V, expected {expected} V",
            out.noise.baseline_v
        );
        // No pre-trigger: upper-clipped median of the whole segment.
        let mut p = pulse_with_return(&gaussian_on_pedestal(&mut rng, 256, 40.0, 5.0, 150.0, 4.0));
        p.gain_v_per_dn = gain;
        p.offset_v = offset;
        let config = DenoiseConfig {
            pretrigger_samples: 0,
            ..Default::default()
        };
        let out = denoise_one(config, p);
        assert!(
            (out.noise.baseline_v - expected).abs() < 1.0 * gain,
            "robust baseline {} V, expected {expected} V",
            out.noise.baseline_v
        );
        // Short segment (< 4 x pre-trigger) with the return covering a third of it.
        let mut p = pulse_with_return(&gaussian_on_pedestal(&mut rng, 30, 40.0, 2.0, 15.0, 1.5));
        p.gain_v_per_dn = gain;
        p.offset_v = offset;
        let out = denoise_one(DenoiseConfig::default(), p);
        assert!(
            (out.noise.baseline_v - expected).abs() < 1.5 * gain,
            "short-segment baseline {} V, expected {expected} V",
            out.noise.baseline_v
        );
    }

    #[test]
    fn level_shift_removes_the_ringing_of_the_recording_edges() {
        let max_abs = |level_shift: bool| {
            let config = DenoiseConfig {
                level_shift,
                ..Default::default()
            };
            let out = denoise_one(config, pulse_with_return(&[30.0; 256]));
            assert_eq!(out.noise.baseline_v, 30.0);
            out.signal.iter().map(|v| v.abs()).fold(0.0, f32::max)
        };
        let on = max_abs(true);
        let off = max_abs(false);
        assert!(on < 1e-4, "constant input rings with the level shift: {on}");
        assert!(
            off > 1.0,
            "expected edge ringing without the level shift: {off}"
        );
        assert!(on < off / 1000.0);
    }

    #[test]
    fn noise_level_is_the_stated_noise_when_the_input_states_it() {
        // GEDI-like: noise smoothed before digitising (a 9-sample running mean of white noise),
        // so hardly any of it lies above the cut-off; 1/32 count per raw count.
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let white: Vec<f64> = (0..800).map(|_| rng.random_range(-1.0..=1.0)).collect();
        let values: Vec<f64> = (0..white.len() - 8)
            .map(|i| 32.0 * (240.0 + 9.0 * white[i..i + 9].iter().sum::<f64>() / 9.0))
            .collect();
        let mut p = pulse_with_return(&values);
        p.gain_v_per_dn = 1.0 / 32.0;
        let measured = denoise_one(DenoiseConfig::default(), p.clone())
            .noise
            .noise_v;
        p.stated_noise = Some(crate::pulse::StatedNoise {
            mean: 240.0,
            stddev: 3.0,
        });
        let stated = denoise_one(DenoiseConfig::default(), p.clone()).noise;
        let want = (2.0 / std::f64::consts::PI).sqrt() * 3.0 * 0.6f64.sqrt();
        assert!(
            (f64::from(stated.noise_v) - want).abs() < 1e-5,
            "{stated:?}"
        );
        assert!(measured < stated.noise_v / 5.0, "{measured} vs {stated:?}");
        assert!((stated.baseline_v - 240.0).abs() < 6.0, "{stated:?}");
        // A stated σ that is not a positive number leaves the measured level.
        p.stated_noise = Some(crate::pulse::StatedNoise {
            mean: 240.0,
            stddev: f32::NAN,
        });
        assert_eq!(
            denoise_one(DenoiseConfig::default(), p).noise.noise_v,
            measured
        );
    }

    #[test]
    fn noise_level_of_uniform_noise_matches_the_high_passed_mad() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let a = 11.0f64;
        let values: Vec<f64> = (0..2048).map(|_| 50.0 + rng.random_range(-a..=a)).collect();
        let mut p = pulse_with_return(&values);
        p.gain_v_per_dn = 0.01;
        let out = denoise_one(DenoiseConfig::default(), p);
        // raw - smoothed keeps the noise above the cut-off: a fraction 1 - 0.2/0.5 of its
        // variance, close to normal, so mean |.| = sqrt(2/pi) * sigma * sqrt(0.6).
        let sigma = a / 3f64.sqrt();
        let expected = (2.0 / std::f64::consts::PI).sqrt() * sigma * 0.6f64.sqrt() * 0.01;
        let got = out.noise.noise_v as f64;
        assert!(
            (got / expected - 1.0).abs() < 0.2,
            "noise level {got} V, expected {expected} V"
        );
    }

    #[test]
    fn every_drop_reason_triggers() {
        let good = || {
            let mut p = Pulse::default();
            p.push_segment(SegmentKind::Outgoing, 0, -10.0, [10u16; 20]);
            p.push_segment(SegmentKind::Return, 0, 900.0, [10u16; 100]);
            p
        };
        let empty = Pulse::default();
        let mut nan_gain = good();
        nan_gain.gain_v_per_dn = f32::NAN;
        let mut inf_offset = good();
        inf_offset.offset_v = f32::INFINITY;
        let mut zero_interval = good();
        zero_interval.sample_ns = 0.0;
        let mut nan_interval = good();
        nan_interval.sample_ns = f64::NAN;
        let mut coarse = good();
        coarse.sample_ns = 4.0; // Nyquist 0.125 GHz < 0.2 GHz
        let mut at_nyquist = good();
        at_nyquist.sample_ns = 2.5; // Nyquist exactly 0.2 GHz
        let mut out_of_bounds = good();
        out_of_bounds.segments[1].len = 1000;
        let mut too_long = good();
        too_long.push_segment(SegmentKind::Return, 0, 0.0, [10u16; 300]);

        let mut stage = Denoise::new(DenoiseConfig {
            max_samples: 256,
            ..Default::default()
        });
        let run = apply(
            [
                good(),
                empty,
                nan_gain,
                inf_offset,
                zero_interval,
                nan_interval,
                coarse,
                at_nyquist,
                out_of_bounds,
                too_long,
            ],
            |p| stage.denoise_pulse(p),
        );
        assert_eq!(run.emitted.len(), 1);
        assert_eq!(run.dropped.get("no_segments"), 1);
        assert_eq!(run.dropped.get("bad_digitizer_parameters"), 4);
        assert_eq!(run.dropped.get("cutoff_above_nyquist"), 2);
        assert_eq!(run.dropped.get("segment_out_of_bounds"), 1);
        assert_eq!(run.dropped.get("segment_too_long"), 1);
        assert_eq!(run.errors, 5, "bad parameters and bad bounds are errors");
    }

    #[test]
    fn zero_length_segments_are_skipped() {
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Outgoing, 0, -10.0, [5u16; 0]);
        p.push_segment(SegmentKind::Return, 0, 900.0, [7u16; 40]);
        p.push_segment(SegmentKind::Return, 1, 900.0, [7u16; 0]);
        let out = denoise_one(DenoiseConfig::default(), p);
        assert_eq!(out.signal.len(), 40);
        assert_eq!(out.noise.baseline_v, 7.0);
        assert!(out.signal.iter().all(|v| v.abs() < 1e-4));
        // Only empty segments: emitted with an empty signal.
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Return, 0, 900.0, [7u16; 0]);
        let out = denoise_one(DenoiseConfig::default(), p);
        assert!(out.signal.is_empty());
        assert_eq!(out.noise, crate::pulse::NoiseEstimate::default());
    }

    #[test]
    fn a_non_positive_cutoff_is_a_typed_error_not_a_panic() {
        for cutoff_ghz in [0.0, -0.2, f64::NAN, f64::INFINITY] {
            let config = DenoiseConfig {
                cutoff_ghz,
                ..Default::default()
            };
            assert!(matches!(
                config.validate(),
                Err(DenoiseError::NonPositiveCutoff { .. })
            ));
            assert!(Denoise::try_new(config).is_err());
        }
        assert!(Denoise::try_new(DenoiseConfig::default()).is_ok());
    }

    fn realistic_pulse(rng: &mut ChaCha8Rng) -> Pulse {
        let mut p = Pulse::default();
        let outgoing: Vec<u16> = (0..64)
            .map(|i| {
                let d = (i as f64 - 32.0) / 6.8;
                (12.0 + 200.0 * (-0.5 * d * d).exp() + rng.random_range(-3.0..=3.0)).round() as u16
            })
            .collect();
        let ret: Vec<u16> = gaussian_on_pedestal(rng, 256, 12.0, 3.0, 160.0, 6.8)
            .into_iter()
            .map(|v| v.round() as u16)
            .collect();
        p.push_segment(SegmentKind::Outgoing, 0, -32.0, outgoing);
        p.push_segment(SegmentKind::Return, 0, 6500.0, ret);
        p
    }

    #[test]
    fn buffers_do_not_grow_after_the_first_pulse() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut stage = Denoise::new(DenoiseConfig::default());
        apply([realistic_pulse(&mut rng)], |p| stage.denoise_pulse(p));
        let caps = stage.buffer_capacities();
        let plans = stage.plans.len();
        let pulses: Vec<Pulse> = (0..999).map(|_| realistic_pulse(&mut rng)).collect();
        let run = apply(pulses, |p| stage.denoise_pulse(p));
        assert_eq!(run.emitted.len(), 999);
        assert_eq!(stage.buffer_capacities(), caps);
        assert_eq!(stage.plans.len(), plans, "no new FFT plans");
    }

    #[test]
    fn signal_is_resized_to_the_raw_length_reusing_its_capacity() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let mut p = realistic_pulse(&mut rng);
        p.signal = Vec::with_capacity(1000);
        p.signal.extend([1.0; 500]);
        let out = denoise_one(DenoiseConfig::default(), p);
        assert_eq!(out.signal.len(), out.raw.len());
        assert_eq!(out.signal.capacity(), 1000);
    }

    #[test]
    fn denoise_segment_matches_the_pulse_path_and_checks_its_input() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let counts: Vec<u16> = gaussian_on_pedestal(&mut rng, 200, 40.0, 4.0, 90.0, 3.0)
            .into_iter()
            .map(|v| v.round() as u16)
            .collect();
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Return, 0, 0.0, counts.iter().copied());
        let via_pulse = denoise_one(DenoiseConfig::default(), p);
        let volts: Vec<f32> = counts.iter().map(|&c| c as f32).collect();
        let mut stage = Denoise::new(DenoiseConfig::default());
        let mut out = vec![0.0; volts.len()];
        let noise = stage.denoise_segment(&volts, 1.0, &mut out).unwrap();
        assert_eq!(noise, via_pulse.noise);
        assert_eq!(out, via_pulse.signal);
        // Short segment (robust baseline path) and an empty one.
        let mut short = vec![0.0; 10];
        let est = stage
            .denoise_segment(&volts[..10], 1.0, &mut short)
            .unwrap();
        assert!(est.baseline_v > 30.0 && est.baseline_v < 50.0);
        assert_eq!(
            stage.denoise_segment(&[], 1.0, &mut []).unwrap(),
            crate::pulse::NoiseEstimate::default()
        );
        // Bad input is a typed error, never a panic.
        let mut o3 = [0.0; 3];
        for (v, ns) in [
            ([1.0, f32::NAN, 1.0], 1.0),
            ([1.0, 2.0, 3.0], 0.0),
            ([1.0, 2.0, 3.0], f64::NAN),
            ([1.0, 2.0, 3.0], 4.0),
        ] {
            assert!(matches!(
                stage.denoise_segment(&v, ns, &mut o3),
                Err(DenoiseError::BadSegment { .. })
            ));
        }
        assert!(stage.denoise_segment(&[1.0; 4], 1.0, &mut o3).is_err());
        let mut small = Denoise::new(DenoiseConfig {
            max_samples: 4,
            ..Default::default()
        });
        assert!(
            small
                .denoise_segment(&[1.0; 5], 1.0, &mut [0.0; 5])
                .is_err()
        );
    }

    fn fir() -> DenoiseConfig {
        DenoiseConfig {
            filter: LowPass::Fir,
            ..Default::default()
        }
    }

    #[test]
    fn fir_design_is_a_symmetric_unit_sum_low_pass_of_bounded_length() {
        let mut taps = Vec::with_capacity(2 * MAX_FIR_HALF + 1);
        design_fir(0.2, &mut taps);
        assert_eq!(taps.len(), 35);
        let sum: f32 = taps.iter().sum();
        assert!((sum - 1.0).abs() < 1e-5);
        for j in 0..taps.len() {
            assert_eq!(taps[j], taps[taps.len() - 1 - j]);
        }
        // −6 dB at the cut-off, > 50 dB down one transition half-width beyond it.
        let gain = |f: f64| -> f64 {
            taps.iter()
                .enumerate()
                .map(|(j, &t)| {
                    t as f64 * (2.0 * std::f64::consts::PI * f * (j as f64 - 17.0)).cos()
                })
                .sum::<f64>()
                .abs()
        };
        assert!((gain(0.2) - 0.5).abs() < 0.02, "{}", gain(0.2));
        assert!(gain(0.05) > 0.999 && gain(0.05) < 1.001);
        assert!(gain(0.3) < 3e-3 && gain(0.45) < 3e-3);
        design_fir(0.005, &mut taps);
        assert_eq!(taps.len(), 2 * MAX_FIR_HALF + 1);
    }

    #[test]
    fn fir_filter_passes_the_band_removes_the_rest_and_keeps_positions() {
        let out = denoise_one(fir(), pulse_with_return(&sine(1024, 20.0, 1000.0, 2000.0)));
        let a = sine_amplitude(&out.signal, 256..756, 20.0);
        assert!((a / 1000.0 - 1.0).abs() < 0.01, "amplitude {a}");
        let out = denoise_one(
            fir(),
            pulse_with_return(&sine(1024, 10.0 / 3.0, 1000.0, 2000.0)),
        );
        let a = sine_amplitude(&out.signal, 256..756, 10.0 / 3.0);
        assert!(a < 10.0, "residual amplitude {a} of 1000");
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let values: Vec<f64> = (0..4096)
            .map(|_| 1000.0 + rng.random_range(-100.0..=100.0))
            .collect();
        let out = denoise_one(fir(), pulse_with_return(&values));
        let std = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
        };
        let after: Vec<f64> = out.signal[512..3584].iter().map(|&v| v as f64).collect();
        let ratio = std(&after) / std(&values[512..3584]);
        assert!((ratio - 0.4f64.sqrt()).abs() < 0.06, "ratio {ratio}");
        for &(mu, sigma) in &[(100.0, 2.0), (100.25, 2.0), (120.8, 3.0)] {
            let clean: Vec<f64> = (0..256)
                .map(|i| 3000.0 * (-0.5 * ((i as f64 - mu) / sigma).powi(2)).exp())
                .collect();
            let values: Vec<f64> = clean.iter().map(|v| v + 500.0).collect();
            let out = denoise_one(fir(), pulse_with_return(&values));
            let shift = gaussian_peak(&out.signal) - gaussian_peak(&clean);
            assert!(shift.abs() < 0.05, "centre {mu}: moved {shift}");
        }
    }

    #[test]
    fn fir_and_fft_agree_on_a_realistic_pulse_and_its_noise_level() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for _ in 0..20 {
            let p = realistic_pulse(&mut rng);
            let a = denoise_one(DenoiseConfig::default(), p.clone());
            let b = denoise_one(fir(), p);
            assert_eq!(a.noise.baseline_v, b.noise.baseline_v);
            let rel = b.noise.noise_v / a.noise.noise_v;
            assert!((rel - 1.0).abs() < 0.1, "noise level FIR/FFT {rel}");
            let peak = a.signal.iter().fold(0.0f32, |m, &v| m.max(v));
            let diff = a
                .signal
                .iter()
                .zip(&b.signal)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(diff < 0.05 * peak, "largest difference {diff} of {peak}");
        }
        // Buffers do not grow on the FIR path either.
        let mut stage = Denoise::new(fir());
        apply([realistic_pulse(&mut rng)], |p| stage.denoise_pulse(p));
        let caps = stage.buffer_capacities();
        let pulses: Vec<Pulse> = (0..50).map(|_| realistic_pulse(&mut rng)).collect();
        apply(pulses, |p| stage.denoise_pulse(p));
        assert_eq!(stage.buffer_capacities(), caps);
    }
}
