//! Non-negative least squares deconvolution: `min ‖R σ − P‖²` subject to `σ ≥ 0`, with `R` the
//! "same"-size convolution (Toeplitz) matrix of the kernel (the convention of
//! [`crate::signal::kernel`]); the method of J. Wu (2012), who used Lawson-Hanson.
//!
//! # Algorithm
//!
//! Lawson-Hanson active set on the normal equations, exploiting the banded Toeplitz structure;
//! the `n × n` matrix is never formed:
//!
//! * Per kernel (O(m²)): a table of prefix sums of the lagged tap products
//!   `Q[d][j] = Σ_{d ≤ j' < j} taps[j'] · taps[j' − d]`. Any entry of the Gram matrix `G = RᵀR`,
//!   including the boundary rows where the "same"-size convolution truncates the columns, is
//!   then one difference of two table entries (O(1)), exact for every segment length (also for
//!   kernels longer than the segment). The interior band (the autocorrelation of the taps,
//!   `2m − 1` values) is `Q[d][m]`.
//! * `b = Rᵀ P` once (a correlation, O(n·m)).
//! * Outer iteration: the dual `w = b − G σ` from the passive (non-zero) set only (O(k·m) for
//!   `k` passive samples); the zero sample with the largest `w` joins the passive set; the
//!   Cholesky factor of `G_PP` grows by one row (O(k²)); the passive subproblem is solved
//!   (O(k²)); if a passive value would go non-positive, the Lawson-Hanson inner loop steps back
//!   to feasibility and drops the samples that reach zero, each by a Givens downdate of the
//!   Cholesky factor (O(k²); no refactorisation).
//! * Early stop (KKT): every zero sample has `w ≤ tolerance · max|b|` (the passive samples have
//!   `w = 0` up to rounding by construction).
//!
//! The passive set grows by at most one sample per outer iteration, so `k ≤ max_iterations`,
//! and every inner step removes at least one sample, so over a run there are at most
//! `max_iterations` inner steps: the worst case is bounded by the configuration (see
//! [`Deconvolver::worst_case_flops`]). A run that reaches the iteration cap returns the feasible
//! (non-negative) solution of its current passive set: a sparse, greedy approximation of the
//! full NNLS solution, a natural regulariser on noisy segments.
//!
//! The arithmetic is in `f64` on a segment scaled to unit peak magnitude (NNLS is homogeneous:
//! `σ(a·P) = a·σ(P)`), so denormal and saturated (65535) inputs behave alike; the result is
//! scaled back and written as `f32`, finite and non-negative. A sample whose column is
//! numerically dependent on the passive set is excluded for the rest of the run.
//!
//! `sample_ns` is not used: the problem is posed in samples, and the stop rule is relative to
//! `max|RᵀP|`. `noise_v` is used only by [`NnlsConfig::support_at_noise`].
//!
//! # Spikes only near echoes
//!
//! Run to its optimality test, NNLS also fits the noise of the empty range: every positive
//! noise bump far from any echo gets a spike, and each costs an outer iteration (and makes the
//! passive set, hence every later iteration, larger). With
//! [`NnlsConfig::support_at_noise`] `= τ`, a sample may join the passive set only when its
//! footprint (the samples a spike there reaches, `i − c ..= i − c + m − 1`) holds a sample of
//! the segment above `τ · noise_v`; the fit still uses every sample. One O(n) scan per run.
//! Measured with `fwlidar tradeoff` (docs/accuracy.md, "NNLS: spikes only near echoes"): at
//! τ = 4 the mean time per pulse falls by about half with the RMSE within 0.002.
//!
//! # Samples left out, and the noise-weighted fit
//!
//! [`Deconvolver::run_excluding`] leaves flagged samples out of the fit (weight 0; e.g. a
//! clipped top, whose true value is unknown). [`NnlsConfig::noise_weights`] fits once, regresses
//! the squared residuals on the fitted signal (`r² ≈ a + b · fit` by least squares over the kept
//! samples, `a` at least `NOISE_FLOOR_SHARE` = 0.1 of the mean `r²`), and when `b · max(fit) ≥ a`
//! (the variance at the strongest echo at least twice the floor: shot noise) fits again with
//! every sample weighted by `a / (a + b · fit)`, the maximum-likelihood weighting of a variance
//! that follows the signal; noise that does not follow it keeps the first fit, bit for bit. No
//! noise model is assumed: `a` and `b` come from the segment. A weighted pass computes each
//! Gram entry directly (O(m)) and the dual from the weighted residual (O(n·m) per outer
//! iteration) instead of from the prefix table; the worst case states it.
//!
//! # Units
//!
//! Input `P`: volts above baseline per sample. Output `σ`: volts per sample bin of the
//! cross-section (the kernel has unit sum, so `Σσ` equals the return's area `ΣP` in V·samples
//! when the fit is exact). [`MethodStats::iterations`] counts outer iterations.
//!
//! # Cost (measured, 256 samples, 41-tap 16 ns Gaussian, 1 ns, `benches/nnls.rs`)
//!
//! About 15 µs median for a two-surface return (early stop after ~12 iterations) and about
//! 140 µs when all 50 iterations run (dense canopy, no early stop); the stated worst case
//! `worst_case_flops(256, 41)` is about 3.1 Mflop at the defaults (the weighted pass's bound; a
//! plain pass, 1.9 Mflop). `fwlidar process`'s setting (budget 128, noise weights) is timed by
//! the `nnls_process_*` benches (docs/performance.md).
//!
//! # Default tolerance: 1e-6
//!
//! At 1e-4 two noise-free echoes 0.5 FWHM apart stopped before the pair was split (the merged
//! fit was already within tolerance); 1e-6 resolves them exactly (`two_echoes_half_fwhm_apart`),
//! and resolving hidden echoes is what deconvolution is for. The stated worst case does not
//! change (it is fixed by `max_iterations`); the typical cost grows: on the benchmark's
//! segments the early stop comes after 14 instead of 6 iterations (clean) and 24 instead of 12
//! (±3 DN ripple), about 11 and 21 µs instead of 6 and 10 µs (release, measured 2026-11-22 on
//! the project machine), far below the 200 µs target and the ~140 µs of a full 50-iteration
//! run.

use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::{DeconvError, Deconvolver, MethodStats, check_inputs};
use crate::signal::kernel::Kernel;

/// Least share of the mean squared residual taken as the variance floor of the noise weights
/// (a floor regressed near zero would weight the background without limit).
const NOISE_FLOOR_SHARE: f64 = 0.1;

/// Relative pivot below which a new column counts as dependent on the passive set.
const DEPENDENT_PIVOT: f64 = 1e-12;

/// Settings of the NNLS deconvolution (`method = "nnls"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NnlsConfig {
    /// Maximum Lawson-Hanson outer iterations (each adds at most one non-zero sample), which is
    /// also the maximum number of non-zero output samples (count; default 50). Buffers of
    /// `min(max_iterations, max_samples)²` `f64` are sized at construction.
    pub max_iterations: u32,
    /// Relative KKT tolerance of the early stop (dimensionless, default 1e-6): the run stops
    /// when no zero sample has a dual value `(Rᵀ(P − Rσ))_i` above `tolerance · max|RᵀP|`.
    pub tolerance: f32,
    /// Weight the fit by a noise variance estimated from the segment itself (default false):
    /// after the first fit, the squared residuals are regressed on the fitted signal,
    /// `var = a + b · fit`; when the variance at the strongest fitted echo is at least twice the
    /// floor `a` (signal-dependent noise, such as photon shot noise), the fit runs again with
    /// every sample weighted by `a / (a + b · fit)`. With noise that does not follow the signal
    /// the second fit does not run. See "Noise-weighted fit" in the module documentation.
    pub noise_weights: bool,
    /// Spikes only near echoes (dimensionless multiple `τ`, default none): a sample may hold a
    /// spike only when the segment exceeds `τ · noise_v` within half a kernel of it; elsewhere
    /// the data are noise and a spike there only fits it. The fit still uses every sample.
    pub support_at_noise: Option<f32>,
}

