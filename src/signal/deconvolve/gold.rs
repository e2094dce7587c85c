//! Gold deconvolution (Gold's ratio method as used by Morháč and the waveformlidar R package):
//!
//! ```text
//! b = max(Kᵀ y, 0)                       (Kᵀ: correlation with the kernel, k ⋆ ·)
//! σ_{i+1} = σ_i · b / (Kᵀ K σ_i)          (iterations per repetition)
//! σ ← α·σ, α = <Kσ, y> / <Kσ, Kσ>         (after each repetition's iterations)
//! σ ← σ^boost, rescaled to keep Σσ        (between repetitions)
//! ```
//!
//! The amplitude step `α` is not in Gold's original iteration: the multiplicative updates fix
//! the *shape* quickly but the overall amplitude slowly (a single spike keeps only ~60 % of its
//! energy after 20 iterations). Every fixed point of Gold satisfies
//! `Σ σ·(KᵀKσ) = Σ σ·(Kᵀy)`, i.e. `<Kσ, Kσ> = <Kσ, y>`, so `α = 1` there: the step is the
//! least-squares optimal rescaling of the current shape and does not move the fixed points.
//!
//! `K σ` is the convolution `k ⊛ σ` of the kernel convention and `Kᵀ` its adjoint (two direct
//! passes per iteration, see the `direct` module). The iteration is the multiplicative solution
//! of the least-squares normal equations `KᵀK σ = Kᵀ y` under `σ ≥ 0`; it stays non-negative
//! because `b` is clipped at zero (Gold needs a positive right-hand side) and the denominator is
//! floored.
//!
//! - **Normalisation**: the data are divided by their largest absolute value (in f64) and the
//!   result multiplied back, so floors are relative and denormal or full-scale inputs stay in
//!   range. An all-zero segment gives zeros.
//! - **Start**: flat, `σ_0 = 1` (normalised units), as Morháč.
//! - **Guards**: the denominator `KᵀKσ` is floored at `10⁻⁶`, `σ` is capped at `10⁹` and values
//!   below `10⁻³⁰` flushed to 0 (normalised units). Output finite and non-negative.
//! - **Boost**: raising to `boost > 1` between repetitions sharpens peaks (Morháč's boosted
//!   Gold); the sum is restored after boosting so the next repetition starts at the data's
//!   energy. With `repetitions = 1` the boost is never applied.
//!
//! - **Stop by the noise** (optional, [`GoldConfig::stop_at_noise`] `= τ`, the discrepancy
//!   principle as for Richardson-Lucy: see `richardson_lucy.rs` for what `noise_v` measures and
//!   why `τ = 1` is the classical rule at the default denoise cut-off): before the update of
//!   each iteration, from the `Kσ_i` the iteration computes anyway, the residual of what would
//!   be returned, the current shape at the amplitude step's `α = <Kσ, y>/<Kσ, Kσ>` (below):
//!   `r = y⁺ − α·Kσ_i` over the samples given (the segment or a gate window), with `y⁺ =
//!   max(y, 0)` as Richardson-Lucy's residual (against `y` itself the non-negative `Kσ` leaves
//!   the mean of the clipped noise in every empty sample, and a mostly empty segment never
//!   reaches the noise level). When `√(Σr² / n) ≤ τ · noise_v` the iterations stop (the
//!   remaining repetitions too), the amplitude step is made and `σ` returned.
//!   `iterations × repetitions` stays the hard cap; a `noise_v` that is not a positive finite
//!   number never stops a run. About `8·n` flops more per iteration.
//!
//! Cost per segment: `2·n·m + repetitions × (iterations × (4·n·m + 6·n) + 2·n·m + 6·n)` flops
//! (`8·n` more per iteration with the stop by the noise).

use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::direct::{convolve_padded, correlate_padded};
use crate::signal::deconvolve::{
    DeconvError, Deconvolver, MethodStats, check_inputs, normalise, scale_out,
};
use crate::signal::kernel::Kernel;

/// Floor of the denominator `KᵀKσ` (normalised units).
const DENOMINATOR_FLOOR: f32 = 1e-6;
/// Cap on the normalised estimate.
const ESTIMATE_CAP: f32 = 1e9;
/// Normalised values below this are flushed to zero.
const FLUSH: f32 = 1e-30;

