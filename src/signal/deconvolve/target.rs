//! Deconvolution to a target pulse (`target_fwhm_ns`): every method delivers its result as
//! seen by a narrower Gaussian pulse `t` (e.g. 2 ns, the seed's truth pulse) instead of as the
//! cross-section itself.
//!
//! Why: the cross-section σ(t) of a received waveform `y = k ⊛ σ + noise` is not recoverable
//! beyond the bandwidth the noise leaves; a method that tries (RL after many iterations, NNLS)
//! sharpens noise into spikes and overshoots the peaks of `t ⊛ σ`, which is what the seed
//! compares with and what a voxel or a decomposition downstream wants. Asking for `t ⊛ σ`
//! directly is better conditioned than asking for σ and blurring afterwards:
//!
//! - **Reduced kernel** (Richardson-Lucy, Gold, Wiener): with `k = t ⊛ h`, `y = h ⊛ (t ⊛ σ)`, so
//!   deconvolving `y` by `h` — the kernel that maps the target pulse to the system pulse —
//!   estimates `t ⊛ σ` itself. `h` is narrower than `k` only by the target's width (for
//!   Gaussians `FWHM_h² = FWHM_k² − FWHM_t²`), so the method never has to restore the
//!   frequencies the target does not carry: the iterations converge towards a solution with
//!   the target's smoothness instead of over-sharpening. `h` is computed for each kernel (per
//!   shot with `kernel = "outgoing"`, once for a calibrated kernel) by regularised division of
//!   spectra, `H = K · conj(T) / (|T|² + λ)` with `λ =` [`REGULARISATION`] (`|T| ≤ 1`, unit
//!   sum), on a zero-padded FFT of length `N = 2^⌈log₂(2m + taps_t)⌉ ≥ 16` (`m` the kernel's
//!   taps), then cut back to the kernel's own span, negative taps clipped (the iterative
//!   methods need a non-negative kernel), normalised to unit sum, the zero-delay tap where the
//!   kernel's is (returns do not move) and taps below [`TRIM`] of the largest trimmed off its
//!   ends (fewer taps, less work per iteration).
//! - **Synthesis with the target** (NNLS): NNLS represents `y` as non-negative spikes `x` with
//!   `k ⊛ x ≈ y`; the result seen by the target is `t ⊛ x` (each spike drawn as the target
//!   pulse). NNLS by `h` would still return spikes (its solutions are sparse), so this is its
//!   well-posed form.
//!
//! A kernel no wider than the target (its variance about its centroid at most the target's
//! plus a quarter of a sample², i.e. nothing left to deconvolve) reduces to the identity
//! (one tap): the method then returns the data as it is (Richardson-Lucy converges to `y` at
//! once).
//!
//! Cost: three FFTs of length `N` and `N` complex products when the kernel changes (≈ 1 µs at
//! `m ≈ 30`; a calibrated kernel is reduced once and reused: the input kernel is compared with
//! the last one tap by tap); NNLS adds one convolution with the target (`n · taps_t` flops).
//! Plans and buffers are made when a new length first appears and reused after (no
//! allocation per pulse once every length in use has been seen).

use std::sync::Arc;

use realfft::num_complex::Complex;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};

use crate::signal::deconvolve::{DeconvError, Deconvolver, MethodStats};
use crate::signal::kernel::{Kernel, KernelError, convolve_same};

/// Tikhonov floor of the spectral division (`|T|²` is 1 at zero frequency).
pub const REGULARISATION: f32 = 1e-3;
/// Taps of the reduced kernel below this fraction of its largest tap are trimmed off its ends.
pub const TRIM: f32 = 1e-4;
/// Smallest FFT length of the reduction.
const MIN_FFT: usize = 16;

/// Checks a configured target FWHM (ns): positive and finite. The message names the key.
pub fn check_target_fwhm(key: &str, fwhm_ns: f64) -> Result<(), String> {
    if fwhm_ns.is_finite() && fwhm_ns > 0.0 {
        Ok(())
    } else {
        Err(format!(
            "{key} must be a positive number of ns (the target pulse's FWHM), got {fwhm_ns}"
        ))
    }
}

/// A planned real FFT pair of one length.
struct Plan {
    forward: Arc<dyn RealToComplex<f32>>,
    inverse: Arc<dyn ComplexToReal<f32>>,
}