impl NnlsConfig {
    /// Worst-case flops for a segment of `n` samples and a kernel of `m` taps, with
    /// `K = max_iterations`, `k = min(K, n)`. One plain pass (every sample weighted alike):
    /// `m² + m + 2·n·m + n + K·(2k(2m − 1) + n + 11k² + 18k)`; a weighted pass (samples left
    /// out, or the noise weights) computes Gram entries and the dual directly:
    /// `m² + 2m + 2·n·m + 4n + K·(2km + 2nm + 5n + 3m(k + 1) + 11k² + 18k)`. The worst case is
    /// the weighted pass's, twice with [`NnlsConfig::noise_weights`] plus the variance
    /// estimate (`2km + 11n`); [`NnlsConfig::support_at_noise`] adds `2n` per pass. See the
    /// comments for the terms.
    pub fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        // Per kernel: table m² + m; b = Rᵀy: 2nm. Per outer iteration (K = max_iterations of
        // them, k ≤ min(K, n) passive samples): dual 2k(2m − 1), argmax n, Cholesky row
        // k² + 3k (one flop per Gram entry), solve 2k² + 2k. Inner steps (≤ K over the whole
        // run, each removes a sample): step 5k, Givens downdate 6k² + 6k, solve 2k² + 2k.
        // Output scaling n.
        let (n, m) = (n as u64, m as u64);
        let it = self.max_iterations as u64;
        let k = it.min(n);
        let outer = 2 * k * (2 * m).saturating_sub(1) + n + 3 * k * k + 5 * k;
        let inner = 8 * k * k + 13 * k;
        let plain = (m * m + m + 2 * n * m + n).saturating_add(it.saturating_mul(outer + inner));
        // Weighted: taps copied (m), weighted input 3n; dual from the residual: fit 2km, clear
        // and residual 4n, correlation 2nm; each Gram entry 3m flops (k + 1 per new row).
        let outer_w = 2 * k * m + 2 * n * m + 5 * n + 3 * m * (k + 1) + 3 * k * k + 5 * k;
        let weighted =
            (m * m + 2 * m + 2 * n * m + 4 * n).saturating_add(it.saturating_mul(outer_w + inner));
        // Spikes only near echoes: one scan (compare and branch) per sample and pass.
        let mask = if self.support_at_noise.is_some() {
            2 * n
        } else {
            0
        };
        if self.noise_weights {
            (weighted + mask)
                .saturating_mul(2)
                .saturating_add(2 * k * m + 11 * n)
        } else {
            plain.max(weighted) + mask
        }
    }
}

impl Default for NnlsConfig {
    fn default() -> Self {
        NnlsConfig {
            max_iterations: 50,
            tolerance: 1e-6,
            noise_weights: false,
            support_at_noise: None,
        }
    }
}

/// NNLS deconvolution with every buffer sized at construction (no allocation in `run`).
pub struct Nnls {
    config: NnlsConfig,
    max_samples: usize,
    max_taps: usize,
    /// Largest passive set (`min(max_iterations, max_samples)`).
    max_k: usize,
    /// Prefix table of lagged tap products, `m × (m + 1)`, row stride `max_taps + 1`.
    q: Vec<f64>,
    /// Interior Gram band: `band[d + m − 1] = G(s, s + d)` for columns with full support.
    band: Vec<f64>,
    /// `Rᵀ P` (scaled segment).
    b: Vec<f64>,
    /// Dual `Rᵀ(P − Rσ)`.
    w: Vec<f64>,
    /// Current (scaled) solution, dense.
    x: Vec<f64>,
    /// Sample flags: bit 0 passive, bit 1 excluded (dependent or failed to enter).
    flags: Vec<u8>,
    /// Passive sample indices in Cholesky order.
    passive: Vec<usize>,
    /// Lower Cholesky factor of `G_PP`, row-major with stride `max_k`.
    chol: Vec<f64>,
    /// Passive subproblem solution (Cholesky order).
    z: Vec<f64>,
    /// Scratch vector of length `max_k`.
    tmp: Vec<f64>,
    /// The kernel's taps in `f64`, `max_taps` (weighted Gram entries).
    taps: Vec<f64>,
    /// Per-sample weight of the squared residual, `max_samples` (0: left out; all 1 when
    /// `weighted` is false).
    wt: Vec<f64>,
    /// The scaled segment, then `R σ` and the weighted residual, `max_samples` each.
    ys: Vec<f64>,
    resid: Vec<f64>,
    /// Whether this pass weights the samples (Gram entries and dual computed directly).
    weighted: bool,
    /// The segment's noise level of this run, volts ([`NnlsConfig::support_at_noise`]).
    noise_v: f64,
}

/// `dst[i] += Σ_j taps[j] · src[i − c + j]` over the valid range (`dst += Rᵀ src`, `src` and
/// `dst` of the segment's length).
fn correlate_into(taps: &[f64], c: isize, src: &[f64], dst: &mut [f64]) {
    let n = dst.len() as isize;
    for (j, &t) in taps.iter().enumerate() {
        let shift = j as isize - c;
        let i_lo = (-shift).max(0);
        let i_hi = (n - shift).min(n);
        if i_hi <= i_lo {
            continue;
        }
        let (i_lo, i_hi) = (i_lo as usize, i_hi as usize);
        let ss = &src[(i_lo as isize + shift) as usize..(i_hi as isize + shift) as usize];
        for (d, &v) in dst[i_lo..i_hi].iter_mut().zip(ss) {
            *d += t * v;
        }
    }
}

const PASSIVE: u8 = 1;
const EXCLUDED: u8 = 2;

/// The geometry of one run: segment length, taps, centre.
#[derive(Clone, Copy)]
struct Geometry {
    n: usize,
    m: usize,
    c: isize,
    stride: usize,
}

impl Geometry {
    /// `G(s, t) = Σ_i R[i][s] R[i][t]`, exact including the truncated boundary columns.
    #[inline]
    fn gram(&self, q: &[f64], s: usize, t: usize) -> f64 {
        let (a, hi_idx) = if s <= t { (s, t) } else { (t, s) };
        let d = hi_idx - a;
        if d >= self.m {
            return 0.0;
        }
        let lo = (d as isize).max(self.c - a as isize);
        let hi = (self.m as isize).min(self.n as isize + self.c - a as isize);
        if hi <= lo {
            return 0.0;
        }
        let row = d * self.stride;
        q[row + hi as usize] - q[row + lo as usize]
    }

    /// True when column `s` of `R` lies entirely inside the segment (its Gram column is the
    /// interior band).
    #[inline]
    fn interior(&self, s: usize) -> bool {
        let s = s as isize;
        s >= self.c && s - self.c + self.m as isize <= self.n as isize
    }

    /// Range of `t` with `|t − s| < m` inside the segment.
    #[inline]
    fn band_range(&self, s: usize) -> (usize, usize) {
        let lo = s.saturating_sub(self.m - 1);
        let hi = (s + self.m).min(self.n);
        (lo, hi)
    }
}

impl Nnls {
    /// Builds the method with buffers for segments of up to `max_samples` samples and kernels of
    /// up to `max_taps` taps.
    pub fn new(config: NnlsConfig, max_samples: usize, max_taps: usize) -> Self {
        let max_k = (config.max_iterations as usize).min(max_samples);
        Nnls {
            config,
            max_samples,
            max_taps,
            max_k,
            q: vec![0.0; max_taps * (max_taps + 1)],
            band: vec![0.0; (2 * max_taps).saturating_sub(1)],
            b: vec![0.0; max_samples],
            w: vec![0.0; max_samples],
            x: vec![0.0; max_samples],
            flags: vec![0; max_samples],
            passive: Vec::with_capacity(max_k),
            chol: vec![0.0; max_k * max_k],
            z: vec![0.0; max_k],
            tmp: vec![0.0; max_k],
            taps: vec![0.0; max_taps],
            wt: vec![1.0; max_samples],
            ys: vec![0.0; max_samples],
            resid: vec![0.0; max_samples],
            weighted: false,
            noise_v: 0.0,
        }
    }