/// Settings of Gold deconvolution (`method = "gold"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GoldConfig {
    /// Iterations per repetition. Default 20.
    #[serde(default = "default_iterations")]
    pub iterations: u32,
    /// Repetitions (boost applied between them). Default 1.
    #[serde(default = "default_repetitions")]
    pub repetitions: u32,
    /// Exponent applied to the estimate between repetitions (dimensionless, > 0; 1 = none).
    /// Default 1.0.
    #[serde(default = "default_boost")]
    pub boost: f32,
    /// Stop by the noise (discrepancy principle, see the module documentation): stop once the
    /// residual RMS of the estimate at its least-squares amplitude is at most this multiple of
    /// the segment's noise level `noise_v` (dimensionless, > 0). `iterations × repetitions`
    /// stays the cap. Default none: always run every iteration.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_at_noise: Option<f32>,
}

fn default_iterations() -> u32 {
    20
}
fn default_repetitions() -> u32 {
    1
}
fn default_boost() -> f32 {
    1.0
}

impl GoldConfig {
    /// Worst-case flops for a segment of `n` samples and a kernel of `m` taps:
    /// `2·n·m + repetitions × (iterations × (4·n·m + 6·n) + 2·n·m + 6·n)`, `8·n` more per
    /// iteration with [`GoldConfig::stop_at_noise`].
    pub fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        let (n, m) = (n as u64, m as u64);
        let residual = if self.stop_at_noise.is_some() {
            8 * n
        } else {
            0
        };
        let per = 4 * n * m + 6 * n + residual;
        let reps = self.repetitions.max(1) as u64;
        let rep = (self.iterations as u64).saturating_mul(per) + 2 * n * m + 6 * n;
        (2 * n * m).saturating_add(reps.saturating_mul(rep))
    }
}

impl Default for GoldConfig {
    fn default() -> Self {
        GoldConfig {
            iterations: default_iterations(),
            repetitions: default_repetitions(),
            boost: default_boost(),
            stop_at_noise: None,
        }
    }
}

/// Gold deconvolution with buffers sized once.
pub struct Gold {
    config: GoldConfig,
    max_samples: usize,
    max_taps: usize,
    /// `max(Kᵀy, 0)`, `max_samples`.
    b: Vec<f32>,
    /// Normalised data, `max_samples`.
    y: Vec<f32>,
    /// Padded estimate σ (also holds the padded data at the start), `max_samples + 2·max_taps`.
    sigma: Vec<f32>,
    /// Padded `Kσ`, `max_samples + 2·max_taps`.
    blurred: Vec<f32>,
    /// `KᵀKσ`, `max_samples`.
    normal: Vec<f32>,
}

impl Gold {
    /// Builds the method for segments of up to `max_samples` samples and kernels of up to
    /// `max_taps` taps.
    pub fn new(config: GoldConfig, max_samples: usize, max_taps: usize) -> Self {
        let padded = max_samples + 2 * max_taps;
        Gold {
            config,
            max_samples,
            max_taps,
            b: vec![0.0; max_samples],
            y: vec![0.0; max_samples],
            sigma: vec![0.0; padded],
            blurred: vec![0.0; padded],
            normal: vec![0.0; max_samples],
        }
    }

    /// The configuration in force.
    pub fn config(&self) -> &GoldConfig {
        &self.config
    }
}

