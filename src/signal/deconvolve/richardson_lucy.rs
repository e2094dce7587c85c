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
//! - **Coarse-to-fine start** (optional, [`RlConfig::coarse_iterations`] `> 0`): with a
//!   kernel whose FWHM spans `D ≥ 2` times [`RlConfig::coarse_fwhm_samples`] samples
//!   (`D = ⌊FWHM_k / coarse_fwhm_samples⌋`, at most [`MAX_DECIMATION`]), RL first runs
//!   `coarse_iterations` times on a grid `D` times coarser: the data's block means
//!   `y_c[J] = (1/D) Σ_l y[D·J + l]` (samples past the segment count as 0), deconvolved by
//!   the kernel exact for estimates constant on the blocks,
//!   `k_c[e] = (1/D) Σ_{|u|<D} (D − |u|) · k(D·e + u)` (`k(δ)` the tap at delay δ, negative
//!   taps clipped, unit sum), from `y_c + 10⁻³`, without the stop by the noise. The coarse
//!   estimate, interpolated linearly between block centres (constant past the ends) plus the
//!   start floor, replaces the data as the start of the `iterations` on the sample grid; with
//!   [`RlConfig::accelerate`] both stages are accelerated. Why: RL's progress per iteration at
//!   a given frequency depends on the kernel's response there, not on the sampling, so a
//!   coarse iteration moves the estimate about as far as a fine one at a `D²`-th of the
//!   flops; the fine iterations then restore what the blocks cannot hold. The gain is for
//!   wide kernels (16 ns FWHM at 1 ns: `D = 3` at the default 4 samples); a kernel narrower
//!   than twice the coarse FWHM skips the stage (same bits as without). Measured with
//!   `fwlidar tradeoff` (docs/accuracy.md): at 16 ns, 50 coarse + 10 fine iterations come
//!   within 0.001 of RL-50 (RMSE 0.079 / 0.054 against 0.078 / 0.053, sparse / extended);
//!   in practice a coarse iteration on a short segment costs about a
//!   quarter of a fine one, not `1/D²` (fixed per-pass overheads). `MethodStats::iterations`
//!   counts the fine iterations only.
//!
//! - **Wiener start** (optional, [`RlConfig::wiener_start`]): the iterations start from the
//!   estimate of a Wiener filter fused with the low-pass (`wiener.rs`; with its
//!   `target_fwhm_ns` the estimate as seen by a Gaussian target pulse, multiplied into the
//!   filter, no extra FFT), negative values clipped, normalised, plus the start floor. The
//!   linear filter has already done most of the sharpening RL spends its first iterations on,
//!   so fewer iterations reach RL 20's accuracy; a target wider than the truth's pulse keeps
//!   the start from carrying noise spikes into the iterations (fewer false peaks). Cost: one
//!   FFT pair of length `fast_len(n + m)` per segment or echo window plus one FFT of the
//!   kernel when it changes (cached while the outgoing pulse repeats bit for bit).
//! - **Noise floor of the output** (optional, [`RlConfig::floor_noise`] `= κ`): estimates below
//!   `κ · noise_v` are set to 0 after the iterations, so ripples the noise leaves in an empty
//!   stretch are not peaks downstream. Not energy conserving (what is floored is lost).
//!
//! Cost per segment: `iterations × (4·n·m + 8·n)` flops (`n` samples, `m` taps; about
//! `2·n` more per iteration accelerated).