    /// `G(s, t) = Σ_i wt_i R[i][s] R[i][t]`: from the prefix table when the samples are
    /// weighted alike, else summed directly (O(m)).
    #[inline]
    fn gram_at(&self, g: &Geometry, s: usize, t: usize) -> f64 {
        if !self.weighted {
            return g.gram(&self.q, s, t);
        }
        let (a, b) = if s <= t { (s, t) } else { (t, s) };
        if b - a >= g.m {
            return 0.0;
        }
        // R[i][s] = taps[i − s + c]: i from b − c to a − c + m − 1, inside the segment.
        let lo = (b as isize - g.c).max(0);
        let hi = (a as isize - g.c + g.m as isize).min(g.n as isize);
        let mut acc = 0.0;
        for i in lo..hi {
            let ta = self.taps[(i - a as isize + g.c) as usize];
            let tb = self.taps[(i - b as isize + g.c) as usize];
            acc += self.wt[i as usize] * ta * tb;
        }
        acc
    }

    /// `resid = R x` (the fit of the passive samples, scaled units), O(k·m).
    fn fit_into_resid(&mut self, g: &Geometry) {
        let n = g.n;
        self.resid[..n].fill(0.0);
        for &s in &self.passive {
            let xs = self.x[s];
            if xs == 0.0 {
                continue;
            }
            // R[i][s] = taps[i − s + c].
            let lo = (s as isize - g.c).max(0);
            let hi = (s as isize - g.c + g.m as isize).min(n as isize);
            for i in lo..hi {
                self.resid[i as usize] += xs * self.taps[(i - s as isize + g.c) as usize];
            }
        }
    }

    /// Fills the prefix table and the interior band for `k` (O(m²)).
    fn prepare_kernel(&mut self, k: &Kernel, g: &Geometry) {
        let m = g.m;
        for d in 0..m {
            let row = &mut self.q[d * g.stride..d * g.stride + m + 1];
            let mut acc = 0.0f64;
            row[..=d].fill(0.0);
            for j in d..m {
                acc += k.taps[j] as f64 * k.taps[j - d] as f64;
                row[j + 1] = acc;
            }
            self.band[m - 1 + d] = acc;
            self.band[m - 1 - d] = acc;
        }
    }

    /// Appends sample `j` to the passive set and its row to the Cholesky factor; false (and
    /// nothing changed) when its column is numerically dependent on the passive set.
    fn chol_push(&mut self, g: &Geometry, j: usize) -> bool {
        let k = self.passive.len();
        if k >= self.max_k {
            return false;
        }
        let st = self.max_k;
        // Forward solve L l = G_Pj into row k.
        let mut sq = 0.0f64;
        for p in 0..k {
            let mut v = self.gram_at(g, self.passive[p], j);
            let (rows, rowk) = self.chol.split_at_mut(k * st);
            let lp = &rows[p * st..p * st + p];
            let lk = &rowk[..p];
            for (a, b) in lp.iter().zip(lk) {
                v -= a * b;
            }
            let l = v / self.chol[p * st + p];
            self.chol[k * st + p] = l;
            sq += l * l;
        }
        let gjj = self.gram_at(g, j, j);
        let piv = gjj - sq;
        if piv.is_nan() || piv <= DEPENDENT_PIVOT * gjj || !piv.is_finite() {
            return false;
        }
        self.chol[k * st + k] = piv.sqrt();
        self.passive.push(j);
        self.flags[j] |= PASSIVE;
        true
    }

    /// Solves `G_PP z = b_P` with the current factor (O(k²)).
    fn chol_solve(&mut self) {
        let k = self.passive.len();
        let st = self.max_k;
        for p in 0..k {
            let row = &self.chol[p * st..p * st + p];
            let mut v = self.b[self.passive[p]];
            for (a, u) in row.iter().zip(&self.tmp[..p]) {
                v -= a * u;
            }
            self.tmp[p] = v / self.chol[p * st + p];
        }
        // Back substitution by rows of L (column-oriented on Lᵀ): contiguous axpys.
        for p in (0..k).rev() {
            let zp = self.tmp[p] / self.chol[p * st + p];
            self.z[p] = zp;
            let row = &self.chol[p * st..p * st + p];
            for (t, l) in self.tmp[..p].iter_mut().zip(row) {
                *t -= l * zp;
            }
        }
    }

    /// Recomputes `w = b − G x` from the passive set (O(k·m)).
    fn update_dual(&mut self, g: &Geometry) {
        let n = g.n;
        if self.weighted {
            // w = Rᵀ W (y − R x), O(k·m + n·m).
            self.fit_into_resid(g);
            for i in 0..n {
                self.resid[i] = self.wt[i] * (self.ys[i] - self.resid[i]);
            }
            self.w[..n].fill(0.0);
            correlate_into(&self.taps[..g.m], g.c, &self.resid[..n], &mut self.w[..n]);
            return;
        }
        self.w[..n].copy_from_slice(&self.b[..n]);
        for &s in &self.passive {
            let xs = self.x[s];
            if xs == 0.0 {
                continue;
            }
            let (lo, hi) = g.band_range(s);
            if g.interior(s) {
                let off = lo + g.m - 1 - s;
                let band = &self.band[off..off + (hi - lo)];
                for (wt, a) in self.w[lo..hi].iter_mut().zip(band) {
                    *wt -= xs * a;
                }
            } else {
                for t in lo..hi {
                    self.w[t] -= xs * g.gram(&self.q, t, s);
                }
            }
        }
    }

    /// Removes passive position `p` from the set and its row and column from the Cholesky
    /// factor by Givens rotations (O(k²), no refactorisation).
    fn chol_remove(&mut self, p: usize) {
        let k = self.passive.len();
        let st = self.max_k;
        let s = self.passive.remove(p);
        self.flags[s] &= !PASSIVE;
        self.x[s] = 0.0;
        // Drop row p; rows p.. of the (k − 1)-row result carry one entry above the diagonal.
        for r in p + 1..k {
            self.chol.copy_within(r * st..r * st + r + 1, (r - 1) * st);
        }
        // Rotate columns (j, j + 1) to zero the entry above the diagonal of row j.
        for j in p..k - 1 {
            let a = self.chol[j * st + j];
            let b = self.chol[j * st + j + 1];
            let r = a.hypot(b);
            let (cs, sn) = if r > 0.0 { (a / r, b / r) } else { (1.0, 0.0) };
            for row in j..k - 1 {
                let x = self.chol[row * st + j];
                let y = self.chol[row * st + j + 1];
                self.chol[row * st + j] = cs * x + sn * y;
                self.chol[row * st + j + 1] = cs * y - sn * x;
            }
            self.chol[j * st + j] = r;
            self.chol[j * st + j + 1] = 0.0;
        }
    }

    /// Drops the passive samples whose value is zero (O(k²) each).
    fn drop_zeros(&mut self) {
        let mut p = self.passive.len();
        while p > 0 {
            p -= 1;
            let s = self.passive[p];
            if self.x[s].is_nan() || self.x[s] <= 0.0 {
                self.chol_remove(p);
            }
        }
    }
}