impl Deconvolver for Gold {
    fn name(&self) -> &'static str {
        "gold"
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        _sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let max_abs = check_inputs(y, k, out, self.max_samples, self.max_taps)?;
        let n = y.len();
        if n == 0 || max_abs <= 0.0 {
            out.fill(0.0);
            return Ok(MethodStats::default());
        }
        let m = k.taps.len();
        let pad = m;
        let scale = max_abs as f64;
        let sigma = &mut self.sigma[..n + 2 * pad];
        let blurred = &mut self.blurred[..n + 2 * pad];
        sigma.fill(0.0);
        blurred.fill(0.0);
        normalise(y, max_abs, &mut sigma[pad..pad + n]);
        let yn = &mut self.y[..n];
        yn.copy_from_slice(&sigma[pad..pad + n]);
        let b = &mut self.b[..n];
        correlate_padded(sigma, pad, &k.taps, k.center, b);
        let mut b_sum = 0.0f64;
        for v in b.iter_mut() {
            *v = v.max(0.0);
            b_sum += *v as f64;
        }
        if b_sum <= 0.0 {
            out.fill(0.0);
            return Ok(MethodStats::default());
        }
        sigma[pad..pad + n].fill(1.0);
        // The stop by the noise: `Σ(y⁺)²` and the largest sum of squared residuals
        // (normalised units) that stops, `n · (τ · noise_v / max)²`; none without a usable
        // noise level.
        let stop = self.config.stop_at_noise.and_then(|tau| {
            let level = tau as f64 * noise_v as f64 / scale;
            (level.is_finite() && level > 0.0).then(|| {
                let yy: f64 = yn.iter().map(|&v| (v.max(0.0) as f64).powi(2)).sum();
                (yy, n as f64 * level * level)
            })
        });
        let normal = &mut self.normal[..n];
        let mut stats = MethodStats::default();
        let reps = self.config.repetitions.max(1);
        for rep in 0..reps {
            for _ in 0..self.config.iterations {
                convolve_padded(sigma, pad, &k.taps, k.center, &mut blurred[pad..pad + n]);
                if let Some((yy, limit)) = stop {
                    // Residual of y⁺ − α·Kσ, α = <Kσ, y> / <Kσ, Kσ>:
                    // Σ(y⁺)² − 2α<Kσ, y⁺> + α²<Kσ, Kσ>.
                    let (mut num, mut pos, mut den) = (0.0f64, 0.0f64, 0.0f64);
                    for (&kb, &yv) in blurred[pad..pad + n].iter().zip(yn.iter()) {
                        let kb = kb as f64;
                        num += kb * yv as f64;
                        pos += kb * yv.max(0.0) as f64;
                        den += kb * kb;
                    }
                    let alpha = if den > 0.0 { num / den } else { 0.0 };
                    let ss = yy - 2.0 * alpha * pos + alpha * alpha * den;
                    if ss <= limit {
                        stats.stopped_early = true;
                        break;
                    }
                }
                correlate_padded(blurred, pad, &k.taps, k.center, normal);
                for ((s, &d), &bv) in sigma[pad..pad + n]
                    .iter_mut()
                    .zip(normal.iter())
                    .zip(b.iter())
                {
                    let mut new = (*s * bv / d.max(DENOMINATOR_FLOOR)).min(ESTIMATE_CAP);
                    if new < FLUSH {
                        new = 0.0;
                    }
                    *s = new;
                }
                stats.iterations += 1;
            }
            // Least-squares amplitude: σ ← α·σ with α = <Kσ, y> / <Kσ, Kσ>.
            convolve_padded(sigma, pad, &k.taps, k.center, &mut blurred[pad..pad + n]);
            let (mut num, mut den) = (0.0f64, 0.0f64);
            for (&kb, &yv) in blurred[pad..pad + n].iter().zip(yn.iter()) {
                num += kb as f64 * yv as f64;
                den += kb as f64 * kb as f64;
            }
            let alpha = num / den;
            if alpha.is_finite() && alpha > 0.0 {
                let alpha = alpha as f32;
                for v in sigma[pad..pad + n].iter_mut() {
                    *v = (*v * alpha).min(ESTIMATE_CAP);
                }
            }
            if stats.stopped_early {
                break;
            }
            let boost = self.config.boost;
            if rep + 1 < reps && boost != 1.0 && boost.is_finite() && boost > 0.0 {
                let s = &mut sigma[pad..pad + n];
                let before: f64 = s.iter().map(|&v| v as f64).sum();
                for v in s.iter_mut() {
                    *v = v.powf(boost).min(ESTIMATE_CAP);
                }
                let after: f64 = s.iter().map(|&v| v as f64).sum();
                if after > 0.0 && after.is_finite() {
                    let r = (before / after) as f32;
                    for v in s.iter_mut() {
                        *v *= r;
                    }
                }
            }
        }
        scale_out(&sigma[pad..pad + n], scale, out);
        Ok(stats)
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        self.config.worst_case_flops(n, m)
    }
}