/// Computes the reduced kernel `h` (`t ⊛ h = k`) of kernels for one target pulse, caching the
/// last result.
pub struct KernelReducer {
    fwhm_ns: f64,
    planner: RealFftPlanner<f32>,
    /// Plans by `log2(N)`.
    plans: Vec<Option<Plan>>,
    time: Vec<f32>,
    spec_k: Vec<Complex<f32>>,
    spec_t: Vec<Complex<f32>>,
    scratch: Vec<Complex<f32>>,
    /// The target pulse at `target_ns` per sample.
    target: Kernel,
    target_ns: f64,
    /// The last kernel reduced and its sample interval (the cache key).
    last: Kernel,
    last_ns: f64,
    reduced: Kernel,
}

impl KernelReducer {
    /// A reducer to the Gaussian target pulse of `fwhm_ns` (ns, positive and finite), with
    /// buffers for kernels of up to `max_taps` taps (they grow if longer kernels come).
    pub fn new(fwhm_ns: f64, max_taps: usize) -> Self {
        let n = fft_len(max_taps, 8);
        KernelReducer {
            fwhm_ns,
            planner: RealFftPlanner::new(),
            plans: Vec::new(),
            time: vec![0.0; n],
            spec_k: vec![Complex::default(); n / 2 + 1],
            spec_t: vec![Complex::default(); n / 2 + 1],
            scratch: Vec::new(),
            target: Kernel::with_capacity(32),
            target_ns: f64::NAN,
            last: Kernel::with_capacity(max_taps),
            last_ns: f64::NAN,
            reduced: Kernel::with_capacity(max_taps),
        }
    }

    /// The last reduced kernel [`KernelReducer::reduce`] returned (empty before the first).
    pub fn last_reduced(&self) -> &Kernel {
        &self.reduced
    }

    /// The target pulse's FWHM, ns.
    pub fn fwhm_ns(&self) -> f64 {
        self.fwhm_ns
    }

    /// The target pulse sampled at `sample_ns` (ns per sample).
    pub fn target(&mut self, sample_ns: f64) -> Result<&Kernel, KernelError> {
        if self.target_ns.to_bits() != sample_ns.to_bits() {
            self.target_ns = f64::NAN;
            self.target.set_gaussian(self.fwhm_ns, sample_ns)?;
            self.target_ns = sample_ns;
        }
        Ok(&self.target)
    }

    /// The reduced kernel `h` of `k` (taps at `sample_ns` ns per sample): `t ⊛ h ≈ k`,
    /// non-negative, unit sum, zero-delay tap aligned with `k`'s (see the module
    /// documentation).
    pub fn reduce(&mut self, k: &Kernel, sample_ns: f64) -> Result<&Kernel, KernelError> {
        if self.last_ns.to_bits() == sample_ns.to_bits()
            && self.last.center == k.center
            && self.last.taps == k.taps
        {
            return Ok(&self.reduced);
        }
        self.last_ns = f64::NAN;
        self.target(sample_ns)?;
        let t = &self.target;
        if k.taps.is_empty() || k.center >= k.taps.len() {
            return Err(KernelError::NoEnergy);
        }
        if variance(&k.taps) <= variance(&t.taps) + 0.25 {
            // Nothing left to deconvolve: the identity.
            self.reduced.taps.clear();
            self.reduced.taps.push(1.0);
            self.reduced.center = 0;
        } else {
            self.reduce_spectrally(k)?;
        }
        self.last.taps.clear();
        self.last.taps.extend_from_slice(&k.taps);
        self.last.center = k.center;
        self.last_ns = sample_ns;
        Ok(&self.reduced)
    }