impl Nnls {
    /// The method on `y` by `k`, the samples flagged in `excluded` left out of the fit; the
    /// noise-weighted refit when configured.
    fn run_masked(
        &mut self,
        y: &[f32],
        k: &Kernel,
        excluded: Option<&[bool]>,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let n = y.len();
        check_inputs(y, k, out, self.max_samples, self.max_taps)?;
        if let Some(e) = excluded.filter(|e| e.len() != n) {
            return Err(DeconvError::LengthMismatch {
                input: n,
                out: e.len(),
            });
        }
        out.fill(0.0);
        let peak = y.iter().fold(0.0f64, |a, &v| a.max((v as f64).abs()));
        if n == 0 || k.taps.is_empty() || peak == 0.0 || self.max_k == 0 {
            return Ok(MethodStats::default());
        }
        let inv_peak = 1.0 / peak;
        let g = Geometry {
            n,
            m: k.taps.len(),
            c: k.center.min(isize::MAX as usize / 4) as isize,
            stride: self.max_taps + 1,
        };
        self.prepare_kernel(k, &g);
        self.weighted = excluded.is_some_and(|e| e.iter().any(|&b| b));
        if self.weighted || self.config.noise_weights {
            for (t, &v) in self.taps[..g.m].iter_mut().zip(&k.taps) {
                *t = v as f64;
            }
            for (d, &v) in self.ys[..n].iter_mut().zip(y) {
                *d = v as f64 * inv_peak;
            }
            for (i, w) in self.wt[..n].iter_mut().enumerate() {
                *w = if excluded.is_some_and(|e| e[i]) {
                    0.0
                } else {
                    1.0
                };
            }
        }
        let mut stats = self.solve(y, k, &g, inv_peak);
        if self.config.noise_weights && self.noise_weights(&g) {
            self.weighted = true;
            let second = self.solve(y, k, &g, inv_peak);
            stats.iterations += second.iterations;
            stats.stopped_early = second.stopped_early;
        }
        for (o, &v) in out.iter_mut().zip(&self.x[..n]) {
            let v = v * peak;
            *o = if v > 0.0 {
                v.min(f32::MAX as f64) as f32
            } else {
                0.0
            };
        }
        Ok(stats)
    }

    /// One Lawson-Hanson run from an empty passive set (weighted when `self.weighted`); the
    /// solution, scaled by `inv_peak`, is left in `x`.
    fn solve(&mut self, y: &[f32], k: &Kernel, g: &Geometry, inv_peak: f64) -> MethodStats {
        let n = g.n;
        if self.weighted {
            // b = Rᵀ W y.
            for i in 0..n {
                self.resid[i] = self.wt[i] * self.ys[i];
            }
            self.b[..n].fill(0.0);
            correlate_into(&self.taps[..g.m], g.c, &self.resid[..n], &mut self.b[..n]);
        } else {
            // b = Rᵀ y (scaled): b[i] = Σ_j taps[j] y[i − c + j], as axpys over valid ranges.
            self.b[..n].fill(0.0);
            for (j, &t) in k.taps.iter().enumerate() {
                let shift = j as isize - g.c; // y index = i + shift
                let i_lo = (-shift).max(0);
                let i_hi = (n as isize - shift).min(n as isize);
                if i_hi <= i_lo {
                    continue;
                }
                let t = t as f64 * inv_peak;
                let (i_lo, i_hi) = (i_lo as usize, i_hi as usize);
                let ys = &y[(i_lo as isize + shift) as usize..(i_hi as isize + shift) as usize];
                for (bi, &yv) in self.b[i_lo..i_hi].iter_mut().zip(ys) {
                    *bi += t * yv as f64;
                }
            }
        }
        let bmax = self.b[..n].iter().fold(0.0f64, |a, &v| a.max(v.abs()));
        self.x[..n].fill(0.0);
        self.passive.clear();
        if bmax.is_nan() || bmax <= 0.0 || !bmax.is_finite() {
            return MethodStats::default();
        }
        let tol = (self.config.tolerance.max(0.0) as f64) * bmax;
        self.flags[..n].fill(0);
        if let Some(tau) = self.config.support_at_noise {
            self.mask_support(y, g, tau);
        }

        let mut stats = MethodStats::default();
        let max_it = self.config.max_iterations;
        while stats.iterations < max_it {
            self.update_dual(g);
            // Largest dual among the free samples.
            let mut best = tol;
            let mut j_best = usize::MAX;
            for (i, (&wi, &f)) in self.w[..n].iter().zip(&self.flags[..n]).enumerate() {
                if f == 0 && wi > best {
                    best = wi;
                    j_best = i;
                }
            }
            if j_best == usize::MAX {
                stats.stopped_early = true;
                break;
            }
            stats.iterations += 1;
            if !self.chol_push(g, j_best) {
                self.flags[j_best] |= EXCLUDED;
                continue;
            }
            // Inner loop: at most one step per passive sample.
            let mut first = true;
            loop {
                self.chol_solve();
                let kk = self.passive.len();
                if first && (self.z[kk - 1].is_nan() || self.z[kk - 1] <= 0.0) {
                    // The new sample cannot enter (rounding): exclude it, keep x.
                    self.passive.pop();
                    self.flags[j_best] = EXCLUDED;
                    break;
                }
                first = false;
                let mut alpha = 1.0f64;
                let mut blocking = usize::MAX;
                for p in 0..kk {
                    let zp = self.z[p];
                    if zp.is_nan() || zp <= 0.0 {
                        let xp = self.x[self.passive[p]];
                        let a = xp / (xp - zp);
                        let a = if a.is_finite() { a } else { 0.0 };
                        if a < alpha || blocking == usize::MAX {
                            alpha = a;
                            blocking = p;
                        }
                    }
                }
                if blocking == usize::MAX {
                    for p in 0..kk {
                        self.x[self.passive[p]] = self.z[p];
                    }
                    break;
                }
                let alpha = alpha.clamp(0.0, 1.0);
                for p in 0..kk {
                    let s = self.passive[p];
                    let v = self.x[s] + alpha * (self.z[p] - self.x[s]);
                    self.x[s] = if p == blocking || v.is_nan() || v <= 0.0 {
                        0.0
                    } else {
                        v
                    };
                }
                self.drop_zeros();
                if self.passive.is_empty() {
                    break;
                }
            }
        }

        stats
    }

    /// Flags as excluded every sample whose kernel footprint (the samples a spike there
    /// reaches, `i − c ..= i − c + m − 1`) holds no sample of `y` above `tau · noise_v`
    /// ([`NnlsConfig::support_at_noise`]); nothing when the noise level is not a positive
    /// finite number. O(n).
    fn mask_support(&mut self, y: &[f32], g: &Geometry, tau: f32) {
        let level = tau as f64 * self.noise_v;
        if !(level.is_finite() && level > 0.0) {
            return;
        }
        let n = g.n as isize;
        let c = g.c.min(n + g.m as isize);
        let ahead = g.m as isize - 1 - c; // the footprint's reach after i (may be negative)
        // `last`: the latest sample above the level at or before i + ahead.
        let mut last = isize::MIN;
        let mut t = 0isize;
        for i in 0..n {
            while t <= i + ahead && t < n {
                if y[t as usize] as f64 > level {
                    last = t;
                }
                t += 1;
            }
            if last < i - c {
                self.flags[i as usize] = EXCLUDED;
            }
        }
    }

    /// The noise weights from the residual of the fit in `x` (see [`NnlsConfig::noise_weights`]):
    /// writes them into `wt` and returns true when the variance follows the signal, else leaves
    /// `wt` as it is and returns false.
    fn noise_weights(&mut self, g: &Geometry) -> bool {
        let n = g.n;
        self.fit_into_resid(g);
        let (mut c, mut sf, mut sff, mut sr, mut sfr, mut fmax) =
            (0.0f64, 0.0, 0.0, 0.0, 0.0, 0.0f64);
        for i in 0..n {
            if self.wt[i] > 0.0 {
                let f = self.resid[i].max(0.0);
                let r = (self.ys[i] - self.resid[i]).powi(2);
                c += 1.0;
                sf += f;
                sff += f * f;
                sr += r;
                sfr += f * r;
                fmax = fmax.max(f);
            }
        }
        let det = c * sff - sf * sf;
        if c < 3.0 || det <= 0.0 || sr <= 0.0 {
            return false;
        }
        let slope = (c * sfr - sf * sr) / det;
        let floor = ((sr - slope * sf) / c).max(NOISE_FLOOR_SHARE * sr / c);
        if !(slope > 0.0 && slope * fmax >= floor && floor.is_finite()) {
            return false;
        }
        for i in 0..n {
            if self.wt[i] > 0.0 {
                self.wt[i] = floor / (floor + slope * self.resid[i].max(0.0));
            }
        }
        true
    }
}

