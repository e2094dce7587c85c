//! Wiener deconvolution fused with the low-pass: one pass in the frequency domain.
//!
//! The segment `y` (length `n`) and the kernel (length `m`) are zero-padded to a length
//! `N ≥ n + m` whose prime factors are 2, 3 and 5 (so the FFT is fast and its circular
//! convolution cannot wrap the end of the segment onto its start). The kernel is placed
//! circularly with its centre tap at index 0 (tap `j` at `(j − center) mod N`), so its phase
//! is referenced to its centre and a centred kernel does not shift returns. With `P` and `R`
//! the real FFTs of the padded segment and kernel:
//!
//! ```text
//! Σ(f) = P(f) · conj(R(f)) · |P(f)|² / ( |P(f)|² · (|R(f)|² + ρ) + |N|² · max(|R(f)|², ρ) ) · LP(f)
//! ```
//!
//! This is `P · conj(R) / (|R|² + |N|²/|S|²)` with the signal spectrum estimated from the
//! data as `|S|² = |P|² / max(|R|², ρ)` (the seed's weight `W = |P|²/(|P|²+|N|²)`: where
//! `|R|² ≥ ρ` it equals the seed's `(P/R) · W` up to the Tikhonov term ρ), plus `ρ`
//! ([`WienerConfig::regularisation`], relative to `|R(0)|² = 1` for a unit-sum kernel) in the
//! denominator, which bounds the gain at `1/(2√ρ)` even without noise.
//!
//! - **Noise spectrum** (white): `|N|² = noise_scale · n · noise_v²` per bin (the unnormalised
//!   DFT of `n` samples of white noise of standard deviation `noise_v`), `noise_v` being the
//!   segment's noise level from the denoise stage, volts.
//! - **Low-pass** `LP(f)`: bins with frequency `k / (N · sample_ns)` above
//!   [`WienerConfig::cutoff_ghz`] are zeroed (so this also replaces a separate low-pass).
//! - **Normalisation**: the segment and `noise_v` are divided by the segment's largest absolute
//!   value (f64) and the result multiplied back (the filter is scale-equivariant), keeping
//!   `|P|⁴` inside f32 for full-scale and denormal inputs.
//! - Output is **not** forced non-negative (Wiener is linear; small negative lobes remain).
//!
//! Cost: three real FFTs of length `N` (segment and kernel forward, one inverse) plus about 20
//! flops per bin. Plans are cached per `N`. The kernel's spectrum is kept with a copy of the
//! taps it came from and reused when the next call's kernel (taps, centre, `N`) is identical
//! (a calibrated kernel): then only two FFTs run. Per-shot kernels change every pulse and pay
//! the third FFT.

use std::sync::Arc;

use realfft::num_complex::Complex;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::{
    DeconvError, Deconvolver, MethodStats, check_inputs, normalise, scale_out,
};
use crate::signal::kernel::Kernel;

/// Settings of the fused Wiener filter (`method = "wiener"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WienerConfig {
    /// Low-pass cut-off, GHz: bins above it are zeroed. Default 0.2.
    #[serde(default = "default_cutoff_ghz")]
    pub cutoff_ghz: f64,
    /// Multiplies the noise power `n · noise_v²` (dimensionless, ≥ 0). Default 1.0.
    #[serde(default = "default_noise_scale")]
    pub noise_scale: f32,
    /// Tikhonov floor ρ on the kernel power `|R(f)|²`, relative to `|R(0)|² = 1`
    /// (dimensionless, > 0); bounds the gain at `1/(2√ρ)`. Default 1e-3.
    #[serde(default = "default_regularisation")]
    pub regularisation: f32,
    /// Deliver the estimate as seen by a Gaussian target pulse of this FWHM, ns (the filter
    /// multiplied by the target's spectrum `exp(−2π²s²f²)`, `s = FWHM / 2.3548`; no extra
    /// FFT). Default none: the cross-section itself, band-limited by `cutoff_ghz`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_fwhm_ns: Option<f64>,
}

fn default_cutoff_ghz() -> f64 {
    0.2
}
fn default_noise_scale() -> f32 {
    1.0
}
fn default_regularisation() -> f32 {
    1e-3
}

impl WienerConfig {
    /// Worst-case flops for a segment of `n` samples and a kernel of `m` taps, with
    /// `L = fast_len(n + m)` the padded FFT length (the next even 2·3·5-smooth number):
    /// `3 × 2.5·L·log₂L` (three real FFTs at the usual 2.5·L·log₂L estimate) `+ 20·(L/2 + 1)`
    /// (the filter per frequency bin). Independent of iterations: the method is direct.
    pub fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        let len = fast_len(n + m) as f64;
        (3.0 * 2.5 * len * len.log2() + 20.0 * (len / 2.0 + 1.0)) as u64
    }
}

