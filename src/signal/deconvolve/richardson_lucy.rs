//! Richardson-Lucy deconvolution: `σ_{i+1} = σ_i · (k ⋆ (y / (k ⊛ σ_i)))` (multiplicative,
//! non-negative, energy conserving for a unit-sum kernel away from the segment's edges).
//!
//! Details (all fixed, so the cost per segment is fixed by the configuration):
//!
//! - **Non-negative data**: RL is the maximum-likelihood iteration for Poisson counts and needs
//!   `y ≥ 0`; negative samples (noise below the baseline after baseline removal) are clipped to
//!   zero first.
//! - **Normalisation**: the clipped segment is divided by its maximum (computed in f64) and the
//!   result multiplied back at the end (RL is scale-equivariant, so this is exact). This makes
//!   the floors below relative and keeps denormal or full-scale (65535) inputs inside the f32
//!   range. A segment whose maximum is not positive deconvolves to zeros (0 iterations).
//! - **Start**: `σ_0 = max(y, 0) / max(y) + 10⁻³` — the data itself (close to the answer, so 20
//!   iterations go far) plus a small positive floor, because RL can never revive a bin that is
//!   exactly zero.
//! - **Guards**: the denominator `k ⊛ σ_i` is floored at `10⁻⁶ · max(y)` (bins where `y = 0`
//!   contribute a ratio of 0); the correction `k ⋆ ratio` is clipped at 0 (it can go negative
//!   only with a calibrated kernel that has negative lobes) and `σ` is capped at
//!   `10⁹ · max(y)` and values below `10⁻³⁰ · max(y)` are flushed to 0 (no denormal slow path).
//!   The output is therefore finite and non-negative.
//! - **Early stop** (optional): after an iteration whose relative L1 change
//!   `Σ|σ_{i+1} − σ_i| / Σσ_i` is below [`RlConfig::early_stop`].
//! - **Stop by the noise** (optional, [`RlConfig::stop_at_noise`] `= τ`; the discrepancy
//!   principle, Morozov): before the update of iteration `i` (`i = 0, 1, …`), the residual of
//!   the current estimate `r = y − k ⊛ σ_i` is taken over the samples given to the method (the
//!   whole segment, or one echo window of the gate: `gate.rs`), with `y` the data RL fits
//!   (negative samples clipped to 0, as above: against the unclipped data the non-negative
//!   `k ⊛ σ` leaves the mean of the clipped noise in every empty sample, and on a mostly empty
//!   segment the residual never came down to the noise level). When
//!   `√(Σr² / n) ≤ τ · noise_v` (`noise_v` the noise level passed to [`Deconvolver::run`], volts)
//!   the run stops and returns `σ_i`: the first iterate that explains the data to within the
//!   noise. `iterations` stays the hard cap (fixed worst-case latency); a `noise_v` that is not
//!   a positive finite number never stops a run. The residual comes from the convolution pass
//!   the iteration makes anyway (the ratio's epilogue sees `k ⊛ σ_i` and `y`): about `3·n`
//!   flops more per iteration, and a stop saves the correlation pass of that iteration.
//!   **What `noise_v` is**: after the denoise stage (pipeline, `fwlidar tradeoff`, `fwlidar
//!   process` without `--no-denoise`) it is the mean `|raw − baseline − smoothed|`, the noise
//!   *above* the low-pass cut-off `fc`: for white noise of standard deviation `s`,
//!   `√(2/π) · s · √(1 − fc/fN)` (`fN` the Nyquist frequency), while the noise left in the
//!   low-passed data RL sees has an RMS of `s · √(fc/fN)`. At the default 0.2 GHz and 1 ns the
//!   two agree within 2 % (0.618 s and 0.632 s), so `τ = 1` is the classical discrepancy
//!   principle (residual RMS = the data's noise RMS); at other cut-offs the ratio of the two is
//!   `√(fc/fN) / (√(2/π) · √(1 − fc/fN))` and `τ` should absorb it. With `fwlidar process
//!   --no-denoise`, `noise_v` is the robust standard deviation of the data's white noise, and
//!   `τ = 1` is again the classical rule.
//! - **Convolution**: direct, in the time domain (see the `direct` module: blocks of outputs
//!   kept in registers across all taps, AVX-512 or AVX2/FMA when the CPU has them). The ratio
//!   `y / (k ⊛ σ)` and (without early stop) the update of σ are computed from each block of
//!   sums while it is still in registers, so an iteration is two passes over the segment, not
//!   four; the results are the same bits as separate passes. An FFT would need four transforms per iteration (σ and the
//!   ratio forward, both back); for the kernels of this sensor class (≤ 64 taps) and segments of
//!   a few hundred samples the direct form is cheaper, so no FFT path is used (cost model:
//!   direct `4·n·m` flops per iteration against about `4 · 2.5·N·log₂N` for padded length
//!   `N ≥ n + m`; the FFT wins only beyond m ≈ 100 taps at n = 256).
//!
//! - **Acceleration** (optional, [`RlConfig::accelerate`]): the vector extrapolation of Biggs
//!   and Andrews (1997, "Acceleration of iterative image restoration algorithms", Applied
//!   Optics 36(8)). Each iteration applies the RL step not to the current estimate `x_k` but to
//!   the point predicted along the last change, `p_k = max(x_k + α_k (x_k − x_{k−1}), 0)`, and
//!   sets `x_{k+1} = RL(p_k)`; with `g_k = x_{k+1} − p_k` the RL step's own change,
//!   `α_{k+1} = Σ g_k·g_{k−1} / Σ g_{k−1}·g_{k−1}` clipped to `[0, 0.95]` (0 for the first two
//!   iterations). The cost per iteration is the same two convolutions plus about `10·n` flops;
//!   the estimate moves about as far in `k` accelerated iterations as plain RL in 2–3 `k`
//!   (measured with `fwlidar tradeoff`, docs/accuracy.md). The guards below apply to `p_k` and
//!   `x_{k+1}` alike, so the output stays finite and non-negative.
//!
//! Cost per segment: `iterations × (4·n·m + 8·n)` flops (`n` samples, `m` taps; about
//! `2·n` more per iteration accelerated).

