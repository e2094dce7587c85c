//! Bounded Levenberg-Marquardt fit of a sum of Gaussians
//! `Σ_k A_k exp(−(t − μ_k)² / 2σ_k²)` to one segment (t in bins from the segment's first sample).
//!
//! Parameters per component: amplitude `A` (signal units, ≥ 0), centre `μ` (bins, inside
//! [`Bounds::center_min_bins`, `Bounds::center_max_bins`]) and width `σ` (bins, inside
//! [`Bounds::sigma_min_bins`, `Bounds::sigma_max_bins`]). Bounds are enforced by projection: every
//! trial point is clamped into the box before its cost is evaluated (a projected LM step).
//!
//! Algorithm (Marquardt 1963, with Nielsen-style simple damping schedule):
//! 1. at the current parameters accumulate the normal equations `JᵀJ` and `Jᵀr`. A component is
//!    evaluated only within ±[`WINDOW_SIGMAS`] σ of its centre (where `exp` is above ~1.5e-8;
//!    the model is exactly 0 beyond), by recurrence (`g(t + 1) = g(t) r(t)`,
//!    `r(t + 1) = r(t) q`: three `exp` per component instead of one per sample); its three
//!    Jacobian columns are stored over its window, its entries of `JᵀJ`/`Jᵀr` are dot products
//!    over that window, and two components couple only over the overlap of their windows;
//! 2. solve `(JᵀJ + λ·diag(JᵀJ)) δ = Jᵀr` by Cholesky on the profile of `JᵀJ` (rows are 0 left
//!    of the first component whose window meets theirs; with the components sorted by centre
//!    the system is banded, and components whose windows do not meet form independent blocks
//!    the factorisation never mixes);
//! 3. clamp `p + δ` into the bounds and evaluate its residual sum of squares — `Σ (y − model)²`
//!    over the union of the windows plus `Σ y²` outside them (prefix sums of `y²`, computed
//!    once per fit), i.e. the same RSS over the whole segment; the same pass stores the trial's
//!    residual and Jacobian columns. Accept and divide λ by 10 when the RSS decreased (the
//!    next normal equations are then only the dot products of those columns: one model pass
//!    per trial step), otherwise multiply λ by 10 and retry from the same normal equations.
//!
//! The fit has converged when the RSS decrease of an accepted step, or the decrease the
//! linearised model predicts for the next one, is below `max(10⁻⁶, 0.01 / n)` × RSS (n samples
//! in the segment): a change of χ² by ~0.01 with `RSS / n` as the noise variance (see
//! `CHI2_TOLERANCE`), or when λ exceeds 10¹⁰.
//!
//! Each trial step counts as one iteration; the caller's iteration cap bounds the work (one
//! cost pass and at most one normal-equation pass per iteration, each linear in the samples
//! inside the windows, not in the segment's length).
//!
//! **Why a hand-written solver.** The system is at most 24 × 24 ([`MAX_PARAMS`]) and symmetric
//! positive (semi-)definite, so a textbook Cholesky factorisation on fixed-size arrays owned by
//! the fitter is exact enough in `f64`, allocation-free and a few dozen lines. Pulling in
//! `nalgebra` (or the `levenberg-marquardt` crate, which depends on it) would add a second
//! linear-algebra stack to the tree for one tiny dense solve, and its dynamically sized matrices
//! would allocate per call.

/// Largest number of Gaussian components one fit can hold.
pub const MAX_COMPONENTS: usize = 8;
/// Largest number of parameters (3 per component).
pub const MAX_PARAMS: usize = 3 * MAX_COMPONENTS;
/// Half-width, in σ, of the window in which a component is evaluated.
pub const WINDOW_SIGMAS: f64 = 6.0;

/// Damping factor at the start of a fit (relative to `diag(JᵀJ)`).
const LAMBDA_START: f64 = 1e-3;
/// Largest damping before the fit is declared stuck at a minimum.
const LAMBDA_MAX: f64 = 1e10;
/// Smallest damping.
const LAMBDA_MIN: f64 = 1e-12;
/// Relative decrease of the residual sum of squares (achieved, or predicted by the linearised
/// model for the next step) below which the fit has always converged.
const RELATIVE_TOLERANCE: f64 = 1e-6;
/// Decrease of the residual sum of squares, in units of its mean per sample (`RSS / n`, an
/// estimate of the noise variance when the model fits), below which the fit has converged: a
/// change of χ² by about 0.01, negligible against the parameters' statistical uncertainty (the
/// region where χ² rises by 1). For segments shorter than 10⁴ samples this is the looser of
/// the two tests; it ends the long creep of noise-limited fits through a flat valley (relative
/// decreases of 10⁻⁴…10⁻⁶ per step) that moves the parameters by a small fraction of their
/// uncertainty.
const CHI2_TOLERANCE: f64 = 0.01;

/// One Gaussian component.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Gaussian {
    /// Peak amplitude, signal units.
    pub amplitude: f64,
    /// Centre, bins from the segment's first sample (fractional).
    pub center_bins: f64,
    /// Standard deviation, bins.
    pub sigma_bins: f64,
}