    /// `h = IFFT(K · conj(T) / (|T|² + λ))`, cut to `k`'s span, clipped, normalised, trimmed.
    fn reduce_spectrally(&mut self, k: &Kernel) -> Result<(), KernelError> {
        let m = k.taps.len();
        let n = fft_len(m, self.target.taps.len());
        let log = n.trailing_zeros() as usize;
        if self.plans.len() <= log {
            self.plans.resize_with(log + 1, || None);
        }
        if self.plans[log].is_none() {
            self.plans[log] = Some(Plan {
                forward: self.planner.plan_fft_forward(n),
                inverse: self.planner.plan_fft_inverse(n),
            });
        }
        let plan = self.plans[log].as_ref().expect("planned above");
        let scratch_len = plan
            .forward
            .get_scratch_len()
            .max(plan.inverse.get_scratch_len());
        if self.scratch.len() < scratch_len {
            self.scratch.resize(scratch_len, Complex::default());
        }
        if self.time.len() < n {
            self.time.resize(n, 0.0);
            self.spec_k.resize(n / 2 + 1, Complex::default());
            self.spec_t.resize(n / 2 + 1, Complex::default());
        }
        let bins = n / 2 + 1;
        let time = &mut self.time[..n];
        let (spec_k, spec_t) = (&mut self.spec_k[..bins], &mut self.spec_t[..bins]);
        let scratch = &mut self.scratch[..scratch_len];
        // Both pulses placed circularly with their zero-delay tap at index 0.
        place(&k.taps, k.center, time);
        // Lengths match by construction, so the transforms cannot fail.
        let _ = plan.forward.process_with_scratch(time, spec_k, scratch);
        place(&self.target.taps, self.target.center, time);
        let _ = plan.forward.process_with_scratch(time, spec_t, scratch);
        for (kk, tt) in spec_k.iter_mut().zip(spec_t.iter()) {
            *kk = *kk * tt.conj() / (tt.norm_sqr() + REGULARISATION);
        }
        spec_k[0].im = 0.0;
        spec_k[bins - 1].im = 0.0;
        let _ = plan.inverse.process_with_scratch(spec_k, time, scratch);
        // Back to the kernel's span: tap j of h sits at delay j − centre, index (j − c) mod n.
        let c = k.center;
        let taps = &mut self.reduced.taps;
        taps.clear();
        taps.extend((0..m).map(|j| time[(j + n - c) % n].max(0.0)));
        let peak = taps.iter().fold(0.0f32, |a, &v| a.max(v));
        let sum: f64 = taps.iter().map(|&v| v as f64).sum();
        if !(peak > 0.0 && sum.is_finite() && sum > 0.0) {
            return Err(KernelError::NoEnergy);
        }
        let first = taps.iter().position(|&v| v >= TRIM * peak).unwrap_or(0);
        let last = taps
            .iter()
            .rposition(|&v| v >= TRIM * peak)
            .unwrap_or(m - 1);
        // The zero-delay tap stays inside (a kernel whose centre is not on its body keeps the
        // taps between).
        let first = first.min(c);
        let last = last.max(c);
        taps.truncate(last + 1);
        taps.drain(..first);
        let sum: f64 = taps.iter().map(|&v| v as f64).sum();
        for v in taps.iter_mut() {
            *v = (*v as f64 / sum) as f32;
        }
        self.reduced.center = c - first;
        Ok(())
    }
}

/// FFT length of the reduction for a kernel of `m` taps and a target of `t` taps.
fn fft_len(m: usize, t: usize) -> usize {
    (2 * m + t).next_power_of_two().max(MIN_FFT)
}

/// Writes `taps` into `buf` circularly with tap `center` at index 0, zeros elsewhere.
fn place(taps: &[f32], center: usize, buf: &mut [f32]) {
    let n = buf.len();
    buf.fill(0.0);
    for (j, &v) in taps.iter().enumerate() {
        buf[(j + n - center % n) % n] += v;
    }
}

/// Variance of a non-negative pulse about its centroid, samples² (taps clipped at 0).
fn variance(taps: &[f32]) -> f64 {
    let (mut s0, mut s1, mut s2) = (0.0f64, 0.0f64, 0.0f64);
    for (j, &v) in taps.iter().enumerate() {
        let (w, x) = (v.max(0.0) as f64, j as f64);
        s0 += w;
        s1 += w * x;
        s2 += w * x * x;
    }
    if s0 <= 0.0 {
        return 0.0;
    }
    let mean = s1 / s0;
    (s2 / s0 - mean * mean).max(0.0)
}

/// A method delivering its result as seen by a target pulse (or as it is, without one).
pub struct Targeted {
    inner: Box<dyn Deconvolver>,
    /// The target pulse the inner method took itself ([`Deconvolver::take_target`]); runs
    /// then pass through.
    taken: Option<f64>,
    reducer: Option<KernelReducer>,
    /// NNLS: deconvolve by the kernel itself, then draw every spike as the target pulse.
    synthesis: bool,
    /// NNLS's spikes before the synthesis, `max_samples`.
    spikes: Vec<f32>,
}