use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::direct::{
    Epilogue, convolve_padded_with, correlate_padded, correlate_padded_with,
};
use crate::signal::deconvolve::{DeconvError, Deconvolver, MethodStats, check_inputs, scale_out};
use crate::signal::kernel::Kernel;

/// Positive floor added to the normalised start estimate (fraction of the segment maximum).
const START_FLOOR: f32 = 1e-3;
/// Floor of the re-blurred estimate in the ratio's denominator (fraction of the maximum).
const DENOMINATOR_FLOOR: f32 = 1e-6;
/// Cap on the normalised estimate.
const ESTIMATE_CAP: f32 = 1e9;
/// Normalised values below this are flushed to zero.
const FLUSH: f32 = 1e-30;

/// Settings of Richardson-Lucy (`method = "richardson_lucy"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RlConfig {
    /// Iterations per segment (the fixed budget). Default 20.
    #[serde(default = "default_iterations")]
    pub iterations: u32,
    /// Stop early once the relative L1 change of the estimate between two iterations falls
    /// below this (dimensionless, e.g. 1e-3). Default none: always run every iteration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub early_stop: Option<f32>,
    /// Biggs-Andrews vector extrapolation of the iterations (see the module documentation).
    /// Default false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub accelerate: bool,
    /// Stop by the noise (discrepancy principle, see the module documentation): stop before
    /// the first iteration whose estimate leaves a residual RMS `√(Σ(y − k ⊛ σ)² / n)` of at
    /// most this multiple of the segment's noise level `noise_v` (dimensionless, > 0; 1 is the
    /// classical rule at the default denoise cut-off). `iterations` stays the cap. Default
    /// none: always run every iteration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_at_noise: Option<f32>,
}

/// Largest extrapolation step of the accelerated iteration (dimensionless; below 1 so that
/// the extrapolation cannot run away on a segment where the changes stay aligned).
const MAX_ALPHA: f64 = 0.95;

fn default_iterations() -> u32 {
    20
}

impl RlConfig {
    /// Worst-case flops for a segment of `n` samples and a kernel of `m` taps:
    /// `iterations × (4·n·m + 8·n)` (per iteration one convolution and one correlation of
    /// `2·n·m` flops each, plus the ratio, product and early-stop sums), `10·n` more per
    /// iteration accelerated and `3·n` more with [`RlConfig::stop_at_noise`] (the residual).
    pub fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        let (n, m) = (n as u64, m as u64);
        let extra = if self.accelerate { 10 * n } else { 0 };
        let residual = if self.stop_at_noise.is_some() {
            3 * n
        } else {
            0
        };
        (self.iterations as u64).saturating_mul(4 * n * m + 8 * n + extra + residual)
    }
}