impl Gaussian {
    /// Value of the component at `t` bins.
    pub fn at(&self, t: f64) -> f64 {
        let d = (t - self.center_bins) / self.sigma_bins;
        self.amplitude * (-0.5 * d * d).exp()
    }
}

/// The box the parameters are kept in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    /// Smallest centre, bins.
    pub center_min_bins: f64,
    /// Largest centre, bins.
    pub center_max_bins: f64,
    /// Smallest σ, bins (must be positive).
    pub sigma_min_bins: f64,
    /// Largest σ, bins.
    pub sigma_max_bins: f64,
}

impl Bounds {
    /// Clamps one component into the box (amplitude ≥ 0).
    pub fn clamp(&self, g: &mut Gaussian) {
        g.amplitude = g.amplitude.max(0.0);
        g.center_bins = g
            .center_bins
            .clamp(self.center_min_bins, self.center_max_bins);
        g.sigma_bins = g.sigma_bins.clamp(self.sigma_min_bins, self.sigma_max_bins);
    }
}

/// What one Levenberg-Marquardt run did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LmReport {
    /// Trial steps taken (accepted or not).
    pub iterations: u32,
    /// Residual sum of squares at the returned parameters, signal units².
    pub rss: f64,
    /// The relative decrease fell below the tolerance (or the damping saturated) before the
    /// iteration cap.
    pub converged: bool,
}

/// A reusable fitter: the normal equations and their factor live in fixed-size arrays and the
/// per-sample work buffers (model, Jacobian columns within each component's window, prefix sums
/// of `y²`) are sized for the longest segment seen ([`GaussFitter::with_capacity`] sizes them up
/// front), so a fit allocates nothing.
pub struct GaussFitter {
    jtj: [[f64; MAX_PARAMS]; MAX_PARAMS],
    jtr: [f64; MAX_PARAMS],
    factor: [[f64; MAX_PARAMS]; MAX_PARAMS],
    step: [f64; MAX_PARAMS],
    /// Per parameter, the first column of its row of `JᵀJ` (lower triangle) that can be
    /// non-zero: the first parameter of the first component whose window meets its own.
    first: [usize; MAX_PARAMS],
    /// Sample windows `[lo, hi]` (inclusive) of the components at the last evaluation.
    windows: [(usize, usize); MAX_COMPONENTS],
    /// Samples the buffers below hold.
    capacity: usize,
    /// Model, then residual `y − model`, within the windows; `capacity` values.
    model: Vec<f64>,
    /// Jacobian column of parameter `j` at sample `i`: `jac[j × capacity + i]` (valid inside the
    /// parameter's component window only).
    jac: Vec<f64>,
    /// `y2[i] = Σ_{t < i} y_t²`; `capacity + 1` values.
    y2: Vec<f64>,
}

impl Default for GaussFitter {
    fn default() -> Self {
        Self::new()
    }
}

impl GaussFitter {
    /// A fitter (about 14 KiB of fixed-size work arrays); per-sample buffers grow on first use.
    pub fn new() -> Self {
        Self::with_capacity(0)
    }

    /// A fitter whose per-sample buffers hold segments of `max_samples` (about
    /// `(3 × MAX_PARAMS + 2) × 8` bytes per sample), so that fits of segments up to that length
    /// never allocate.
    pub fn with_capacity(max_samples: usize) -> Self {
        let mut f = GaussFitter {
            jtj: [[0.0; MAX_PARAMS]; MAX_PARAMS],
            jtr: [0.0; MAX_PARAMS],
            factor: [[0.0; MAX_PARAMS]; MAX_PARAMS],
            step: [0.0; MAX_PARAMS],
            first: [0; MAX_PARAMS],
            windows: [(0, 0); MAX_COMPONENTS],
            capacity: 0,
            model: Vec::new(),
            jac: Vec::new(),
            y2: Vec::new(),
        };
        f.reserve(max_samples);
        f
    }

    fn reserve(&mut self, n: usize) {
        if n <= self.capacity {
            return;
        }
        self.capacity = n;
        self.model = vec![0.0; n];
        self.jac = vec![0.0; MAX_PARAMS * n];
        self.y2 = vec![0.0; n + 1];
    }

    /// Residual sum of squares of `comps` against `y`, signal units² (reference
    /// implementation: every sample, one `exp` per sample and component within its window).
    pub fn rss(y: &[f32], comps: &[Gaussian]) -> f64 {
        let mut rss = 0.0;
        for (i, &v) in y.iter().enumerate() {
            let r = v as f64 - model_at(comps, i as f64);
            rss += r * r;
        }
        rss
    }