use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::direct::{
    Epilogue, convolve_padded_with, correlate_padded, correlate_padded_with,
};
use crate::signal::deconvolve::wiener::{Wiener, WienerConfig};
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
    /// Coarse-to-fine start (see the module documentation): this many RL iterations on a
    /// grid decimated so that the kernel spans about [`RlConfig::coarse_fwhm_samples`] coarse
    /// samples, whose result, interpolated back, is the start of the `iterations` on the
    /// sample grid. 0 (default): start from the data. At most 1000.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub coarse_iterations: u32,
    /// Kernel FWHM aimed at on the coarse grid, samples of that grid (finite, ≥ 1; default
    /// 4): the decimation factor is `⌊FWHM_k / coarse_fwhm_samples⌋` clamped to
    /// `1..=`[`MAX_DECIMATION`] (`FWHM_k` the kernel's RMS width × 2.3548, in samples); a
    /// factor of 1 (a kernel narrower than twice this) skips the coarse stage.
    #[serde(default = "default_coarse_fwhm")]
    pub coarse_fwhm_samples: f32,
    /// Warm start (see the module documentation): the iterations start from this Wiener
    /// filter's estimate of the segment (negative values clipped) instead of the data; one
    /// FFT pair (and the kernel's FFT when the kernel changes) replaces the many iterations
    /// RL spends sharpening the data. Excludes `coarse_iterations`. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wiener_start: Option<WienerConfig>,
    /// Noise floor of the output (see the module documentation): estimates below this
    /// multiple of the segment's noise level `noise_v` are set to 0 (dimensionless, > 0), so
    /// that ripples the noise leaves are not taken for returns downstream. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub floor_noise: Option<f32>,
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

fn default_coarse_fwhm() -> f32 {
    4.0
}

/// Largest decimation factor of the coarse-to-fine start.
pub const MAX_DECIMATION: usize = 8;
/// Largest [`RlConfig::coarse_iterations`].
pub const MAX_COARSE_ITERATIONS: u32 = 1000;

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
        let fine = (self.iterations as u64).saturating_mul(4 * n * m + 8 * n + extra + residual);
        let fine = match &self.wiener_start {
            Some(w) => fine.saturating_add(w.worst_case_flops(n as usize, m as usize) + 2 * n),
            None => fine,
        };
        if self.coarse_iterations == 0 {
            return fine;
        }
        // The coarse stage at its most expensive factor, 2: `⌈n/2⌉` samples, at most
        // `⌊m/2⌋ + 3` taps; plus the decimation, the coarse kernel and the interpolation.
        let (nc, mc) = (n.div_ceil(2), m / 2 + 3);
        let coarse = (self.coarse_iterations as u64).saturating_mul(4 * nc * mc + 8 * nc);
        fine.saturating_add(coarse)
            .saturating_add(4 * n + 4 * m * MAX_DECIMATION as u64)
    }
}

impl Default for RlConfig {
    fn default() -> Self {
        RlConfig {
            iterations: default_iterations(),
            early_stop: None,
            accelerate: false,
            stop_at_noise: None,
            coarse_iterations: 0,
            coarse_fwhm_samples: default_coarse_fwhm(),
            wiener_start: None,
            floor_noise: None,
        }
    }
}

impl RlConfig {
    /// The on-board setting (`config/onboard.toml`): 12 iterations from a Wiener start
    /// delivering the estimate as seen by a 4 ns target (noise scale 2), output floor at 5.5
    /// noise levels. Chosen with `fwlidar tradeoff --chain` to be no worse than 20 plain
    /// iterations on eq. 14 RMSE, true detections and false peaks per pulse at three noise
    /// levels (docs/accuracy.md, "The on-board chain", with the scenes where it is not).
    pub fn onboard() -> Self {
        RlConfig {
            iterations: 12,
            wiener_start: Some(WienerConfig {
                noise_scale: 2.0,
                target_fwhm_ns: Some(4.0),
                ..WienerConfig::default()
            }),
            floor_noise: Some(5.5),
            ..RlConfig::default()
        }
    }
}

/// Samples of the coarse grid's buffers for segments of up to `max_samples` (0 without the
/// coarse stage): `⌈n/D⌉ ≤ n/2 + 1` at factor `D ≥ 2`.
fn coarse_n_of(max_samples: usize, coarse: bool) -> usize {
    if coarse { max_samples / 2 + 1 } else { 0 }
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
    /// Coarse stage (empty without it): the decimated data.
    coarse_y: Vec<f32>,
    /// Coarse stage: padded estimate.
    coarse_sigma: Vec<f32>,
    /// Coarse stage: padded ratio.
    coarse_ratio: Vec<f32>,
    /// Coarse stage: the decimated kernel (capacity `max_taps + 4`).
    coarse_kernel: Kernel,
    /// Coarse stage, accelerated: `x`, `x_prev`, `g_prev` (empty when not accelerated).
    coarse_acc: [Vec<f32>; 3],
    /// Warm start: the Wiener filter and its estimate, volts, `max_samples` (none without).
    wiener: Option<(Box<Wiener>, Vec<f32>)>,
}