impl Targeted {
    /// Wraps `inner` (built for segments of up to `max_samples` samples and kernels of up to
    /// `max_taps` taps). With `target_fwhm_ns`, results are seen by that Gaussian pulse: by
    /// the reduced kernel, or (NNLS) by synthesis with the target.
    pub fn new(
        inner: Box<dyn Deconvolver>,
        target_fwhm_ns: Option<f64>,
        max_samples: usize,
        max_taps: usize,
    ) -> Self {
        let mut inner = inner;
        let taken = target_fwhm_ns.filter(|&f| inner.take_target(f));
        let target_fwhm_ns = target_fwhm_ns.filter(|_| taken.is_none());
        let synthesis = inner.name() == "nnls";
        Targeted {
            taken,
            reducer: target_fwhm_ns.map(|f| KernelReducer::new(f, max_taps)),
            spikes: if synthesis && target_fwhm_ns.is_some() {
                vec![0.0; max_samples]
            } else {
                Vec::new()
            },
            synthesis,
            inner,
        }
    }

    /// The target pulse's FWHM, ns (`None`: results as they are).
    pub fn target_fwhm_ns(&self) -> Option<f64> {
        self.taken
            .or_else(|| self.reducer.as_ref().map(KernelReducer::fwhm_ns))
    }

    /// NNLS's spikes of the last run of `n` samples, before they were drawn as the target pulse;
    /// `None` when this wrapper draws none (another method, no target, or `n` too long).
    pub fn last_spikes(&self, n: usize) -> Option<&[f32]> {
        let drawn = self.synthesis && self.reducer.is_some();
        self.spikes.get(..n).filter(|_| drawn)
    }

    /// The reduced kernel the last run deconvolved by (a method deconvolving by it, with a
    /// target); `None` otherwise.
    pub fn reduced_kernel(&self) -> Option<&Kernel> {
        self.reducer
            .as_ref()
            .filter(|_| !self.synthesis)
            .map(KernelReducer::last_reduced)
    }

    /// The wrapped method, without the target (e.g. a first deconvolution by a calibrated
    /// system response before the one by the outgoing pulse).
    pub fn plain(&mut self) -> &mut dyn Deconvolver {
        self.inner.as_mut()
    }
}

impl Targeted {
    /// [`Deconvolver::run`], or [`Deconvolver::run_excluding`] with `excluded`.
    fn run_with(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: Option<&[bool]>,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let Some(reducer) = self.reducer.as_mut() else {
            return super::run_flagged(
                self.inner.as_mut(),
                y,
                k,
                noise_v,
                sample_ns,
                excluded,
                out,
            );
        };
        if !(sample_ns.is_finite() && sample_ns > 0.0) {
            return Err(DeconvError::BadKernel);
        }
        if self.synthesis {
            let n = y.len();
            if n > self.spikes.len() {
                return Err(DeconvError::TooLong {
                    len: n,
                    max: self.spikes.len(),
                });
            }
            let spikes = &mut self.spikes[..n];
            let stats = super::run_flagged(
                self.inner.as_mut(),
                y,
                k,
                noise_v,
                sample_ns,
                excluded,
                spikes,
            )?;
            let sigma = reducer.fwhm_ns() / sample_ns / FWHM_PER_SIGMA;
            let t = reducer
                .target(sample_ns)
                .map_err(|_| DeconvError::BadKernel)?;
            if out.len() != n {
                return Err(DeconvError::LengthMismatch {
                    input: n,
                    out: out.len(),
                });
            }
            convolve_same(spikes, t, out);
            redraw_adjacent_pairs(spikes, t, sigma, out);
            return Ok(stats);
        }
        let h = reducer
            .reduce(k, sample_ns)
            .map_err(|_| DeconvError::BadKernel)?;
        super::run_flagged(self.inner.as_mut(), y, h, noise_v, sample_ns, excluded, out)
    }
}

/// FWHM of a Gaussian in units of its σ, `2 √(2 ln 2)`.
const FWHM_PER_SIGMA: f64 = 2.354_820_045_030_949;