    /// Writes `y − model` into `res` (`res.len() == y.len()`) and returns the residual sum of
    /// squares, signal units². The same model as [`model_at`] (each component within its
    /// window), evaluated only inside the windows, by recurrence.
    pub fn residual(&mut self, y: &[f32], comps: &[Gaussian], res: &mut [f32]) -> f64 {
        let n = y.len();
        self.reserve(n);
        res[..n].copy_from_slice(y);
        let k = comps.len().min(MAX_COMPONENTS);
        self.model_in_windows(&comps[..k], n, false);
        let (merged, count) = self.union(k);
        let mut rss = 0.0;
        let mut next = 0;
        for &(lo, hi) in &merged[..count] {
            rss += y[next..lo]
                .iter()
                .map(|&v| (v as f64) * (v as f64))
                .sum::<f64>();
            for i in lo..=hi {
                let r = y[i] as f64 - self.model[i];
                res[i] = y[i] - self.model[i] as f32;
                rss += r * r;
            }
            next = hi + 1;
        }
        rss + y[next..n]
            .iter()
            .map(|&v| (v as f64) * (v as f64))
            .sum::<f64>()
    }

    /// Fits `comps` (initial guesses in, fitted parameters out; at most [`MAX_COMPONENTS`],
    /// extra ones are left untouched) to `y` with at most `max_iterations` trial steps, keeping
    /// every parameter inside `bounds`. The guesses are clamped into the bounds first.
    /// Components sorted by centre make the solve cheapest (the normal equations are then
    /// banded).
    pub fn fit(
        &mut self,
        y: &[f32],
        comps: &mut [Gaussian],
        bounds: &Bounds,
        max_iterations: u32,
    ) -> LmReport {
        let k = comps.len().min(MAX_COMPONENTS);
        let comps = &mut comps[..k];
        for g in comps.iter_mut() {
            bounds.clamp(g);
        }
        let m = 3 * k;
        if k == 0 || y.is_empty() {
            return LmReport {
                iterations: 0,
                rss: Self::rss(y, comps),
                converged: true,
            };
        }
        let n = y.len();
        self.reserve(n);
        let mut acc = 0.0f64;
        self.y2[0] = 0.0;
        for (s, &v) in self.y2[1..=n].iter_mut().zip(y) {
            acc += (v as f64) * (v as f64);
            *s = acc;
        }
        let mut rss = self.windowed_rss(y, comps, true);
        self.accumulate_normal_equations(k);
        let mut lambda = LAMBDA_START;
        let tolerance = RELATIVE_TOLERANCE.max(CHI2_TOLERANCE / n as f64);
        let mut iterations = 0;
        let mut converged = false;
        let mut trial = [Gaussian::default(); MAX_COMPONENTS];
        while iterations < max_iterations {
            if rss <= f64::MIN_POSITIVE {
                converged = true;
                break;
            }
            iterations += 1;
            let frozen = self.active_bounds(comps, bounds);
            if !self.solve_damped(m, lambda, &frozen) {
                lambda *= 10.0;
                if lambda > LAMBDA_MAX {
                    converged = true;
                    break;
                }
                continue;
            }
            // Reduction of the RSS the linearised model predicts for this step:
            // 2δ·Jᵀr − δᵀJᵀJδ. When even that is negligible, no step can make progress.
            let predicted = self.predicted_reduction(m);
            if predicted <= tolerance * rss {
                converged = true;
                break;
            }
            for (j, (t, g)) in trial.iter_mut().zip(comps.iter()).enumerate() {
                *t = Gaussian {
                    amplitude: g.amplitude + self.step[3 * j],
                    center_bins: g.center_bins + self.step[3 * j + 1],
                    sigma_bins: g.sigma_bins + self.step[3 * j + 2],
                };
                bounds.clamp(t);
            }
            // The trial's residual and Jacobian columns replace the current point's (its normal
            // equations are already accumulated): if the step is accepted, only the dot products
            // remain to be done.
            let new_rss = self.windowed_rss(y, &trial[..k], true);
            if new_rss.is_finite() && new_rss < rss {
                let relative = (rss - new_rss) / rss;
                comps.copy_from_slice(&trial[..k]);
                lambda = (lambda * 0.1).max(LAMBDA_MIN);
                rss = new_rss;
                if relative < tolerance {
                    converged = true;
                    break;
                }
                self.accumulate_normal_equations(k);
            } else {
                lambda *= 10.0;
                if lambda > LAMBDA_MAX {
                    converged = true;
                    break;
                }
            }
        }
        LmReport {
            iterations,
            rss,
            converged,
        }
    }

    /// Sample window of `g` in a segment of `n` samples: the samples `i` with
    /// `|i − μ| ≤ WINDOW_SIGMAS σ`, or `None` when there are none.
    fn window(g: &Gaussian, n: usize) -> Option<(usize, usize)> {
        let half = WINDOW_SIGMAS * g.sigma_bins;
        let lo = (g.center_bins - half).ceil().max(0.0);
        let hi = (g.center_bins + half).floor().min(n as f64 - 1.0);
        (lo <= hi).then_some((lo as usize, hi as usize))
    }