impl Default for RlConfig {
    fn default() -> Self {
        RlConfig {
            iterations: default_iterations(),
            early_stop: None,
            accelerate: false,
            stop_at_noise: None,
        }
    }
}

/// Richardson-Lucy with buffers sized once.
pub struct RichardsonLucy {
    config: RlConfig,
    max_samples: usize,
    max_taps: usize,
    /// Normalised, clipped data, `max_samples`.
    y: Vec<f32>,
    /// Padded estimate σ, `max_samples + 2·max_taps`.
    sigma: Vec<f32>,
    /// Padded ratio `y / (k ⊛ σ)`, `max_samples + 2·max_taps`.
    ratio: Vec<f32>,
    /// Correction `k ⋆ ratio`, `max_samples`.
    correction: Vec<f32>,
    /// Accelerated iteration: the estimate `x_k`, `max_samples` (empty when not accelerated).
    x: Vec<f32>,
    /// Accelerated iteration: the previous estimate `x_{k−1}`.
    x_prev: Vec<f32>,
    /// Accelerated iteration: the last RL change `g_{k−1}`.
    g_prev: Vec<f32>,
}

impl RichardsonLucy {
    /// Builds the method for segments of up to `max_samples` samples and kernels of up to
    /// `max_taps` taps.
    pub fn new(config: RlConfig, max_samples: usize, max_taps: usize) -> Self {
        let padded = max_samples + 2 * max_taps;
        let acc = if config.accelerate { max_samples } else { 0 };
        RichardsonLucy {
            config,
            max_samples,
            max_taps,
            y: vec![0.0; max_samples],
            sigma: vec![0.0; padded],
            ratio: vec![0.0; padded],
            correction: vec![0.0; max_samples],
            x: vec![0.0; acc],
            x_prev: vec![0.0; acc],
            g_prev: vec![0.0; acc],
        }
    }

    /// The configuration in force.
    pub fn config(&self) -> &RlConfig {
        &self.config
    }
}

/// Epilogue of the convolution `k ⊛ σ`: `ratio = y / max(k ⊛ σ, floor)` where `y > 0`, else 0.
struct Ratio<'a> {
    y: &'a [f32],
    ratio: &'a mut [f32],
}

impl Epilogue for Ratio<'_> {
    #[inline(always)]
    fn store(&mut self, i0: usize, acc: &[f32]) {
        let y = &self.y[i0..i0 + acc.len()];
        let ratio = &mut self.ratio[i0..i0 + acc.len()];
        for ((r, &b), &v) in ratio.iter_mut().zip(acc).zip(y) {
            // Branch-free (the sign of noisy data is unpredictable) so the loop vectorises:
            // the quotient is always computed, then selected.
            let q = v / b.max(DENOMINATOR_FLOOR);
            *r = if v > 0.0 { q } else { 0.0 };
        }
    }
}

/// One convolution pass: `ratio[pad..pad + n] = y / (k ⊛ σ)` (the [`Ratio`] epilogue), with
/// `σ` and `ratio` padded by `pad` zeros on both sides and `n = y.len()`.
#[inline(always)]
fn ratio_pass(sigma: &[f32], pad: usize, k: &Kernel, yn: &[f32], ratio: &mut [f32]) {
    let n = yn.len();
    convolve_padded_with(
        sigma,
        pad,
        &k.taps,
        k.center,
        n,
        Ratio {
            y: yn,
            ratio: &mut ratio[pad..pad + n],
        },
    );
}

/// Epilogue of the convolution `k ⊛ σ` with the stop by the noise: the [`Ratio`] (the same
/// bits), and the residual `Σ (y − k ⊛ σ)²` summed per lane.
struct RatioResidual<'a> {
    y: &'a [f32],
    ratio: &'a mut [f32],
    sums: &'a mut [f32; LANES],
}