/// Redraws in `out` (the `spikes` drawn by the target pulse `t` of σ `sigma` samples) every
/// isolated pair of adjacent non-zero spikes as one target pulse at their amplitude-weighted
/// centroid, of their summed area: NNLS on a grid splits a surface lying between two samples
/// into two adjacent spikes, and the centroid puts it back between them (docs/accuracy.md,
/// "Deconvolution over noise models", third step). Runs of one or of three or more spikes
/// stay as drawn. No allocation.
fn redraw_adjacent_pairs(spikes: &[f32], t: &Kernel, sigma: f64, out: &mut [f32]) {
    let n = spikes.len();
    if !(sigma.is_finite() && sigma > 0.0) || n < 2 {
        return;
    }
    let half = (3.5 * sigma).ceil().max(1.0) as isize;
    let on = |i: isize| i >= 0 && (i as usize) < n && spikes[i as usize] > 0.0;
    let mut i = 0isize;
    while (i as usize) + 1 < n {
        if !(on(i) && on(i + 1)) || on(i - 1) || on(i + 2) {
            i += 1;
            continue;
        }
        let (a, b) = (spikes[i as usize] as f64, spikes[i as usize + 1] as f64);
        let area = a + b;
        let centre = i as f64 + b / area;
        // Take the two spikes' own pulses out.
        for (s, amp) in [(i, a), (i + 1, b)] {
            for (j, &tap) in t.taps.iter().enumerate() {
                let o = s + j as isize - t.center as isize;
                if o >= 0 && (o as usize) < n {
                    out[o as usize] -= (amp * tap as f64) as f32;
                }
            }
        }
        // One unit-sum sampled Gaussian at the centroid, scaled to the area.
        let (lo, hi) = (
            centre.floor() as isize - half,
            centre.ceil() as isize + half,
        );
        let weight = |p: isize| (-0.5 * ((p as f64 - centre) / sigma).powi(2)).exp();
        let sum: f64 = (lo..=hi).map(weight).sum();
        for p in lo.max(0)..=hi.min(n as isize - 1) {
            out[p as usize] += (area * weight(p) / sum) as f32;
        }
        i += 2;
    }
}

impl Deconvolver for Targeted {
    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn take_target(&mut self, fwhm_ns: f64) -> bool {
        // Already wrapped: a second target would be applied twice.
        let _ = fwhm_ns;
        false
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.run_with(y, k, noise_v, sample_ns, None, out)
    }

    fn run_excluding(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: &[bool],
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.run_with(y, k, noise_v, sample_ns, Some(excluded), out)
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        let extra = match &self.reducer {
            None => 0,
            Some(_) if self.synthesis => 2 * n as u64 * 32,
            Some(_) => {
                let len = fft_len(m, 32) as u64;
                // Three transforms of ~2.5 N log2 N flops and the spectral division.
                3 * (5 * len / 2) * len.trailing_zeros() as u64 + 8 * len
            }
        };
        self.inner.worst_case_flops(n, m) + extra
    }