    /// Sets `self.windows` for `comps` (an empty window is `(1, 0)`), zeroes the model there and
    /// adds every component within its window, Gaussians by recurrence
    /// (`e(t + 1) = e(t) r(t)`, `r(t + 1) = r(t) q`: three `exp` per component). With `jac`,
    /// also stores the Jacobian columns `∂model/∂(A, μ, σ)` within each window.
    fn model_in_windows(&mut self, comps: &[Gaussian], n: usize, jac: bool) {
        for (w, g) in self.windows.iter_mut().zip(comps) {
            *w = Self::window(g, n).unwrap_or((1, 0));
            if w.0 <= w.1 {
                self.model[w.0..=w.1].fill(0.0);
            }
        }
        let cap = self.capacity;
        for (j, g) in comps.iter().enumerate() {
            let (lo, hi) = self.windows[j];
            if lo > hi {
                continue;
            }
            let inv_s2 = 1.0 / (g.sigma_bins * g.sigma_bins);
            let d0 = lo as f64 - g.center_bins;
            let mut e = (-0.5 * d0 * d0 * inv_s2).exp();
            let mut r = (-(d0 + 0.5) * inv_s2).exp();
            let q = (-inv_s2).exp();
            let a = g.amplitude;
            if jac {
                let (ja, rest) = self.jac[3 * j * cap..].split_at_mut(cap);
                let (jm, rest) = rest.split_at_mut(cap);
                let js = &mut rest[..cap];
                let inv_s3 = inv_s2 / g.sigma_bins;
                for i in lo..=hi {
                    let d = i as f64 - g.center_bins;
                    let ae = a * e;
                    self.model[i] += ae;
                    ja[i] = e;
                    jm[i] = ae * d * inv_s2;
                    js[i] = ae * d * d * inv_s3;
                    e *= r;
                    r *= q;
                }
            } else {
                for v in &mut self.model[lo..=hi] {
                    *v += a * e;
                    e *= r;
                    r *= q;
                }
            }
        }
    }

    /// The union of the first `k` windows as disjoint sorted intervals, and their count.
    fn union(&self, k: usize) -> ([(usize, usize); MAX_COMPONENTS], usize) {
        let mut w = [(0usize, 0usize); MAX_COMPONENTS];
        let mut c = 0;
        for &(lo, hi) in &self.windows[..k] {
            if lo > hi {
                continue;
            }
            // Insertion by start.
            let mut p = c;
            while p > 0 && w[p - 1].0 > lo {
                w[p] = w[p - 1];
                p -= 1;
            }
            w[p] = (lo, hi);
            c += 1;
        }
        let mut merged = [(0usize, 0usize); MAX_COMPONENTS];
        let mut count = 0;
        for &(lo, hi) in &w[..c] {
            if count > 0 && lo <= merged[count - 1].1 + 1 {
                merged[count - 1].1 = merged[count - 1].1.max(hi);
            } else {
                merged[count] = (lo, hi);
                count += 1;
            }
        }
        (merged, count)
    }

    /// Residual sum of squares of `comps` against `y`: `Σ (y − model)²` over the union of the
    /// windows plus `Σ y²` (from the prefix sums) outside, where the model is 0. Leaves the
    /// residual in `self.model` over the union when `keep_residual`. Needs `self.y2` for `y`.
    fn windowed_rss(&mut self, y: &[f32], comps: &[Gaussian], keep_residual: bool) -> f64 {
        let n = y.len();
        self.model_in_windows(comps, n, keep_residual);
        let (merged, count) = self.union(comps.len());
        let mut rss = 0.0;
        let mut next = 0;
        for &(lo, hi) in &merged[..count] {
            rss += self.y2[lo] - self.y2[next];
            let (m, yy) = (&mut self.model[lo..=hi], &y[lo..=hi]);
            if keep_residual {
                for (mv, &v) in m.iter_mut().zip(yy) {
                    let r = v as f64 - *mv;
                    *mv = r;
                    rss += r * r;
                }
            } else {
                for (mv, &v) in m.iter().zip(yy) {
                    let r = v as f64 - *mv;
                    rss += r * r;
                }
            }
            next = hi + 1;
        }
        rss + (self.y2[n] - self.y2[next])
    }

    /// Accumulates `JᵀJ` and `Jᵀr` at `comps` and returns the residual sum of squares (the
    /// fit's two steps in one, for tests).
    #[cfg(test)]
    fn normal_equations(&mut self, y: &[f32], comps: &[Gaussian]) -> f64 {
        let rss = self.windowed_rss(y, comps, true);
        self.accumulate_normal_equations(comps.len());
        rss
    }