impl Default for WienerConfig {
    fn default() -> Self {
        WienerConfig {
            cutoff_ghz: default_cutoff_ghz(),
            noise_scale: default_noise_scale(),
            regularisation: default_regularisation(),
            target_fwhm_ns: None,
        }
    }
}

/// A forward/inverse real FFT pair planned for one padded length.
struct Plan {
    len: usize,
    forward: Arc<dyn RealToComplex<f32>>,
    inverse: Arc<dyn ComplexToReal<f32>>,
    scratch_len: usize,
}

/// The fused Wiener filter with plans cached and buffers sized once.
pub struct Wiener {
    config: WienerConfig,
    max_samples: usize,
    max_taps: usize,
    planner: RealFftPlanner<f32>,
    plans: Vec<Plan>,
    /// Padded segment / output, time domain.
    time: Vec<f32>,
    /// Padded kernel, time domain.
    kernel_time: Vec<f32>,
    /// Segment spectrum, then the estimate's spectrum.
    spectrum: Vec<Complex<f32>>,
    /// Kernel spectrum.
    kernel_spectrum: Vec<Complex<f32>>,
    scratch: Vec<Complex<f32>>,
    /// The kernel whose spectrum `kernel_spectrum` holds (taps, centre, padded length), so an
    /// unchanged (calibrated) kernel is not transformed again; `None` until the first run.
    cached_kernel: Vec<f32>,
    cached_key: Option<(usize, usize)>,
}

/// The spectrum of a unit-area Gaussian target pulse at the bins `k = 0, 1, …` of a real FFT
/// of length `len` at `sample_ns`: `T(k) = exp(−a·k²)` with `a = 2π²s² / (len·Δt)²` (`s` the
/// target's standard deviation, ns), by the exact recurrence `T(k+1) = T(k)·q_k`,
/// `q_{k+1} = q_k·exp(−2a)`: two `exp` per segment, not one per bin. Without a target every
/// gain is 1.
#[derive(Clone, Copy, Debug)]
struct TargetGain {
    /// `exp(−a)`, or 1 without a target.
    q0: f64,
    /// `exp(−2a)`, or 1 without a target.
    q_step: f64,
}

impl TargetGain {
    fn new(fwhm_ns: Option<f64>, len: usize, sample_ns: f64) -> Self {
        match fwhm_ns {
            Some(fwhm) if fwhm.is_finite() && fwhm > 0.0 => {
                let s = fwhm / (8.0 * std::f64::consts::LN_2).sqrt();
                let df = 1.0 / (len as f64 * sample_ns);
                let a = 2.0 * std::f64::consts::PI.powi(2) * s * s * df * df;
                TargetGain {
                    q0: (-a).exp(),
                    q_step: (-2.0 * a).exp(),
                }
            }
            _ => TargetGain {
                q0: 1.0,
                q_step: 1.0,
            },
        }
    }

    /// `T(0), T(1), …` in order.
    fn iter(self) -> impl Iterator<Item = f32> {
        let (mut t, mut q) = (1.0f64, self.q0);
        std::iter::repeat_with(move || {
            let v = t as f32;
            t *= q;
            q *= self.q_step;
            v
        })
    }
}

/// Smallest even `N ≥ min` whose prime factors are 2, 3 and 5.
pub(crate) fn fast_len(min: usize) -> usize {
    let mut n = min.max(2);
    loop {
        if n.is_multiple_of(2) {
            let mut r = n;
            for p in [2, 3, 5] {
                while r.is_multiple_of(p) {
                    r /= p;
                }
            }
            if r == 1 {
                return n;
            }
        }
        n += 1;
    }
}

impl Wiener {
    /// Builds the filter for segments of up to `max_samples` samples and kernels of up to
    /// `max_taps` taps (buffers sized for the largest padded length).
    pub fn new(config: WienerConfig, max_samples: usize, max_taps: usize) -> Self {
        let max_len = fast_len(max_samples + max_taps);
        let bins = max_len / 2 + 1;
        Wiener {
            config,
            max_samples,
            max_taps,
            planner: RealFftPlanner::new(),
            plans: Vec::with_capacity(8),
            time: vec![0.0; max_len],
            kernel_time: vec![0.0; max_len],
            spectrum: vec![Complex::new(0.0, 0.0); bins],
            kernel_spectrum: vec![Complex::new(0.0, 0.0); bins],
            scratch: vec![Complex::new(0.0, 0.0); max_len],
            cached_kernel: Vec::with_capacity(max_taps),
            cached_key: None,
        }
    }