impl Deconvolver for Nnls {
    fn name(&self) -> &'static str {
        "nnls"
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        _sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.noise_v = noise_v as f64;
        self.run_masked(y, k, None, out)
    }

    fn run_excluding(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        _sample_ns: f64,
        excluded: &[bool],
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.noise_v = noise_v as f64;
        self.run_masked(y, k, Some(excluded), out)
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        self.config.worst_case_flops(n, m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A Gaussian kernel of `fwhm` samples with taps to ±3σ, centred.
    fn gaussian(fwhm: f64) -> Kernel {
        let sigma = fwhm / 2.354_82;
        let half = (3.0 * sigma).round() as i64;
        let taps: Vec<f32> = (-half..=half)
            .map(|i| (-0.5 * (i as f64 / sigma).powi(2)).exp() as f32)
            .collect();
        let mut k = Kernel::default();
        k.set_from_taps(&taps, half as usize, taps.len()).unwrap();
        k
    }

    /// `R x` in f64 (the kernel module's convention).
    fn conv(x: &[f64], k: &Kernel) -> Vec<f64> {
        let n = x.len() as isize;
        (0..n)
            .map(|i| {
                let mut acc = 0.0;
                for (j, &t) in k.taps.iter().enumerate() {
                    let s = i + k.center as isize - j as isize;
                    if s >= 0 && s < n {
                        acc += t as f64 * x[s as usize];
                    }
                }
                acc
            })
            .collect()
    }

    /// `Rᵀ r` in f64.
    fn corr(r: &[f64], k: &Kernel) -> Vec<f64> {
        let n = r.len() as isize;
        (0..n)
            .map(|i| {
                let mut acc = 0.0;
                for (j, &t) in k.taps.iter().enumerate() {
                    let s = i - k.center as isize + j as isize;
                    if s >= 0 && s < n {
                        acc += t as f64 * r[s as usize];
                    }
                }
                acc
            })
            .collect()
    }

    fn objective(y: &[f32], k: &Kernel, s: &[f64]) -> f64 {
        let r = conv(s, k);
        r.iter().zip(y).map(|(a, &b)| (a - b as f64).powi(2)).sum()
    }

    /// Deterministic pseudo-random numbers in [0, 1).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    fn run(cfg: NnlsConfig, y: &[f32], k: &Kernel) -> Result<Vec<f32>, DeconvError> {
        let mut d = Nnls::new(cfg, y.len().max(1), k.len().max(1));
        let mut out = vec![0.0f32; y.len()];
        d.run(y, k, 0.01, 1.0, &mut out)?;
        Ok(out)
    }

    fn assert_sane(y: &[f32], k: &Kernel) -> Vec<f32> {
        let out = run(NnlsConfig::default(), y, k).expect("runs");
        assert_eq!(out.len(), y.len());
        assert!(out.iter().all(|v| v.is_finite() && *v >= 0.0), "{out:?}");
        out
    }

    fn two_echoes(n: usize, k: &Kernel, at: [(usize, f64); 2]) -> Vec<f32> {
        let mut t = vec![0.0; n];
        for (i, a) in at {
            t[i] += a;
        }
        conv(&t, k).iter().map(|&v| v as f32).collect()
    }

    /// Dense Lawson-Hanson (normal equations, Gaussian elimination) for small problems.
    fn dense_nnls(y: &[f32], k: &Kernel) -> Vec<f64> {
        let n = y.len();
        let cols: Vec<Vec<f64>> = (0..n)
            .map(|s| {
                let mut e = vec![0.0; n];
                e[s] = 1.0;
                conv(&e, k)
            })
            .collect();
        let g =
            |a: usize, b: usize| -> f64 { cols[a].iter().zip(&cols[b]).map(|(p, q)| p * q).sum() };
        let yb: Vec<f64> = y.iter().map(|&v| v as f64).collect();
        let bvec: Vec<f64> = (0..n)
            .map(|s| cols[s].iter().zip(&yb).map(|(p, q)| p * q).sum())
            .collect();
        let solve = |p: &[usize]| -> Vec<f64> {
            let kk = p.len();
            let mut a: Vec<Vec<f64>> = (0..kk)
                .map(|r| {
                    let mut row: Vec<f64> = (0..kk).map(|c| g(p[r], p[c])).collect();
                    row.push(bvec[p[r]]);
                    row
                })
                .collect();
            for c in 0..kk {
                let piv = (c..kk)
                    .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
                    .unwrap();
                a.swap(c, piv);
                for r in c + 1..kk {
                    let f = a[r][c] / a[c][c];
                    let (top, bottom) = a.split_at_mut(r);
                    for (dst, src) in bottom[0][c..].iter_mut().zip(&top[c][c..]) {
                        *dst -= f * src;
                    }
                }
            }
            let mut z = vec![0.0; kk];
            for r in (0..kk).rev() {
                let mut v = a[r][kk];
                for c in r + 1..kk {
                    v -= a[r][c] * z[c];
                }
                z[r] = v / a[r][r];
            }
            z
        };
        let mut x = vec![0.0; n];
        let mut p: Vec<usize> = Vec::new();
        for _ in 0..3 * n {
            let r: Vec<f64> = conv(&x, k).iter().zip(&yb).map(|(a, b)| b - a).collect();
            let w = corr(&r, k);
            let cand = (0..n)
                .filter(|i| !p.contains(i))
                .max_by(|&a, &b| w[a].total_cmp(&w[b]));
            match cand {
                Some(j) if w[j] > 1e-12 => p.push(j),
                _ => break,
            }
            loop {
                let z = solve(&p);
                if z.iter().all(|&v| v > 0.0) {
                    for (i, &s) in p.iter().enumerate() {
                        x[s] = z[i];
                    }
                    break;
                }
                let mut alpha = f64::INFINITY;
                for (i, &s) in p.iter().enumerate() {
                    if z[i] <= 0.0 {
                        alpha = alpha.min(x[s] / (x[s] - z[i]));
                    }
                }
                for (i, &s) in p.iter().enumerate() {
                    x[s] += alpha * (z[i] - x[s]);
                }
                p.retain(|&s| x[s] > 1e-14);
                for (s, xs) in x.iter_mut().enumerate() {
                    if !p.contains(&s) {
                        *xs = 0.0;
                    }
                }
            }
        }
        x
    }

    #[test]
    fn gram_entries_are_exact_at_the_boundaries() {
        let mut k = Kernel::default();
        for (taps, centre) in [
            (vec![0.2f32, 1.0, 3.0, 2.0, 1.5, -0.4, 0.6], 2usize),
            (vec![1.0, 2.0, 0.5], 0),
            (vec![1.0, 2.0, 0.5, 0.25], 3),
        ] {
            k.set_from_taps(&taps, centre, 16).unwrap();
            for n in [1usize, 2, 3, 5, 6, 7, 8, 20] {
                let mut d = Nnls::new(NnlsConfig::default(), n, 16);
                let g = Geometry {
                    n,
                    m: k.len(),
                    c: centre as isize,
                    stride: 17,
                };
                d.prepare_kernel(&k, &g);
                let cols: Vec<Vec<f64>> = (0..n)
                    .map(|s| {
                        let mut e = vec![0.0; n];
                        e[s] = 1.0;
                        conv(&e, &k)
                    })
                    .collect();
                for s in 0..n {
                    for t in 0..n {
                        let dense: f64 = cols[s].iter().zip(&cols[t]).map(|(a, b)| a * b).sum();
                        let banded = g.gram(&d.q, s, t);
                        assert!(
                            (dense - banded).abs() < 1e-12,
                            "n {n} ({s},{t}): {dense} vs {banded}"
                        );
                        if g.interior(s) && s.abs_diff(t) < g.m {
                            let b = d.band[t + g.m - 1 - s];
                            assert!((dense - b).abs() < 1e-12);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn cholesky_downdate_matches_the_reduced_gram() {
        let k = gaussian(5.0);
        let n = 40;
        let mut d = Nnls::new(NnlsConfig::default(), n, 16);
        let g = Geometry {
            n,
            m: k.len(),
            c: k.center as isize,
            stride: 17,
        };
        d.prepare_kernel(&k, &g);
        for &s in &[0usize, 3, 7, 8, 20, 24, 39] {
            assert!(d.chol_push(&g, s));
        }
        for p in [2usize, 0, 4] {
            d.chol_remove(p);
            let kk = d.passive.len();
            let st = d.max_k;
            for r in 0..kk {
                for c in 0..=r {
                    let llt: f64 = (0..=c)
                        .map(|i| d.chol[r * st + i] * d.chol[c * st + i])
                        .sum();
                    let gram = g.gram(&d.q, d.passive[r], d.passive[c]);
                    assert!((llt - gram).abs() < 1e-12, "({r},{c}) {llt} vs {gram}");
                }
                assert!(d.chol[r * st + r] > 0.0);
            }
        }
        assert_eq!(d.passive, vec![3, 8, 20, 24]);
    }

    #[test]
    fn recovers_two_spikes_exactly() {
        let k = gaussian(16.0);
        assert_eq!(k.len(), 41);
        let y = two_echoes(256, &k, [(80, 1.0), (170, 0.7)]);
        let out = assert_sane(&y, &k);
        assert!((out[80] - 1.0).abs() < 1e-3, "{}", out[80]);
        assert!((out[170] - 0.7).abs() < 1e-3, "{}", out[170]);
        for (i, &v) in out.iter().enumerate() {
            if i != 80 && i != 170 {
                assert!(v < 1e-3, "sample {i}: {v}");
            }
        }
    }

    #[test]
    fn result_satisfies_kkt() {
        let k = gaussian(5.0);
        let mut rng = Lcg(7);
        let n = 96;
        let mut t = vec![0.0; n];
        for _ in 0..8 {
            t[(rng.next() * n as f64) as usize] += rng.next() * 3.0;
        }
        let y: Vec<f32> = conv(&t, &k)
            .iter()
            .map(|&v| (v + 0.05 * (rng.next() - 0.5)) as f32)
            .collect();
        let cfg = NnlsConfig {
            max_iterations: 500,
            tolerance: 1e-7,
            ..Default::default()
        };
        let out = run(cfg, &y, &k).unwrap();
        let s: Vec<f64> = out.iter().map(|&v| v as f64).collect();
        let r: Vec<f64> = conv(&s, &k)
            .iter()
            .zip(&y)
            .map(|(a, &b)| a - b as f64)
            .collect();
        let grad = corr(&r, &k);
        let yb: Vec<f64> = y.iter().map(|&v| v as f64).collect();
        let bmax = corr(&yb, &k).iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let tol = 1e-4 * bmax;
        for i in 0..n {
            assert!(s[i] >= 0.0);
            if s[i] > 0.0 {
                assert!(grad[i].abs() <= tol, "active {i}: {}", grad[i]);
            } else {
                assert!(grad[i] >= -tol, "zero {i}: {}", grad[i]);
            }
        }
    }

    #[test]
    fn matches_dense_lawson_hanson() {
        let mut rng = Lcg(42);
        for trial in 0..20 {
            let n = 30;
            let fw = 2.0 + 4.0 * rng.next();
            let mut k = gaussian(fw);
            if trial % 3 == 1 {
                // Asymmetric, off-centre kernel.
                let taps: Vec<f32> = (0..7)
                    .map(|i| 1.0 + (i as f32) * 0.6 - (i * i) as f32 * 0.08)
                    .collect();
                k.set_from_taps(&taps, 1, 16).unwrap();
            }
            let mut t = vec![0.0; n];
            for _ in 0..5 {
                t[(rng.next() * n as f64) as usize] += rng.next() * 2.0;
            }
            let y: Vec<f32> = conv(&t, &k)
                .iter()
                .map(|&v| (v + 0.2 * (rng.next() - 0.5)) as f32)
                .collect();
            let cfg = NnlsConfig {
                max_iterations: 200,
                tolerance: 1e-9,
                ..Default::default()
            };
            let out = run(cfg, &y, &k).unwrap();
            let mine = objective(&y, &k, &out.iter().map(|&v| v as f64).collect::<Vec<_>>());
            let reference = objective(&y, &k, &dense_nnls(&y, &k));
            let energy: f64 = y.iter().map(|&v| (v as f64).powi(2)).sum();
            let denom = reference.max(1e-6 * energy);
            assert!(
                (mine - reference).abs() <= 1e-4 * denom,
                "trial {trial}: {mine} vs {reference}"
            );
        }
    }

    #[test]
    fn all_zero() {
        let out = assert_sane(&[0.0; 64], &gaussian(16.0));
        assert!(out.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn constant() {
        let out = assert_sane(&[3.0; 128], &gaussian(16.0));
        assert!(out.iter().any(|&v| v > 0.0));
    }

    #[test]
    fn single_sample_spike() {
        let mut y = vec![0.0f32; 64];
        y[30] = 5.0;
        assert_sane(&y, &gaussian(16.0));
        let mut delta = Kernel::default();
        delta.set_from_taps(&[1.0], 0, 1).unwrap();
        let out = assert_sane(&y, &delta);
        assert!((out[30] - 5.0).abs() < 1e-5);
    }

    #[test]
    fn weighted_gram_with_unit_weights_equals_the_prefix_table_at_every_boundary() {
        for (fwhm, n) in [(5.0, 40usize), (9.0, 12), (3.0, 7)] {
            let k = gaussian(fwhm);
            let mut d = Nnls::new(NnlsConfig::default(), 64, 64);
            let g = Geometry {
                n,
                m: k.taps.len(),
                c: k.center as isize,
                stride: d.max_taps + 1,
            };
            d.prepare_kernel(&k, &g);
            for (t, &v) in d.taps.iter_mut().zip(&k.taps) {
                *t = v as f64;
            }
            d.wt[..n].fill(1.0);
            for s in 0..n {
                for t in 0..n {
                    d.weighted = false;
                    let a = d.gram_at(&g, s, t);
                    d.weighted = true;
                    let b = d.gram_at(&g, s, t);
                    assert!(
                        (a - b).abs() <= 1e-12 * a.abs().max(1e-300),
                        "{s} {t}: {a} {b}"
                    );
                }
            }
        }
    }

    /// Two echoes 40 samples apart, the stronger one's top clipped at `clip`.
    fn clipped_pair(k: &Kernel, clip: f32) -> (Vec<f32>, Vec<bool>) {
        let y: Vec<f32> = two_echoes(128, k, [(40, 1.0), (80, 3.0)])
            .into_iter()
            .map(|v| v.min(clip))
            .collect();
        let mut ex = Vec::new();
        crate::signal::drift::flag_saturated(&y, &mut ex);
        (y, ex)
    }

    #[test]
    fn clipped_samples_left_out_recover_the_clipped_echo() {
        let k = gaussian(8.0);
        let peak = two_echoes(128, &k, [(80, 3.0), (40, 0.0)])
            .into_iter()
            .fold(0.0f32, f32::max);
        let (y, ex) = clipped_pair(&k, 0.6 * peak);
        assert!(ex.iter().filter(|&&e| e).count() >= 4);
        let mut d = Nnls::new(NnlsConfig::default(), 128, 64);
        let mut plain = vec![0.0; 128];
        d.run(&y, &k, 0.0, 1.0, &mut plain).unwrap();
        let mut kept = vec![0.0; 128];
        d.run_excluding(&y, &k, 0.0, 1.0, &ex, &mut kept).unwrap();
        let area = |o: &[f32]| o[70..90].iter().sum::<f32>();
        // The flat top fitted as it is loses a tenth of the area or more; left out, the flanks
        // give the echo back.
        assert!(area(&plain) < 2.7, "plain {}", area(&plain));
        assert!((area(&kept) - 3.0).abs() < 0.05, "kept {}", area(&kept));
        assert!((o_sum(&kept[30..50]) - 1.0).abs() < 0.02);
        // A mask of the wrong length is refused.
        assert!(matches!(
            d.run_excluding(&y, &k, 0.0, 1.0, &ex[1..], &mut kept),
            Err(DeconvError::LengthMismatch { .. })
        ));
    }

    fn o_sum(o: &[f32]) -> f32 {
        o.iter().sum()
    }

    /// `y` with noise of variance `floor² + gain · signal` (Gaussian draws).
    fn with_noise(y: &[f32], floor: f64, gain: f64, seed: u64) -> Vec<f32> {
        let mut rng = Lcg(seed);
        y.iter()
            .map(|&v| {
                // Box-Muller from two uniforms.
                let (u1, u2) = (rng.next().max(1e-12), rng.next());
                let z = (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos();
                let sd = (floor * floor + gain * (v as f64).max(0.0)).sqrt();
                (v as f64 + sd * z) as f32
            })
            .collect()
    }

    #[test]
    fn noise_weights_refit_only_when_the_variance_follows_the_signal() {
        let k = gaussian(8.0);
        let clean = two_echoes(200, &k, [(60, 1.0), (140, 4.0)]);
        let peak = clean.iter().fold(0.0f32, |a, &v| a.max(v)) as f64;
        let cfg = NnlsConfig {
            max_iterations: 120,
            noise_weights: true,
            ..Default::default()
        };
        let mut d = Nnls::new(cfg.clone(), 200, 64);
        let mut plain = Nnls::new(
            NnlsConfig {
                noise_weights: false,
                ..cfg
            },
            200,
            64,
        );
        let (mut a, mut b) = (vec![0.0; 200], vec![0.0; 200]);
        // White noise: no second fit, the plain result bit for bit.
        let white = with_noise(&clean, 0.02 * peak, 0.0, 3);
        d.run(&white, &k, 0.0, 1.0, &mut a).unwrap();
        assert!(!d.weighted);
        plain.run(&white, &k, 0.0, 1.0, &mut b).unwrap();
        assert_eq!(a, b);
        // Shot noise (variance 100 × the floor's at the peak): the weighted refit runs, and
        // over 20 draws it fits the truth more closely than the plain fit.
        let truth = clean.clone();
        let err = |o: &[f32]| -> f64 {
            let s: Vec<f64> = o.iter().map(|&v| v as f64).collect();
            conv(&s, &k)
                .iter()
                .zip(&truth)
                .map(|(f, &t)| (f - t as f64).powi(2))
                .sum::<f64>()
        };
        let (mut ew, mut ep) = (0.0, 0.0);
        for seed in 0..20 {
            let shot = with_noise(&clean, 0.005 * peak, 0.0025 * peak, 5 + seed);
            let s1 = d.run(&shot, &k, 0.0, 1.0, &mut a).unwrap();
            assert!(d.weighted, "seed {seed}");
            let s0 = plain.run(&shot, &k, 0.0, 1.0, &mut b).unwrap();
            assert!(s1.iterations > s0.iterations);
            ew += err(&a);
            ep += err(&b);
        }
        assert!(ew < ep, "weighted {ew} plain {ep}");
    }

    #[test]
    fn saturated_plateau() {
        let mut y = vec![12.0f32; 256];
        y[100..140].fill(65535.0);
        assert_sane(&y, &gaussian(16.0));
    }

    #[test]
    fn negative_values() {
        let y: Vec<f32> = (0..100).map(|i| -1.0 - (i % 7) as f32).collect();
        let out = assert_sane(&y, &gaussian(16.0));
        assert!(out.iter().all(|&v| v == 0.0));
        let y: Vec<f32> = (0..100).map(|i| ((i as f32) * 0.3).sin() * 10.0).collect();
        assert_sane(&y, &gaussian(8.0));
    }

    #[test]
    fn nan_and_inf_are_errors() {
        let k = gaussian(16.0);
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut y = vec![1.0f32; 32];
            y[5] = bad;
            assert_eq!(
                run(NnlsConfig::default(), &y, &k),
                Err(DeconvError::NonFiniteInput)
            );
        }
    }

    #[test]
    fn denormals() {
        let k = gaussian(16.0);
        let y: Vec<f32> = (0..128)
            .map(|i| f32::from_bits(1 + (i % 5) as u32))
            .collect();
        assert_sane(&y, &k);
        let y = two_echoes(128, &k, [(40, 1e-40), (90, 5e-41)]);
        assert_sane(&y, &k);
    }

    #[test]
    fn kernel_longer_than_segment() {
        let k = gaussian(16.0);
        let y: Vec<f32> = (0..10).map(|i| 1.0 + i as f32).collect();
        assert_sane(&y, &k);
    }

    #[test]
    fn one_sample_segment() {
        assert_sane(&[2.0], &gaussian(16.0));
        assert_sane(&[-2.0], &gaussian(4.0));
    }

    #[test]
    fn long_4096_sample_segment() {
        let k = gaussian(16.0);
        let mut rng = Lcg(3);
        let mut t = vec![0.0; 4096];
        for _ in 0..30 {
            t[(rng.next() * 4096.0) as usize] += rng.next() * 100.0;
        }
        let y: Vec<f32> = conv(&t, &k)
            .iter()
            .map(|&v| (v + rng.next() - 0.5) as f32)
            .collect();
        assert_sane(&y, &k);
    }

    #[test]
    fn asymmetric_off_centre_kernel() {
        let mut k = Kernel::default();
        k.set_from_taps(&[0.2, 1.0, 3.0, 2.0, 1.5, 1.0, 0.6, 0.3, 0.1], 2, 16)
            .unwrap();
        let y = two_echoes(80, &k, [(3, 2.0), (60, 1.0)]);
        let out = assert_sane(&y, &k);
        assert!((out[3] - 2.0).abs() < 1e-3 && (out[60] - 1.0).abs() < 1e-3);
        // Centre at the far end, too.
        k.set_from_taps(&[0.2, 1.0, 3.0, 2.0], 3, 16).unwrap();
        assert_sane(&y, &k);
    }

    #[test]
    fn ringing_kernel_with_negative_lobes() {
        let taps: Vec<f32> = (-12..=12)
            .map(|i| {
                let x = i as f32 * 0.5;
                (-0.1 * x * x).exp() * x.cos()
            })
            .collect();
        let mut k = Kernel::default();
        k.set_from_taps(&taps, 12, 32).unwrap();
        let y = two_echoes(128, &k, [(40, 1.0), (70, 0.5)]);
        assert_sane(&y, &k);
        let y: Vec<f32> = (0..128).map(|i| ((i * 37 % 11) as f32) - 3.0).collect();
        assert_sane(&y, &k);
    }

    #[test]
    fn echoes_at_snr_1() {
        let k = gaussian(16.0);
        let mut rng = Lcg(11);
        let clean = two_echoes(256, &k, [(80, 10.0), (160, 10.0)]);
        let peak = clean.iter().fold(0.0f32, |a, &v| a.max(v));
        let y: Vec<f32> = clean
            .iter()
            .map(|&v| v + peak * 2.0 * (rng.next() as f32 - 0.5) * 1.732)
            .collect();
        assert_sane(&y, &k);
    }

    #[test]
    fn two_echoes_half_fwhm_apart() {
        let k = gaussian(16.0);
        let y = two_echoes(256, &k, [(120, 1.0), (128, 0.8)]);
        assert_sane(&y, &k);
        // At 1e-4 the stop comes before the pair is split (the merged fit is already within
        // tolerance); the default, 1e-6, resolves both exactly.
        let loose = NnlsConfig {
            max_iterations: 50,
            tolerance: 1e-4,
            ..Default::default()
        };
        let out = run(loose, &y, &k).unwrap();
        assert!(out[115..135].iter().sum::<f32>() > 1.7);
        assert!((out[120] - 1.0).abs() > 1e-2 || (out[128] - 0.8).abs() > 1e-2);
        let out = run(NnlsConfig::default(), &y, &k).unwrap();
        assert!(
            (out[120] - 1.0).abs() < 1e-3 && (out[128] - 0.8).abs() < 1e-3,
            "{} {}",
            out[120],
            out[128]
        );
    }

    #[test]
    fn size_errors() {
        let k = gaussian(16.0);
        let mut d = Nnls::new(NnlsConfig::default(), 16, 64);
        let mut out = vec![0.0; 32];
        assert!(matches!(
            d.run(&[1.0; 32], &k, 0.0, 1.0, &mut out),
            Err(DeconvError::TooLong { .. })
        ));
        let mut d = Nnls::new(NnlsConfig::default(), 64, 8);
        assert!(matches!(
            d.run(&[1.0; 32], &k, 0.0, 1.0, &mut out),
            Err(DeconvError::KernelTooLong { .. })
        ));
        let mut d = Nnls::new(NnlsConfig::default(), 64, 64);
        let mut short = vec![0.0; 31];
        assert!(matches!(
            d.run(&[1.0; 32], &k, 0.0, 1.0, &mut short),
            Err(DeconvError::LengthMismatch { .. })
        ));
        // An empty kernel is refused like every method refuses it; an empty segment is fine.
        assert_eq!(
            d.run(&[1.0; 32], &Kernel::default(), 0.0, 1.0, &mut out),
            Err(DeconvError::BadKernel)
        );
        assert!(d.run(&[], &k, 0.0, 1.0, &mut []).is_ok());
    }

    #[test]
    fn config_rejects_unknown_fields_and_has_defaults() {
        let c: NnlsConfig = toml::from_str("max_iterations = 20").unwrap();
        assert_eq!(c.max_iterations, 20);
        assert_eq!(c.tolerance, 1e-6);
        assert!(toml::from_str::<NnlsConfig>("iterations = 20").is_err());
    }

    #[test]
    fn worst_case_is_stated() {
        let d = Nnls::new(NnlsConfig::default(), 256, 41);
        let f = d.worst_case_flops(256, 41);
        // The weighted pass's bound (a run may leave samples out).
        assert_eq!(f, 3_076_029);
        let weighted = NnlsConfig {
            noise_weights: true,
            ..Default::default()
        };
        assert!(weighted.worst_case_flops(256, 41) > 2 * f);
        let masked = NnlsConfig {
            support_at_noise: Some(4.0),
            ..Default::default()
        };
        assert_eq!(masked.worst_case_flops(256, 41), f + 2 * 256);
        assert_eq!(d.worst_case_flops(0, 0), 0);
    }

    /// The method with `support_at_noise = tau` on `y` at noise level `noise_v`: the output
    /// and the outer iterations.
    fn run_support(tau: Option<f32>, y: &[f32], k: &Kernel, noise_v: f32) -> (Vec<f32>, u32) {
        let cfg = NnlsConfig {
            support_at_noise: tau,
            ..NnlsConfig::default()
        };
        let mut d = Nnls::new(cfg, y.len().max(1), k.len().max(1));
        let mut out = vec![0.0f32; y.len()];
        let st = d.run(y, k, noise_v, 1.0, &mut out).expect("runs");
        (out, st.iterations)
    }

    /// True when a spike at `i` reaches a sample of `y` above `level` (its footprint
    /// `i − c ..= i − c + m − 1`).
    fn reaches_echo(y: &[f32], k: &Kernel, i: usize, level: f32) -> bool {
        let lo = i as isize - k.center as isize;
        (lo..lo + k.len() as isize)
            .filter(|&t| t >= 0 && (t as usize) < y.len())
            .any(|t| y[t as usize] > level)
    }

    #[test]
    fn spikes_only_near_echoes_keep_the_echoes_and_drop_the_noise_spikes() {
        let k = gaussian(8.0);
        let mut y = two_echoes(256, &k, [(80, 1.0), (84, 0.6)]);
        // Uniform noise of ±0.02: mean |noise| 0.01 (the denoise stage's noise level).
        let mut rng = Lcg(7);
        for v in y.iter_mut() {
            *v += (0.04 * rng.next() - 0.02) as f32;
        }
        let noise_v = 0.01;
        let (all, it_all) = run_support(None, &y, &k, noise_v);
        let (near, it_near) = run_support(Some(4.0), &y, &k, noise_v);
        // Without the mask NNLS fits the noise far from the echoes; with it nothing is there.
        let far = |o: &[f32]| {
            (0..o.len())
                .filter(|&i| o[i] > 0.0 && !reaches_echo(&y, &k, i, 4.0 * noise_v))
                .count()
        };
        assert!(
            far(&all) >= 5,
            "noise spikes without the mask: {}",
            far(&all)
        );
        assert_eq!(far(&near), 0);
        assert!(it_near < it_all, "{it_near} vs {it_all} iterations");
        // The echoes keep their area and place.
        let area = |o: &[f32]| o[70..95].iter().sum::<f32>();
        assert!((area(&near) - 1.6).abs() < 0.05, "{}", area(&near));
        assert!((area(&near) - area(&all)).abs() < 0.03);
        let centroid = |o: &[f32]| (70..95).map(|i| i as f32 * o[i]).sum::<f32>() / area(o);
        let (c_near, c_all) = (centroid(&near), centroid(&all));
        assert!((c_near - c_all).abs() < 0.2, "{c_near} vs {c_all}");
        assert!((c_near - 81.5).abs() < 0.6, "{c_near}");
    }

    #[test]
    fn spikes_only_near_echoes_without_a_noise_level_change_nothing() {
        let k = gaussian(8.0);
        let y = two_echoes(128, &k, [(40, 1.0), (90, 0.3)]);
        let (plain, _) = run_support(None, &y, &k, 0.0);
        for noise_v in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let (near, _) = run_support(Some(4.0), &y, &k, noise_v);
            assert_eq!(near, plain, "noise_v {noise_v}");
        }
        // A level above every sample: no spike anywhere, a zero (finite) result.
        let (none, _) = run_support(Some(4.0), &y, &k, 1.0);
        assert!(none.iter().all(|&v| v == 0.0));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn spikes_only_where_they_reach_an_echo(
            y in proptest::collection::vec(-1.0f32..1.0, 1..200),
            taps in proptest::collection::vec(0.01f32..1.0, 1..30),
            centre in 0usize..30,
            tau in 0.5f32..3.0,
        ) {
            let mut k = Kernel::default();
            let centre = centre % taps.len();
            if k.set_from_taps(&taps, centre, 64).is_err() {
                return Ok(());
            }
            let (out, _) = run_support(Some(tau), &y, &k, 0.2);
            for (i, &v) in out.iter().enumerate() {
                prop_assert!(v.is_finite() && v >= 0.0);
                prop_assert!(v == 0.0 || reaches_echo(&y, &k, i, tau * 0.2), "spike at {}", i);
            }
        }

        #[test]
        fn never_panics_and_stays_non_negative(
            y in proptest::collection::vec(-100.0f32..70000.0, 0..300),
            taps in proptest::collection::vec(-0.5f32..1.0, 1..40),
            centre in 0usize..40,
            iterations in 0u32..80,
        ) {
            let mut k = Kernel::default();
            let centre = centre % taps.len();
            if k.set_from_taps(&taps, centre, 64).is_err() {
                return Ok(());
            }
            let cfg = NnlsConfig { max_iterations: iterations, tolerance: 1e-4, ..Default::default() };
            let mut d = Nnls::new(cfg.clone(), 300, 64);
            let mut out = vec![0.0f32; y.len()];
            d.run(&y, &k, 1.0, 1.0, &mut out).unwrap();
            prop_assert!(out.iter().all(|v| v.is_finite() && *v >= 0.0));
            // The same with the noise-weighted refit and every third sample left out.
            let mut w = Nnls::new(NnlsConfig { noise_weights: true, ..cfg }, 300, 64);
            let excluded: Vec<bool> = (0..y.len()).map(|i| i % 3 == 0).collect();
            w.run_excluding(&y, &k, 1.0, 1.0, &excluded, &mut out).unwrap();
            prop_assert!(out.iter().all(|v| v.is_finite() && *v >= 0.0));
        }
    }
}