    /// Accumulates `JᵀJ` (upper triangle) and `Jᵀr` of `k` components from the Jacobian columns,
    /// windows and residual left by `windowed_rss(…, true)`. `r = y − model`, so the
    /// Gauss-Newton step is `+ (JᵀJ)⁻¹ Jᵀr`; only samples inside a component's window enter its
    /// columns, two components couple only over the overlap of their windows, and `self.first`
    /// records that profile for the solve.
    fn accumulate_normal_equations(&mut self, k: usize) {
        let m = 3 * k;
        for row in self.jtj[..m].iter_mut() {
            row[..m].fill(0.0);
        }
        self.jtr[..m].fill(0.0);
        let cap = self.capacity;
        let col = |j: usize, lo: usize, hi: usize| j * cap + lo..j * cap + hi + 1;
        for a in 0..k {
            let (lo, hi) = self.windows[a];
            let mut first = a;
            if lo > hi {
                for p in 0..3 {
                    self.first[3 * a + p] = 3 * a;
                }
                continue;
            }
            let res = &self.model[lo..=hi];
            for p in 0..3 {
                self.jtr[3 * a + p] = dot(&self.jac[col(3 * a + p, lo, hi)], res);
                for q in p..3 {
                    self.jtj[3 * a + p][3 * a + q] = dot(
                        &self.jac[col(3 * a + p, lo, hi)],
                        &self.jac[col(3 * a + q, lo, hi)],
                    );
                }
            }
            for b in 0..k {
                if b == a {
                    continue;
                }
                let (blo, bhi) = self.windows[b];
                let (olo, ohi) = (lo.max(blo), hi.min(bhi));
                if olo > ohi {
                    continue;
                }
                if b < a {
                    first = first.min(b);
                    continue;
                }
                for p in 0..3 {
                    for q in 0..3 {
                        self.jtj[3 * a + p][3 * b + q] = dot(
                            &self.jac[col(3 * a + p, olo, ohi)],
                            &self.jac[col(3 * b + q, olo, ohi)],
                        );
                    }
                }
            }
            for p in 0..3 {
                self.first[3 * a + p] = 3 * first;
            }
        }
    }

    /// Solves `(JᵀJ + λ·D) δ = Jᵀr` for the first `m` parameters into `self.step`, with
    /// `D = diag(JᵀJ)` floored at a small fraction of its largest entry (a component whose
    /// amplitude hit 0 has zero centre and width columns). Returns false when the damped matrix
    /// is not positive definite (numerically). Only the profile of the lower triangle
    /// (`self.first`) is copied and factorised: entries left of it are 0 and stay 0 in the
    /// Cholesky factor.
    fn solve_damped(&mut self, m: usize, lambda: f64, frozen: &[bool; MAX_PARAMS]) -> bool {
        let max_diag = (0..m).map(|j| self.jtj[j][j]).fold(0.0f64, f64::max);
        let floor = 1e-12 * max_diag + f64::MIN_POSITIVE;
        for i in 0..m {
            for j in self.first[i]..i {
                self.factor[i][j] = if frozen[i] || frozen[j] {
                    0.0
                } else {
                    self.jtj[j][i]
                };
            }
            let d = self.jtj[i][i].max(floor);
            self.factor[i][i] = if frozen[i] {
                1.0
            } else {
                self.jtj[i][i] + lambda * d + floor
            };
        }
        let mut rhs = self.jtr;
        for j in 0..m {
            if frozen[j] {
                rhs[j] = 0.0;
            }
        }
        cholesky_solve_profile(&mut self.factor, m, &self.first, &rhs, &mut self.step)
    }

    /// `2δ·Jᵀr − δᵀ(JᵀJ)δ` for the current step δ (first `m` parameters; `jtj` upper triangle).
    fn predicted_reduction(&self, m: usize) -> f64 {
        let d = &self.step;
        let mut quad = 0.0;
        let mut lin = 0.0;
        for i in 0..m {
            lin += d[i] * self.jtr[i];
            quad += self.jtj[i][i] * d[i] * d[i];
            for j in i + 1..m {
                quad += 2.0 * self.jtj[i][j] * d[i] * d[j];
            }
        }
        2.0 * lin - quad
    }

    /// The active set of the box constraints: parameters sitting on a bound whose descent
    /// direction (`Jᵀr`, the negative half-gradient of the RSS) points out of the box. They are
    /// held fixed for the step; otherwise the projection of the unconstrained step (e.g. a dead
    /// component's amplitude pushed below 0) would spoil the step of every coupled parameter.
    fn active_bounds(&self, comps: &[Gaussian], bounds: &Bounds) -> [bool; MAX_PARAMS] {
        let mut frozen = [false; MAX_PARAMS];
        for (k, g) in comps.iter().enumerate() {
            let at = |v: f64, lo: f64, hi: f64, grad: f64| {
                (v <= lo && grad < 0.0) || (v >= hi && grad > 0.0)
            };
            frozen[3 * k] = at(g.amplitude, 0.0, f64::INFINITY, self.jtr[3 * k]);
            frozen[3 * k + 1] = at(
                g.center_bins,
                bounds.center_min_bins,
                bounds.center_max_bins,
                self.jtr[3 * k + 1],
            );
            frozen[3 * k + 2] = at(
                g.sigma_bins,
                bounds.sigma_min_bins,
                bounds.sigma_max_bins,
                self.jtr[3 * k + 2],
            );
        }
        frozen
    }
}