    /// The configuration in force.
    pub fn config(&self) -> &WienerConfig {
        &self.config
    }

    fn plan_index(&mut self, len: usize) -> usize {
        if let Some(i) = self.plans.iter().position(|p| p.len == len) {
            return i;
        }
        let forward = self.planner.plan_fft_forward(len);
        let inverse = self.planner.plan_fft_inverse(len);
        let scratch_len = forward.get_scratch_len().max(inverse.get_scratch_len());
        if self.scratch.len() < scratch_len {
            self.scratch.resize(scratch_len, Complex::new(0.0, 0.0));
        }
        self.plans.push(Plan {
            len,
            forward,
            inverse,
            scratch_len,
        });
        self.plans.len() - 1
    }

    /// Number of cached FFT plans (for the no-allocation tests).
    #[cfg(test)]
    pub(crate) fn plan_count(&self) -> usize {
        self.plans.len()
    }
}

impl Deconvolver for Wiener {
    fn name(&self) -> &'static str {
        "wiener"
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let max_abs = check_inputs(y, k, out, self.max_samples, self.max_taps)?;
        let n = y.len();
        if n == 0 || max_abs <= 0.0 {
            out.fill(0.0);
            return Ok(MethodStats::default());
        }
        let m = k.taps.len();
        let len = fast_len(n + m);
        let plan_i = self.plan_index(len);
        let plan = &self.plans[plan_i];
        let bins = len / 2 + 1;
        let scale = max_abs as f64;
        let inv = 1.0 / scale;

        let time = &mut self.time[..len];
        normalise(y, max_abs, &mut time[..n]);
        time[n..].fill(0.0);
        let spectrum = &mut self.spectrum[..bins];
        let rs = &mut self.kernel_spectrum[..bins];
        let scratch = &mut self.scratch[..plan.scratch_len];
        // Lengths match the plan by construction; an error cannot occur.
        let _ = plan.forward.process_with_scratch(time, spectrum, scratch);
        let key = Some((k.center, len));
        if self.cached_key != key || self.cached_kernel != k.taps {
            let kt = &mut self.kernel_time[..len];
            kt.fill(0.0);
            for (j, &t) in k.taps.iter().enumerate() {
                // (j − center) mod len; len ≥ m > center.
                kt[(j + len - k.center) % len] = t;
            }
            let _ = plan.forward.process_with_scratch(kt, rs, scratch);
            self.cached_kernel.clear();
            self.cached_kernel.extend_from_slice(&k.taps);
            self.cached_key = key;
        }

        let noise_n = if noise_v.is_finite() {
            (noise_v.abs() as f64 * inv) as f32
        } else {
            0.0
        };
        let scale_noise = if self.config.noise_scale.is_finite() {
            self.config.noise_scale.max(0.0)
        } else {
            0.0
        };
        let n2 = scale_noise * n as f32 * noise_n * noise_n;
        let n2 = if n2.is_finite() { n2 } else { f32::MAX };
        let rho = if self.config.regularisation.is_finite() && self.config.regularisation > 0.0 {
            self.config.regularisation
        } else {
            default_regularisation()
        };
        let keep = self.config.cutoff_ghz * len as f64 * sample_ns;
        let first_zeroed = if keep.is_finite() && keep >= 0.0 {
            ((keep.floor() as usize).saturating_add(1)).min(bins)
        } else if keep.is_finite() {
            0
        } else {
            // NaN or infinite: keep everything (the stage validates the configuration).
            bins
        };
        let target = TargetGain::new(self.config.target_fwhm_ns, len, sample_ns);
        for ((s, r), t) in spectrum[..first_zeroed]
            .iter_mut()
            .zip(rs.iter())
            .zip(target.iter())
        {
            let p2 = s.norm_sqr();
            let r2 = r.norm_sqr();
            let den = p2 * (r2 + rho) + n2 * r2.max(rho);
            *s = if den > 0.0 && den.is_finite() {
                *s * r.conj() * (p2 / den * t)
            } else {
                Complex::new(0.0, 0.0)
            };
        }
        spectrum[first_zeroed..].fill(Complex::new(0.0, 0.0));
        spectrum[0].im = 0.0;
        spectrum[bins - 1].im = 0.0;
        let _ = plan.inverse.process_with_scratch(spectrum, time, scratch);
        // Finite: every bin is finite (guarded above) and `scale_out` clamps.
        scale_out(&time[..n], scale / len as f64, out);
        Ok(MethodStats::default())
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        self.config.worst_case_flops(n, m)
    }
}