impl Epilogue for RatioResidual<'_> {
    #[inline(always)]
    fn store(&mut self, i0: usize, acc: &[f32]) {
        let len = acc.len();
        let y = &self.y[i0..i0 + len];
        let ratio = &mut self.ratio[i0..i0 + len];
        let sums = &mut *self.sums;
        let mut one = |i: usize, l: usize| {
            let (b, v) = (acc[i], y[i]);
            let q = v / b.max(DENOMINATOR_FLOOR);
            ratio[i] = if v > 0.0 { q } else { 0.0 };
            let r = v - b;
            sums[l] += r * r;
        };
        let whole = len / LANES * LANES;
        for c in (0..whole).step_by(LANES) {
            for l in 0..LANES {
                one(c + l, l);
            }
        }
        for i in whole..len {
            one(i, i - whole);
        }
    }
}

/// The ratio pass, and with `stop` (the largest sum of squared residuals that stops) whether
/// the residual of the current estimate is within it.
#[inline(always)]
fn ratio_pass_checked(
    sigma: &[f32],
    pad: usize,
    k: &Kernel,
    yn: &[f32],
    ratio: &mut [f32],
    stop: Option<f64>,
) -> bool {
    let Some(limit) = stop else {
        ratio_pass(sigma, pad, k, yn, ratio);
        return false;
    };
    let n = yn.len();
    let mut sums = [0.0f32; LANES];
    convolve_padded_with(
        sigma,
        pad,
        &k.taps,
        k.center,
        n,
        RatioResidual {
            y: yn,
            ratio: &mut ratio[pad..pad + n],
            sums: &mut sums,
        },
    );
    sums.iter().map(|&v| v as f64).sum::<f64>() <= limit
}

/// Epilogue of the correlation `k ⋆ ratio` (no early stop): `σ ← flush(min(σ · max(c, 0),
/// cap))`.
struct Update<'a> {
    sigma: &'a mut [f32],
}

impl Epilogue for Update<'_> {
    #[inline(always)]
    fn store(&mut self, i0: usize, acc: &[f32]) {
        let sigma = &mut self.sigma[i0..i0 + acc.len()];
        for (s, &c) in sigma.iter_mut().zip(acc) {
            let new = (*s * c.max(0.0)).min(ESTIMATE_CAP);
            *s = if new < FLUSH { 0.0 } else { new };
        }
    }
}

/// Lanes of the accelerated update's partial sums (so that the reductions vectorise).
const LANES: usize = 8;

/// Partial sums of the accelerated update, per lane: `Σ g·g_prev`, `Σ g²`, `Σ|x_new − x|`,
/// `Σ x`.
#[derive(Default)]
struct AccSums {
    cross: [f32; LANES],
    norm: [f32; LANES],
    change: [f32; LANES],
    total: [f32; LANES],
}

impl AccSums {
    fn total(a: &[f32; LANES]) -> f64 {
        a.iter().map(|&v| v as f64).sum()
    }
}

/// Epilogue of the correlation `c = k ⋆ ratio` in the accelerated iteration:
/// `x_new = flush(min(p · max(c, 0), cap))`, `g = x_new − p`, the sums, then
/// `x_prev ← x`, `x ← x_new`, `g_prev ← g`.
struct AccUpdate<'a> {
    p: &'a [f32],
    x: &'a mut [f32],
    x_prev: &'a mut [f32],
    g_prev: &'a mut [f32],
    sums: &'a mut AccSums,
}

impl Epilogue for AccUpdate<'_> {
    #[inline(always)]
    fn store(&mut self, i0: usize, acc: &[f32]) {
        let len = acc.len();
        let p = &self.p[i0..i0 + len];
        let x = &mut self.x[i0..i0 + len];
        let xp = &mut self.x_prev[i0..i0 + len];
        let gp = &mut self.g_prev[i0..i0 + len];
        let s = &mut *self.sums;
        let mut one = |i: usize, l: usize| {
            let new = (p[i] * acc[i].max(0.0)).min(ESTIMATE_CAP);
            let new = if new < FLUSH { 0.0 } else { new };
            let g = new - p[i];
            s.cross[l] += g * gp[i];
            s.norm[l] += g * g;
            s.change[l] += (new - x[i]).abs();
            s.total[l] += x[i];
            gp[i] = g;
            xp[i] = x[i];
            x[i] = new;
        };
        let whole = len / LANES * LANES;
        for c in (0..whole).step_by(LANES) {
            for l in 0..LANES {
                one(c + l, l);
            }
        }
        for i in whole..len {
            one(i, i - whole);
        }
    }
}