/// Value of the sum of `comps` at `t` bins (each within its evaluation window).
pub fn model_at(comps: &[Gaussian], t: f64) -> f64 {
    let mut s = 0.0;
    for g in comps {
        let d = t - g.center_bins;
        if d.abs() <= WINDOW_SIGMAS * g.sigma_bins {
            s += g.at(t);
        }
    }
    s
}

/// Solves `a x = b` for the leading `m × m` block of the symmetric positive definite `a`
/// (lower triangle read; overwritten by its Cholesky factor `L`). Returns false if a pivot is
/// not positive and finite.
pub fn cholesky_solve(
    a: &mut [[f64; MAX_PARAMS]; MAX_PARAMS],
    m: usize,
    b: &[f64; MAX_PARAMS],
    x: &mut [f64; MAX_PARAMS],
) -> bool {
    cholesky_solve_profile(a, m, &[0; MAX_PARAMS], b, x)
}

/// [`cholesky_solve`] for a matrix whose row `i` (lower triangle) is 0 left of column
/// `first[i]` (`first[i] ≤ i`): a profile (envelope) factorisation, which touches only the
/// entries inside the profile (the factor has the same profile). Returns false if a pivot is
/// not positive and finite.
// Textbook index notation reads closest to the algorithm for a factorisation.
#[allow(clippy::needless_range_loop)]
pub fn cholesky_solve_profile(
    a: &mut [[f64; MAX_PARAMS]; MAX_PARAMS],
    m: usize,
    first: &[usize; MAX_PARAMS],
    b: &[f64; MAX_PARAMS],
    x: &mut [f64; MAX_PARAMS],
) -> bool {
    // Row by row: L[i][j] = (a[i][j] − Σ_k L[i][k] L[j][k]) / L[j][j] for first[i] ≤ j < i.
    for i in 0..m {
        let fi = first[i].min(i);
        for j in fi..i {
            let mut s = a[i][j];
            for k in fi.max(first[j])..j {
                s -= a[i][k] * a[j][k];
            }
            a[i][j] = s / a[j][j];
        }
        let mut d = a[i][i];
        for k in fi..i {
            d -= a[i][k] * a[i][k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        a[i][i] = d.sqrt();
    }
    // Forward: L z = b.
    for i in 0..m {
        let mut s = b[i];
        for k in first[i].min(i)..i {
            s -= a[i][k] * x[k];
        }
        x[i] = s / a[i][i];
    }
    // Backward: Lᵀ x = z.
    for i in (0..m).rev() {
        let mut s = x[i];
        for k in i + 1..m {
            if first[k] <= i {
                s -= a[k][i] * x[k];
            }
        }
        x[i] = s / a[i][i];
    }
    x[..m].iter().all(|v| v.is_finite())
}

/// `Σ a_i b_i` with four partial sums (lets the compiler vectorise).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut s = [0.0f64; 4];
    let mut ca = a.chunks_exact(4);
    let mut cb = b.chunks_exact(4);
    for (x, y) in (&mut ca).zip(&mut cb) {
        for l in 0..4 {
            s[l] += x[l] * y[l];
        }
    }
    let mut t = (s[0] + s[1]) + (s[2] + s[3]);
    for (x, y) in ca.remainder().iter().zip(cb.remainder()) {
        t += x * y;
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds(n: usize) -> Bounds {
        Bounds {
            center_min_bins: 0.0,
            center_max_bins: (n - 1) as f64,
            sigma_min_bins: 0.5,
            sigma_max_bins: 30.0,
        }
    }

    #[test]
    fn cholesky_solves_a_small_system() {
        let mut a = [[0.0; MAX_PARAMS]; MAX_PARAMS];
        a[0][0] = 4.0;
        a[0][1] = 2.0;
        a[1][0] = 2.0;
        a[1][1] = 3.0;
        let mut b = [0.0; MAX_PARAMS];
        b[0] = 2.0;
        b[1] = 5.0;
        let mut x = [0.0; MAX_PARAMS];
        assert!(cholesky_solve(&mut a, 2, &b, &mut x));
        // 4x + 2y = 2, 2x + 3y = 5 -> x = -0.5, y = 2.
        assert!((x[0] + 0.5).abs() < 1e-12 && (x[1] - 2.0).abs() < 1e-12);
        let mut singular = [[0.0; MAX_PARAMS]; MAX_PARAMS];
        singular[0][0] = 1.0;
        assert!(!cholesky_solve(&mut singular, 2, &b, &mut x));
    }

    #[test]
    fn exact_gaussian_is_recovered_from_a_poor_guess() {
        let truth = Gaussian {
            amplitude: 50.0,
            center_bins: 100.3,
            sigma_bins: 4.0,
        };
        let y: Vec<f32> = (0..256).map(|i| truth.at(i as f64) as f32).collect();
        let mut comps = [Gaussian {
            amplitude: 45.0,
            center_bins: 101.0,
            sigma_bins: 6.0,
        }];
        let mut f = GaussFitter::new();
        let rep = f.fit(&y, &mut comps, &bounds(256), 30);
        let g = comps[0];
        assert!((g.center_bins - 100.3).abs() < 1e-3, "{g:?} {rep:?}");
        assert!((g.amplitude - 50.0).abs() < 0.05, "{g:?}");
        assert!((g.sigma_bins - 4.0).abs() < 0.01, "{g:?}");
        assert!(rep.iterations <= 30);
    }

    #[test]
    fn the_stopping_test_leaves_only_a_negligible_decrease() {
        // Two overlapping echoes in noise, a start far enough off for a long fit. The fit must
        // converge within the budget, and continuing it (a fresh fit from its result with a
        // large budget) may lower the RSS by only a negligible amount: less than 0.1 of the
        // noise variance (χ² by 0.1; the stopping test is at 0.01 per step).
        let truth = [
            Gaussian {
                amplitude: 40.0,
                center_bins: 100.0,
                sigma_bins: 4.0,
            },
            Gaussian {
                amplitude: 25.0,
                center_bins: 109.0,
                sigma_bins: 5.0,
            },
        ];
        let n = 256;
        let mut state = 12345u64;
        let y: Vec<f32> = (0..n)
            .map(|i| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let u = (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
                (model_at(&truth, i as f64) + 2.0 * u) as f32
            })
            .collect();
        let noise_var = 4.0 / 12.0;
        let mut comps = [
            Gaussian {
                amplitude: 30.0,
                center_bins: 98.0,
                sigma_bins: 6.0,
            },
            Gaussian {
                amplitude: 30.0,
                center_bins: 112.0,
                sigma_bins: 3.0,
            },
        ];
        let mut f = GaussFitter::new();
        let rep = f.fit(&y, &mut comps, &bounds(n), 60);
        assert!(rep.converged, "{rep:?}");
        let mut more = comps;
        let rep2 = f.fit(&y, &mut more, &bounds(n), 500);
        assert!(rep2.rss <= rep.rss);
        assert!(
            rep.rss - rep2.rss < 0.1 * noise_var,
            "{rep:?} then {rep2:?}"
        );
        for (a, b) in comps.iter().zip(&more) {
            assert!((a.center_bins - b.center_bins).abs() < 0.05, "{a:?} {b:?}");
            assert!(
                (a.amplitude / b.amplitude - 1.0).abs() < 0.01,
                "{a:?} {b:?}"
            );
        }
    }

    #[test]
    fn bounds_hold_even_when_the_data_want_otherwise() {
        // A very narrow spike: the unbounded optimum has σ well below 0.5.
        let mut y = vec![0.0f32; 64];
        y[20] = 100.0;
        let mut comps = [Gaussian {
            amplitude: 80.0,
            center_bins: 22.0,
            sigma_bins: 2.0,
        }];
        let b = Bounds {
            center_min_bins: 21.0,
            center_max_bins: 40.0,
            sigma_min_bins: 1.0,
            sigma_max_bins: 3.0,
        };
        let rep = GaussFitter::new().fit(&y, &mut comps, &b, 50);
        let g = comps[0];
        assert!(g.center_bins >= 21.0 && g.center_bins <= 40.0, "{g:?}");
        assert!(g.sigma_bins >= 1.0 && g.sigma_bins <= 3.0, "{g:?}");
        assert!(g.amplitude >= 0.0);
        assert!(rep.iterations <= 50);
    }

    /// Components overlapping in pairs, one alone, one at the segment's start and one cut off
    /// by its end, σ from the lower bound to wide; `y` their sum plus a deterministic ripple.
    fn mixed_case() -> (Vec<f32>, Vec<Gaussian>) {
        let comps = vec![
            Gaussian {
                amplitude: 3.0,
                center_bins: 0.4,
                sigma_bins: 0.5,
            },
            Gaussian {
                amplitude: 40.0,
                center_bins: 30.2,
                sigma_bins: 2.5,
            },
            Gaussian {
                amplitude: 25.0,
                center_bins: 36.9,
                sigma_bins: 3.1,
            },
            Gaussian {
                amplitude: 12.0,
                center_bins: 120.0,
                sigma_bins: 11.7,
            },
            Gaussian {
                amplitude: 8.0,
                center_bins: 190.3,
                sigma_bins: 1.2,
            },
            Gaussian {
                amplitude: 30.0,
                center_bins: 254.6,
                sigma_bins: 4.0,
            },
        ];
        let y = (0..256)
            .map(|i| {
                let ripple = 0.4 * ((i * 7919 % 17) as f64 / 8.0 - 1.0);
                (model_at(&comps, i as f64) * 0.97 + ripple) as f32
            })
            .collect();
        (y, comps)
    }

    #[test]
    fn windowed_model_matches_the_per_sample_reference() {
        let (y, comps) = mixed_case();
        let mut f = GaussFitter::new();
        let mut res = vec![0.0f32; y.len()];
        let rss = f.residual(&y, &comps, &mut res);
        let reference = GaussFitter::rss(&y, &comps);
        assert!((rss / reference - 1.0).abs() < 1e-9, "{rss} vs {reference}");
        for (i, (&r, &v)) in res.iter().zip(&y).enumerate() {
            let want = v - model_at(&comps, i as f64) as f32;
            assert!((r - want).abs() < 1e-4, "sample {i}: {r} vs {want}");
        }
        // The fit's RSS (windows plus prefix sums of y² outside them) agrees too.
        let mut g = comps.clone();
        let rep = f.fit(&y, &mut g, &bounds(256), 0);
        assert!(
            (rep.rss / reference - 1.0).abs() < 1e-9,
            "{rep:?} vs {reference}"
        );
    }

    #[test]
    // Matrix index notation, as in the code under test.
    #[allow(clippy::needless_range_loop)]
    fn normal_equations_match_the_per_sample_reference() {
        let (y, comps) = mixed_case();
        let k = comps.len();
        let m = 3 * k;
        // Reference: the Jacobian sample by sample, one exp per sample and component.
        let mut jtj = [[0.0f64; MAX_PARAMS]; MAX_PARAMS];
        let mut jtr = [0.0f64; MAX_PARAMS];
        for (i, &v) in y.iter().enumerate() {
            let t = i as f64;
            let r = v as f64 - model_at(&comps, t);
            let mut grad = [0.0f64; MAX_PARAMS];
            for (j, g) in comps.iter().enumerate() {
                let d = t - g.center_bins;
                if d.abs() > WINDOW_SIGMAS * g.sigma_bins {
                    continue;
                }
                let e = (-0.5 * (d / g.sigma_bins).powi(2)).exp();
                let s2 = g.sigma_bins * g.sigma_bins;
                grad[3 * j] = e;
                grad[3 * j + 1] = g.amplitude * e * d / s2;
                grad[3 * j + 2] = g.amplitude * e * d * d / (s2 * g.sigma_bins);
            }
            for a in 0..m {
                jtr[a] += grad[a] * r;
                for b in a..m {
                    jtj[a][b] += grad[a] * grad[b];
                }
            }
        }
        let mut f = GaussFitter::new();
        f.reserve(y.len());
        let mut acc = 0.0;
        for (i, &v) in y.iter().enumerate() {
            acc += (v as f64) * (v as f64);
            f.y2[i + 1] = acc;
        }
        let rss = f.normal_equations(&y, &comps);
        assert!((rss / GaussFitter::rss(&y, &comps) - 1.0).abs() < 1e-9);
        let scale = (0..m).map(|a| jtj[a][a]).fold(0.0f64, f64::max);
        let rscale = jtr[..m].iter().fold(0.0f64, |s, v| s.max(v.abs()));
        for a in 0..m {
            assert!((f.jtr[a] - jtr[a]).abs() <= 1e-9 * rscale, "jtr {a}");
            for b in a..m {
                assert!(
                    (f.jtj[a][b] - jtj[a][b]).abs() <= 1e-9 * scale,
                    "jtj {a} {b}: {} vs {}",
                    f.jtj[a][b],
                    jtj[a][b]
                );
                // Entries left of the profile are 0.
                if a < f.first[b] {
                    assert_eq!(jtj[a][b], 0.0, "{a} {b} outside the profile");
                }
            }
        }
        // Component 1 does not meet component 0; component 2 meets component 1.
        assert_eq!(f.first[3], 3);
        assert_eq!(f.first[3 * 2 + 1], 3);
    }

    #[test]
    // Matrix index notation, as in the code under test.
    #[allow(clippy::needless_range_loop)]
    fn profile_cholesky_matches_the_dense_solve() {
        // A block-banded SPD matrix: 4 blocks of 3, each coupled to the previous one only,
        // except block 3, which stands alone.
        let m = 12;
        let mut a = [[0.0f64; MAX_PARAMS]; MAX_PARAMS];
        let mut first = [0usize; MAX_PARAMS];
        for i in 0..m {
            let blk = i / 3;
            first[i] = match blk {
                0 => 0,
                3 => 9,
                _ => 3 * (blk - 1),
            };
            for j in first[i]..=i {
                let v = if i == j {
                    10.0 + i as f64
                } else {
                    1.0 / (1.0 + (i + 2 * j) as f64)
                };
                a[i][j] = v;
                a[j][i] = v;
            }
        }
        let mut b = [0.0; MAX_PARAMS];
        for (i, v) in b[..m].iter_mut().enumerate() {
            *v = (i as f64 * 0.7).sin();
        }
        let (mut dense, mut profile) = (a, a);
        let (mut x1, mut x2) = ([0.0; MAX_PARAMS], [0.0; MAX_PARAMS]);
        assert!(cholesky_solve(&mut dense, m, &b, &mut x1));
        assert!(cholesky_solve_profile(&mut profile, m, &first, &b, &mut x2));
        for i in 0..m {
            assert!((x1[i] - x2[i]).abs() < 1e-12, "{i}: {} vs {}", x1[i], x2[i]);
            let ax: f64 = (0..m).map(|j| a[i][j] * x2[j]).sum();
            assert!((ax - b[i]).abs() < 1e-12, "row {i}");
        }
    }
}