    fn choice_counts(&self) -> Option<super::ChoiceCounts> {
        self.inner.choice_counts()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::deconvolve::{MethodConfig, NnlsConfig, RlConfig};

    fn gaussian(fwhm_ns: f64, sample_ns: f64) -> Kernel {
        let mut k = Kernel::default();
        k.set_gaussian(fwhm_ns, sample_ns).unwrap();
        k
    }

    fn width_var(k: &Kernel) -> f64 {
        variance(&k.taps)
    }

    #[test]
    fn the_reduced_kernel_of_gaussians_has_the_difference_of_their_variances() {
        for (pulse, target) in [(8.0, 2.0), (16.0, 4.0), (4.0, 2.0), (16.0, 2.0)] {
            let k = gaussian(pulse, 1.0);
            let t = gaussian(target, 1.0);
            let mut r = KernelReducer::new(target, 256);
            let h = r.reduce(&k, 1.0).unwrap().clone();
            let want = width_var(&k) - width_var(&t);
            let got = width_var(&h);
            assert!(
                (got - want).abs() < 0.05 * want + 0.05,
                "{pulse}/{target} ns: variance {got} against {want}"
            );
            // t ⊛ h reproduces k.
            let n = 160;
            let mut spike = vec![0.0f32; n];
            spike[80] = 1.0;
            let (mut a, mut b, mut c) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            convolve_same(&spike, &h, &mut a);
            convolve_same(&a, &t, &mut b);
            convolve_same(&spike, &k, &mut c);
            let err = b
                .iter()
                .zip(&c)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            let peak = c.iter().fold(0.0f32, |m, &v| m.max(v));
            assert!(err < 0.02 * peak, "{pulse}/{target} ns: t ⊛ h off by {err}");
            // Unit sum, non-negative, centred like k.
            let sum: f32 = h.taps.iter().sum();
            assert!((sum - 1.0).abs() < 1e-4);
            assert!(h.taps.iter().all(|&v| v >= 0.0));
            let hp = crate::signal::kernel::peak_index(&h.taps).unwrap() as isize;
            assert!((hp - h.center as isize).abs() <= 1);
        }
    }

    #[test]
    fn a_kernel_no_wider_than_the_target_reduces_to_the_identity() {
        let mut r = KernelReducer::new(4.0, 64);
        let h = r.reduce(&gaussian(3.0, 1.0), 1.0).unwrap();
        assert_eq!((h.taps.as_slice(), h.center), (&[1.0f32][..], 0));
    }

    #[test]
    fn the_reduction_is_cached_and_follows_a_new_kernel() {
        let mut r = KernelReducer::new(2.0, 64);
        let a = r.reduce(&gaussian(8.0, 1.0), 1.0).unwrap().clone();
        let b = r.reduce(&gaussian(8.0, 1.0), 1.0).unwrap().clone();
        assert_eq!(a, b);
        let c = r.reduce(&gaussian(12.0, 1.0), 1.0).unwrap().clone();
        assert!(c.taps.len() > a.taps.len());
        // The same kernel at another sample interval is another pulse.
        let d = r.reduce(&gaussian(8.0, 1.0), 0.5).unwrap().clone();
        assert_ne!(a, d);
    }

    /// RL to a 2 ns target on two echoes 4 ns apart seen with a 4 ns pulse and noise: closer
    /// to the truth `t ⊛ σ` than RL to spikes at the same 200 iterations (which sharpen past
    /// the target: `docs/accuracy.md`).
    #[test]
    fn rl_to_a_target_approaches_the_target_view_of_the_cross_section() {
        let n = 128;
        let mut sigma = vec![0.0f32; n];
        sigma[60] = 1.0;
        sigma[64] = 0.7;
        let k = gaussian(4.0, 1.0);
        let t = gaussian(2.0, 1.0);
        let (mut y, mut truth) = (vec![0.0; n], vec![0.0; n]);
        convolve_same(&sigma, &k, &mut y);
        convolve_same(&sigma, &t, &mut truth);
        // Uniform noise in ±2 % of the peak (a fixed linear congruential sequence).
        let peak = y.iter().fold(0.0f32, |m, &v| m.max(v));
        let mut state = 12345u64;
        for v in y.iter_mut() {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v += 0.02 * peak * ((state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0);
        }
        let rmse = |x: &[f32]| {
            (x.iter()
                .zip(&truth)
                .map(|(a, b)| ((a - b) as f64).powi(2))
                .sum::<f64>()
                / n as f64)
                .sqrt()
        };
        let method = MethodConfig::RichardsonLucy(RlConfig {
            iterations: 200,
            ..RlConfig::default()
        });
        let mut plain = Targeted::new(method.build(n, 64), None, n, 64);
        let mut to_2ns = Targeted::new(method.build(n, 64), Some(2.0), n, 64);
        assert_eq!(to_2ns.target_fwhm_ns(), Some(2.0));
        let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
        plain.run(&y, &k, 1e-4, 1.0, &mut a).unwrap();
        to_2ns.run(&y, &k, 1e-4, 1.0, &mut b).unwrap();
        assert!(b.iter().all(|v| v.is_finite() && *v >= 0.0));
        assert!(
            rmse(&b) < 0.7 * rmse(&a),
            "to 2 ns {} against spikes {}",
            rmse(&b),
            rmse(&a)
        );
        // Energy is kept (RL clips the noise below zero, so within the noise's share).
        let sy: f32 = y.iter().map(|v| v.max(0.0)).sum();
        let sb: f32 = b.iter().sum();
        assert!((sy - sb).abs() < 0.03 * sy, "{sy} against {sb}");
    }

    #[test]
    fn nnls_spikes_are_drawn_as_the_target_pulse() {
        let n = 96;
        let mut sigma = vec![0.0f32; n];
        sigma[40] = 1.0;
        let k = gaussian(8.0, 1.0);
        let t = gaussian(2.0, 1.0);
        let mut y = vec![0.0; n];
        convolve_same(&sigma, &k, &mut y);
        let method = MethodConfig::Nnls(NnlsConfig::default());
        let mut d = Targeted::new(method.build(n, 64), Some(2.0), n, 64);
        let mut out = vec![0.0; n];
        d.run(&y, &k, 1e-4, 1.0, &mut out).unwrap();
        for (i, &tap) in t.taps.iter().enumerate() {
            let at = 40 + i - t.center;
            assert!(
                (out[at] - tap).abs() < 0.02,
                "bin {at}: {} vs {tap}",
                out[at]
            );
        }
    }

    #[test]
    fn bad_targets_are_refused_with_the_key() {
        assert!(check_target_fwhm("target_fwhm_ns", 2.0).is_ok());
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = check_target_fwhm("target_fwhm_ns", bad).unwrap_err();
            assert!(e.contains("target_fwhm_ns"), "{e}");
        }
    }
}