impl RichardsonLucy {
    /// Builds the method for segments of up to `max_samples` samples and kernels of up to
    /// `max_taps` taps.
    pub fn new(config: RlConfig, max_samples: usize, max_taps: usize) -> Self {
        let padded = max_samples + 2 * max_taps;
        let acc = if config.accelerate { max_samples } else { 0 };
        // Coarse buffers: at factor D ≥ 2, `⌈n/D⌉ ≤ n/2 + 1` samples and `m/D + 3 ≤ m/2 + 3`
        // taps, padded by the taps on both sides.
        let coarse = config.coarse_iterations > 0;
        let coarse_acc = if config.accelerate {
            coarse_n_of(max_samples, coarse)
        } else {
            0
        };
        let coarse_n = coarse_n_of(max_samples, coarse);
        let coarse_padded = if coarse {
            coarse_n + 2 * (max_taps / 2 + 4)
        } else {
            0
        };
        let wiener = config.wiener_start.clone().map(|w| {
            (
                Box::new(Wiener::new(w, max_samples, max_taps)),
                vec![0.0; max_samples],
            )
        });
        RichardsonLucy {
            max_samples,
            max_taps,
            y: vec![0.0; max_samples],
            sigma: vec![0.0; padded],
            ratio: vec![0.0; padded],
            correction: vec![0.0; max_samples],
            x: vec![0.0; acc],
            x_prev: vec![0.0; acc],
            g_prev: vec![0.0; acc],
            coarse_y: vec![0.0; coarse_n],
            coarse_sigma: vec![0.0; coarse_padded],
            coarse_ratio: vec![0.0; coarse_padded],
            coarse_kernel: Kernel::with_capacity(if coarse { max_taps + 4 } else { 0 }),
            coarse_acc: std::array::from_fn(|_| vec![0.0; coarse_acc]),
            wiener,
            config,
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

/// Plain RL iterations on padded buffers (`pad` zeros either side of the `n = yn.len()`
/// samples): `sigma[pad..pad + n]` holds the start on entry and the estimate on return.
#[allow(clippy::too_many_arguments)]
fn plain(
    iterations: u32,
    early_stop: Option<f32>,
    yn: &[f32],
    k: &Kernel,
    pad: usize,
    [sigma, ratio, correction]: [&mut [f32]; 3],
    stop: Option<f64>,
    stats: &mut MethodStats,
) {
    let n = yn.len();
    for _ in 0..iterations {
        // The ratio y / (k ⊛ σ) is formed from each block of sums while it is in
        // registers (with the stop by the noise, the residual too: σ is the answer when
        // it is within the noise).
        if ratio_pass_checked(sigma, pad, k, yn, ratio, stop) {
            stats.stopped_early = true;
            break;
        }
        stats.iterations += 1;
        let Some(tol) = early_stop else {
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
            stats.stopped_early = stats.iterations < iterations;
            break;
        }
    }
}

/// The buffers of the coarse stage.
struct CoarseBuffers<'a> {
    /// `x`, `x_prev`, `g_prev` of the accelerated iteration (each at least `⌈n/D⌉` long when
    /// accelerated).
    acc: &'a mut [Vec<f32>; 3],
    y: &'a mut [f32],
    sigma: &'a mut [f32],
    ratio: &'a mut [f32],
    kernel: &'a mut Kernel,
}

/// Decimation factor of the coarse stage for kernel `k`: `⌊FWHM_k / target⌋` clamped to
/// `1..=MAX_DECIMATION`, with `FWHM_k = 2.3548 ×` the RMS width of the kernel's non-negative
/// part about its centroid (samples). 1 for a kernel without positive energy.
pub fn decimation_factor(k: &Kernel, coarse_fwhm_samples: f32) -> usize {
    let (mut s0, mut s1, mut s2) = (0.0f64, 0.0f64, 0.0f64);
    for (j, &t) in k.taps.iter().enumerate() {
        let (t, j) = (t.max(0.0) as f64, j as f64);
        s0 += t;
        s1 += t * j;
        s2 += t * j * j;
    }
    if s0 <= 0.0 || !(coarse_fwhm_samples.is_finite() && coarse_fwhm_samples >= 1.0) {
        return 1;
    }
    let mean = s1 / s0;
    let var = (s2 / s0 - mean * mean).max(0.0);
    let fwhm = 2.354_82 * var.sqrt();
    let d = (fwhm / coarse_fwhm_samples as f64).floor();
    if d.is_finite() {
        (d as usize).clamp(1, MAX_DECIMATION)
    } else {
        1
    }
}

/// Sets `c` to kernel `k` on the grid decimated by `d` (module documentation):
/// `k_c[e] = (1/d) Σ_{|u|<d} (d − |u|) · max(k(d·e + u), 0)`, `k(δ)` the tap at delay `δ`,
/// normalised to unit sum. False when it does not fit `max_taps` or has no energy.
fn decimate_kernel(k: &Kernel, d: usize, c: &mut Kernel, max_taps: usize) -> bool {
    let (m, center, di) = (k.taps.len() as i64, k.center as i64, d as i64);
    // Delays e with some d·e + u in [−center, m − 1 − center], |u| < d.
    let e_min = -((center + di - 1).div_euclid(di));
    let e_max = (m - 2 - center + di).div_euclid(di);
    let len = (e_max - e_min + 1) as usize;
    if len > max_taps || len == 0 {
        return false;
    }
    c.taps.clear();
    let mut sum = 0.0f64;
    for e in e_min..=e_max {
        let mut acc = 0.0f64;
        for u in (1 - di)..di {
            let j = center + di * e + u;
            if (0..m).contains(&j) {
                acc += (di - u.abs()) as f64 * k.taps[j as usize].max(0.0) as f64;
            }
        }
        sum += acc;
        c.taps.push(acc as f32);
    }
    if sum <= 0.0 {
        return false;
    }
    for t in c.taps.iter_mut() {
        *t = (*t as f64 / sum) as f32;
    }
    c.center = (-e_min) as usize;
    true
}

/// The coarse-to-fine start (module documentation): when the configuration asks for it and
/// the kernel is wide enough (factor ≥ 2), runs the coarse iterations and writes their result,
/// interpolated to the sample grid plus the start floor, into `start` (`n` samples); returns
/// whether it did. Allocates nothing.
fn coarse_start(
    config: &RlConfig,
    yn: &[f32],
    k: &Kernel,
    b: CoarseBuffers<'_>,
    start: &mut [f32],
) -> bool {
    if config.coarse_iterations == 0 {
        return false;
    }
    let d = decimation_factor(k, config.coarse_fwhm_samples);
    let n = yn.len();
    let nc = n.div_ceil(d);
    if d < 2 || nc < 2 || nc > b.y.len() {
        return false;
    }
    let max_taps = b.kernel.taps.capacity();
    if !decimate_kernel(k, d, b.kernel, max_taps) {
        return false;
    }
    let pad = b.kernel.taps.len();
    if nc + 2 * pad > b.sigma.len() {
        return false;
    }
    // Block means (samples past the segment count as 0, as in the zero-padded convolution).
    let inv_d = 1.0 / d as f32;
    let yc = &mut b.y[..nc];
    for (j, c) in yc.iter_mut().enumerate() {
        let end = ((j + 1) * d).min(n);
        *c = yn[j * d..end].iter().sum::<f32>() * inv_d;
    }
    let sigma = &mut b.sigma[..nc + 2 * pad];
    let ratio = &mut b.ratio[..nc + 2 * pad];
    sigma.fill(0.0);
    ratio.fill(0.0);
    for (s, &v) in sigma[pad..pad + nc].iter_mut().zip(yc.iter()) {
        *s = v + START_FLOOR;
    }
    let mut stats = MethodStats::default();
    let coarse_config = RlConfig {
        iterations: config.coarse_iterations,
        early_stop: None,
        ..RlConfig::default()
    };
    let est: &[f32] = if config.accelerate {
        let [x, x_prev, g_prev] = &mut *b.acc;
        if x.len() < nc || x_prev.len() < nc || g_prev.len() < nc {
            return false;
        }
        let (x, x_prev, g_prev) = (&mut x[..nc], &mut x_prev[..nc], &mut g_prev[..nc]);
        accelerated(
            &coarse_config,
            yc,
            b.kernel,
            pad,
            [sigma, ratio],
            [x, x_prev, g_prev],
            None,
            &mut stats,
        );
        &b.acc[0][..nc]
    } else {
        // The correction buffer is used only with an early stop, which the coarse stage has
        // not.
        plain(
            config.coarse_iterations,
            None,
            yc,
            b.kernel,
            pad,
            [sigma, ratio, &mut []],
            None,
            &mut stats,
        );
        &sigma[pad..pad + nc]
    };
    // Linear interpolation between block centres `d·J + (d − 1)/2`, constant past the ends.
    let half = (d as f32 - 1.0) * 0.5;
    for (i, s) in start.iter_mut().enumerate() {
        let t = ((i as f32 - half) * inv_d).max(0.0);
        let j0 = (t as usize).min(nc - 1);
        let j1 = (j0 + 1).min(nc - 1);
        let f = (t - j0 as f32).clamp(0.0, 1.0);
        *s = est[j0] + f * (est[j1] - est[j0]) + START_FLOOR;
    }
    true
}

/// The output's noise floor ([`RlConfig::floor_noise`] `= κ`): estimates below `κ · noise_v`
/// (volts) set to 0; nothing without a floor or a usable noise level.
fn floor_at_noise(kappa: Option<f32>, noise_v: f32, out: &mut [f32]) {
    let Some(kappa) = kappa else { return };
    let floor = kappa * noise_v;
    if floor.is_finite() && floor > 0.0 {
        for o in out.iter_mut() {
            if *o < floor {
                *o = 0.0;
            }
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
        sample_ns: f64,
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
        let coarse = CoarseBuffers {
            acc: &mut self.coarse_acc,
            y: &mut self.coarse_y,
            sigma: &mut self.coarse_sigma,
            ratio: &mut self.coarse_ratio,
            kernel: &mut self.coarse_kernel,
        };
        if let Some((wiener, start)) = &mut self.wiener {
            // Warm start: the Wiener estimate, clipped, normalised, plus the floor.
            let start = &mut start[..n];
            wiener.run(y, k, noise_v, sample_ns, start)?;
            for (s, &v) in sigma[pad..pad + n].iter_mut().zip(start.iter()) {
                *s = (v.max(0.0) as f64 * inv) as f32 + START_FLOOR;
            }
        } else if !coarse_start(&self.config, yn, k, coarse, &mut sigma[pad..pad + n]) {
            for (s, &v) in sigma[pad..pad + n].iter_mut().zip(yn.iter()) {
                *s = v + START_FLOOR;
            }
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
            floor_at_noise(self.config.floor_noise, noise_v, out);
            return Ok(stats);
        }
        plain(
            self.config.iterations,
            self.config.early_stop,
            yn,
            k,
            pad,
            [sigma, ratio, correction],
            stop,
            &mut stats,
        );
        scale_out(&sigma[pad..pad + n], scale, out);
        floor_at_noise(self.config.floor_noise, noise_v, out);
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
    use crate::signal::kernel::convolve_same;

    fn gaussian(fwhm_ns: f64) -> Kernel {
        let mut k = Kernel::default();
        k.set_gaussian(fwhm_ns, 1.0).unwrap();
        k
    }

    /// Two echoes 6 ns apart blurred by an 8 ns pulse with deterministic ±1 % ripple noise:
    /// `(truth, data)`.
    fn close_pair(k: &Kernel) -> (Vec<f32>, Vec<f32>) {
        let n = 160;
        let mut truth = vec![0.0f32; n];
        truth[70] = 1.0;
        truth[76] = 0.6;
        let mut y = vec![0.0f32; n];
        convolve_same(&truth, k, &mut y);
        for (i, v) in y.iter_mut().enumerate() {
            *v += 0.01 * ((i as f32 * 2.3).sin());
        }
        (truth, y)
    }

    fn run(config: RlConfig, y: &[f32], k: &Kernel, noise_v: f32) -> Vec<f32> {
        let mut rl = RichardsonLucy::new(config, 256, 64);
        let mut out = vec![0.0f32; y.len()];
        rl.run(y, k, noise_v, 1.0, &mut out).unwrap();
        out
    }

    /// The Wiener start replaces the data as the start (the result differs from RL from the
    /// data); what follows are RL iterations: finite, non-negative, energy conserving. Its
    /// accuracy is the sweep's to show (`eval::tradeoff` test
    /// `the_on_board_setting_is_no_worse_than_rl20_on_the_sweep`).
    #[test]
    fn the_wiener_start_is_where_the_iterations_begin() {
        let k = gaussian(8.0);
        let (_, y) = close_pair(&k);
        let plain = run(
            RlConfig {
                iterations: 12,
                ..RlConfig::default()
            },
            &y,
            &k,
            0.01,
        );
        let started = run(
            RlConfig {
                floor_noise: None,
                ..RlConfig::onboard()
            },
            &y,
            &k,
            0.01,
        );
        let differs = plain
            .iter()
            .zip(&started)
            .any(|(a, b)| (a - b).abs() > 1e-3);
        assert!(differs, "the start changed nothing");
        assert!(started.iter().all(|v| v.is_finite() && *v >= 0.0));
        let (sy, so): (f64, f64) = (
            y.iter().map(|&v| v.max(0.0) as f64).sum(),
            started.iter().map(|&v| v as f64).sum(),
        );
        assert!((so / sy - 1.0).abs() < 0.02, "{so} against {sy}");
    }

    #[test]
    fn the_noise_floor_zeroes_what_is_below_it_and_keeps_the_rest() {
        let k = gaussian(8.0);
        let (_, y) = close_pair(&k);
        let noise_v = 0.01;
        let without = run(RlConfig::default(), &y, &k, noise_v);
        let with = run(
            RlConfig {
                floor_noise: Some(5.5),
                ..RlConfig::default()
            },
            &y,
            &k,
            noise_v,
        );
        let floor = 5.5 * noise_v;
        assert!(
            without.iter().any(|&v| v > 0.0 && v < floor),
            "nothing to floor"
        );
        for (&a, &b) in without.iter().zip(&with) {
            if a < floor {
                assert_eq!(b, 0.0);
            } else {
                assert_eq!(a, b);
            }
        }
        // Without a usable noise level the floor does nothing.
        let no_noise = run(
            RlConfig {
                floor_noise: Some(5.5),
                ..RlConfig::default()
            },
            &y,
            &k,
            f32::NAN,
        );
        assert_eq!(no_noise, without);
    }

    #[test]
    fn decimation_factor_follows_the_kernel_width() {
        // 4 ns: FWHM / 4 ≈ 1 → no coarse stage; 8 ns / 3 ≈ 2.7 → 2; 16 ns / 3 ≈ 5.3 → 5;
        // 40 ns / 1 → clamped to the largest factor.
        assert_eq!(decimation_factor(&gaussian(4.0), 4.0), 1);
        assert_eq!(decimation_factor(&gaussian(8.0), 3.0), 2);
        assert_eq!(decimation_factor(&gaussian(16.0), 3.0), 5);
        assert_eq!(decimation_factor(&gaussian(40.0), 1.0), MAX_DECIMATION);
        // No positive energy, or a bad target: 1.
        let mut k = Kernel::default();
        k.set_from_taps(&[-1.0, 3.0, -1.0], 1, 8).unwrap();
        assert_eq!(decimation_factor(&k, 0.5), 1);
        assert_eq!(decimation_factor(&gaussian(16.0), f32::NAN), 1);
    }

    /// The decimated kernel is exact for estimates constant on the coarse blocks: the block
    /// means of `k ⊛ σ` are `k_c ⊛ σ_c` (model of the coarse stage), for an off-centre kernel
    /// too.
    #[test]
    fn decimated_kernel_maps_block_constant_estimates_exactly() {
        let skewed: Vec<f32> = (0..23)
            .map(|j| ((j as f32) * 0.3).sin().abs() + 0.1)
            .collect();
        let mut k_skewed = Kernel::default();
        k_skewed.set_from_taps(&skewed, 5, 64).unwrap();
        for (k, d) in [(gaussian(16.0), 4usize), (gaussian(8.0), 2), (k_skewed, 3)] {
            let mut kc = Kernel::with_capacity(64);
            assert!(decimate_kernel(&k, d, &mut kc, 64));
            let sum: f32 = kc.taps.iter().sum();
            assert!((sum - 1.0).abs() < 1e-5, "{sum}");
            let nc = 40;
            let sc: Vec<f32> = (0..nc)
                .map(|j| {
                    if j % 7 == 3 {
                        1.0 + j as f32 * 0.1
                    } else {
                        0.0
                    }
                })
                .collect();
            let fine: Vec<f32> = (0..nc * d).map(|i| sc[i / d]).collect();
            let mut blurred = vec![0.0f32; nc * d];
            convolve_same(&fine, &k, &mut blurred);
            let mut coarse = vec![0.0f32; nc];
            convolve_same(&sc, &kc, &mut coarse);
            for j in 0..nc {
                let mean: f32 = blurred[j * d..(j + 1) * d].iter().sum::<f32>() / d as f32;
                assert!(
                    (mean - coarse[j]).abs() < 1e-5,
                    "d {d} block {j}: {mean} vs {}",
                    coarse[j]
                );
            }
        }
    }

    /// A kernel too narrow for a factor of 2 skips the coarse stage (same bits as without);
    /// on a wide kernel the coarse start brings RL closer to the truth for the same fine
    /// iterations, with a finite, non-negative output.
    #[test]
    fn coarse_start_is_skipped_for_narrow_kernels_and_helps_wide_ones() {
        let n = 225;
        let truth: Vec<f32> = (0..n)
            .map(|i| {
                let g = |c: f32, a: f32| a * (-0.5 * ((i as f32 - c) / 0.85).powi(2)).exp();
                g(60.0, 1.0) + g(71.0, 0.6) + g(140.0, 0.8)
            })
            .collect();
        let run = |k: &Kernel, coarse_iterations: u32| {
            let mut y = vec![0.0f32; n];
            convolve_same(&truth, k, &mut y);
            for (i, v) in y.iter_mut().enumerate() {
                *v += 0.005 * (((i * 7919) % 13) as f32 - 6.0) / 6.0;
            }
            let mut out = vec![0.0f32; n];
            let config = RlConfig {
                iterations: 10,
                coarse_iterations,
                ..RlConfig::default()
            };
            RichardsonLucy::new(config, 256, 64)
                .run(&y, k, 0.0, 1.0, &mut out)
                .unwrap();
            out
        };
        let narrow = gaussian(4.0);
        let (a, b) = (run(&narrow, 0), run(&narrow, 50));
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        let wide = gaussian(16.0);
        let err = |o: &[f32]| -> f32 {
            (o.iter()
                .zip(&truth)
                .map(|(x, t)| (x - t).powi(2))
                .sum::<f32>()
                / n as f32)
                .sqrt()
        };
        let (plain, coarse) = (run(&wide, 0), run(&wide, 50));
        assert!(coarse.iter().all(|v| v.is_finite() && *v >= 0.0));
        assert!(
            err(&coarse) < 0.97 * err(&plain),
            "coarse {} vs plain {}",
            err(&coarse),
            err(&plain)
        );
    }

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