/// The accelerated iteration (module documentation): `sigma` holds the predicted point `p_k`
/// (padded by `pad` zeros on both sides), `x` receives the estimate. `sigma[pad..pad + n]`
/// holds the start estimate on entry.
#[allow(clippy::too_many_arguments)]
fn accelerated(
    config: &RlConfig,
    yn: &[f32],
    k: &Kernel,
    pad: usize,
    [sigma, ratio]: [&mut [f32]; 2],
    [x, x_prev, g_prev]: [&mut [f32]; 3],
    stop: Option<f64>,
    stats: &mut MethodStats,
) {
    let n = yn.len();
    x.copy_from_slice(&sigma[pad..pad + n]);
    x_prev.copy_from_slice(x);
    g_prev.fill(0.0);
    let mut alpha = 0.0f64;
    let mut g_prev_norm = 0.0f64;
    for it in 0..config.iterations {
        // The predicted point p = max(x + α (x − x_prev), 0), guarded like σ.
        let a = alpha as f32;
        for ((p, &xi), &xp) in sigma[pad..pad + n]
            .iter_mut()
            .zip(x.iter())
            .zip(x_prev.iter())
        {
            let v = (xi + a * (xi - xp)).clamp(0.0, ESTIMATE_CAP);
            *p = if v < FLUSH { 0.0 } else { v };
        }
        if ratio_pass_checked(sigma, pad, k, yn, ratio, stop) {
            // The predicted point explains the data to within the noise: it is the answer.
            x.copy_from_slice(&sigma[pad..pad + n]);
            stats.stopped_early = true;
            break;
        }
        // x_{k+1} = RL(p) and g = x_{k+1} − p, formed in the correlation's epilogue.
        let mut sums = AccSums::default();
        correlate_padded_with(
            ratio,
            pad,
            &k.taps,
            k.center,
            n,
            AccUpdate {
                p: &sigma[pad..pad + n],
                x,
                x_prev,
                g_prev,
                sums: &mut sums,
            },
        );
        stats.iterations += 1;
        let (cross, norm) = (AccSums::total(&sums.cross), AccSums::total(&sums.norm));
        alpha = if it >= 1 && g_prev_norm > 0.0 {
            (cross / g_prev_norm).clamp(0.0, MAX_ALPHA)
        } else {
            0.0
        };
        if !alpha.is_finite() {
            alpha = 0.0;
        }
        g_prev_norm = norm;
        if let Some(tol) = config.early_stop
            && AccSums::total(&sums.change) <= tol as f64 * AccSums::total(&sums.total)
        {
            stats.stopped_early = stats.iterations < config.iterations;
            break;
        }
    }
}

impl Deconvolver for RichardsonLucy {
    fn name(&self) -> &'static str {
        "richardson_lucy"
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        _sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        check_inputs(y, k, out, self.max_samples, self.max_taps)?;
        let n = y.len();
        let peak = y.iter().fold(0.0f32, |a, &v| a.max(v));
        if n == 0 || peak <= 0.0 {
            out.fill(0.0);
            return Ok(MethodStats::default());
        }
        let m = k.taps.len();
        let pad = m;
        let scale = peak as f64;
        let inv = 1.0 / scale;
        let yn = &mut self.y[..n];
        for (d, &v) in yn.iter_mut().zip(y) {
            *d = (v.max(0.0) as f64 * inv) as f32;
        }
        // The stop by the noise: the largest sum of squared residuals (normalised units) that
        // stops, `n · (τ · noise_v / max)²`; none without a usable noise level.
        let stop = self.config.stop_at_noise.and_then(|tau| {
            let level = tau as f64 * noise_v as f64 * inv;
            (level.is_finite() && level > 0.0).then_some(n as f64 * level * level)
        });
        let sigma = &mut self.sigma[..n + 2 * pad];
        let ratio = &mut self.ratio[..n + 2 * pad];
        sigma.fill(0.0);
        ratio.fill(0.0);
        for (s, &v) in sigma[pad..pad + n].iter_mut().zip(yn.iter()) {
            *s = v + START_FLOOR;
        }
        let correction = &mut self.correction[..n];
        let mut stats = MethodStats::default();
        if self.config.accelerate {
            let (x, x_prev, g_prev) = (
                &mut self.x[..n],
                &mut self.x_prev[..n],
                &mut self.g_prev[..n],
            );
            accelerated(
                &self.config,
                yn,
                k,
                pad,
                [sigma, ratio],
                [x, x_prev, g_prev],
                stop,
                &mut stats,
            );
            scale_out(&self.x[..n], scale, out);
            return Ok(stats);
        }
        for _ in 0..self.config.iterations {
            // The ratio y / (k ⊛ σ) is formed from each block of sums while it is in
            // registers (with the stop by the noise, the residual too: σ is the answer when
            // it is within the noise).
            if ratio_pass_checked(sigma, pad, k, yn, ratio, stop) {
                stats.stopped_early = true;
                break;
            }
            stats.iterations += 1;
            let Some(tol) = self.config.early_stop else {
                // No early stop: σ is updated from each block of the correction `k ⋆ ratio`
                // while it is in registers (the correlation reads only the ratio).
                correlate_padded_with(
                    ratio,
                    pad,
                    &k.taps,
                    k.center,
                    n,
                    Update {
                        sigma: &mut sigma[pad..pad + n],
                    },
                );
                continue;
            };
            correlate_padded(ratio, pad, &k.taps, k.center, correction);
            let mut change = 0.0f32;
            let mut total = 0.0f32;
            for (s, &c) in sigma[pad..pad + n].iter_mut().zip(correction.iter()) {
                let mut new = (*s * c.max(0.0)).min(ESTIMATE_CAP);
                if new < FLUSH {
                    new = 0.0;
                }
                change += (new - *s).abs();
                total += *s;
                *s = new;
            }
            if change <= tol * total {
                stats.stopped_early = stats.iterations < self.config.iterations;
                break;
            }
        }
        scale_out(&sigma[pad..pad + n], scale, out);
        Ok(stats)
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        self.config.worst_case_flops(n, m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::deconvolve::direct::convolve_padded;

    /// The fused iteration (ratio and update formed in the convolution's epilogues) gives the
    /// same bits as the plain three-pass iteration it replaced.
    #[test]
    fn fused_iteration_matches_the_three_pass_reference_bit_for_bit() {
        let sigma_k = 16.0f32 / 2.354_82;
        let taps: Vec<f32> = (0..41)
            .map(|j| (-0.5 * ((j as f32 - 20.0) / sigma_k).powi(2)).exp())
            .collect();
        let mut k = Kernel::default();
        k.set_from_taps(&taps, 20, 64).unwrap();
        for n in [7usize, 100, 256, 300] {
            let y: Vec<f32> = (0..n)
                .map(|i| {
                    let d = (i as f32 - n as f32 * 0.4) / 5.0;
                    (-0.5 * d * d).exp() + 0.01 * (((i * 7919) % 13) as f32 - 6.0)
                })
                .collect();
            let mut out = vec![0.0f32; n];
            RichardsonLucy::new(RlConfig::default(), 512, 64)
                .run(&y, &k, 0.0, 1.0, &mut out)
                .unwrap();
            // Reference: the unfused iteration.
            let m = k.len();
            let pad = m;
            let peak = y.iter().fold(0.0f32, |a, &v| a.max(v)) as f64;
            let yn: Vec<f32> = y
                .iter()
                .map(|&v| (v.max(0.0) as f64 / peak) as f32)
                .collect();
            let mut sigma = vec![0.0f32; n + 2 * pad];
            let mut ratio = vec![0.0f32; n + 2 * pad];
            for (s, &v) in sigma[pad..pad + n].iter_mut().zip(&yn) {
                *s = v + START_FLOOR;
            }
            let (mut blurred, mut corr) = (vec![0.0f32; n], vec![0.0f32; n]);
            for _ in 0..20 {
                convolve_padded(&sigma, pad, &k.taps, k.center, &mut blurred);
                for i in 0..n {
                    ratio[pad + i] = if yn[i] > 0.0 {
                        yn[i] / blurred[i].max(DENOMINATOR_FLOOR)
                    } else {
                        0.0
                    };
                }
                correlate_padded(&ratio, pad, &k.taps, k.center, &mut corr);
                for i in 0..n {
                    let new = (sigma[pad + i] * corr[i].max(0.0)).min(ESTIMATE_CAP);
                    sigma[pad + i] = if new < FLUSH { 0.0 } else { new };
                }
            }
            let mut expect = vec![0.0f32; n];
            scale_out(&sigma[pad..pad + n], peak, &mut expect);
            for (a, b) in out.iter().zip(&expect) {
                assert_eq!(a.to_bits(), b.to_bits(), "n = {n}");
            }
        }
    }
}
