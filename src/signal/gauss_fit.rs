//! Bounded Levenberg-Marquardt fit of a sum of Gaussians
//! `Σ_k A_k exp(−(t − μ_k)² / 2σ_k²)` to one segment (t in bins from the segment's first sample).
//!
//! Parameters per component: amplitude `A` (signal units, ≥ 0), centre `μ` (bins, inside
//! [`Bounds::center_min_bins`, `Bounds::center_max_bins`]) and width `σ` (bins, inside
//! [`Bounds::sigma_min_bins`, `Bounds::sigma_max_bins`]). Bounds are enforced by projection: every
//! trial point is clamped into the box before its cost is evaluated (a projected LM step).
//!
//! Algorithm (Marquardt 1963, with Nielsen-style simple damping schedule):
//! 1. at the current parameters accumulate the normal equations `JᵀJ` and `Jᵀr` in one pass
//!    over the samples (the Jacobian itself is never stored; a component contributes only within
//!    ±[`WINDOW_SIGMAS`] σ of its centre, where `exp` is above ~1.5e-8);
//! 2. solve `(JᵀJ + λ·diag(JᵀJ)) δ = Jᵀr` by Cholesky;
//! 3. clamp `p + δ` into the bounds and evaluate its residual sum of squares; accept and divide
//!    λ by 10 when it decreased, otherwise multiply λ by 10 and retry from the same normal
//!    equations (no new Jacobian pass).
//!
//! Each trial step counts as one iteration; the caller's iteration cap bounds the work (one
//! cost pass and at most one normal-equation pass per iteration).
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
/// model for the next step) below which the fit has converged.
const RELATIVE_TOLERANCE: f64 = 1e-6;

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

/// A reusable fitter: the normal equations and their factor live in fixed-size arrays, so a fit
/// allocates nothing.
pub struct GaussFitter {
    jtj: [[f64; MAX_PARAMS]; MAX_PARAMS],
    jtr: [f64; MAX_PARAMS],
    factor: [[f64; MAX_PARAMS]; MAX_PARAMS],
    step: [f64; MAX_PARAMS],
}

impl Default for GaussFitter {
    fn default() -> Self {
        Self::new()
    }
}

impl GaussFitter {
    /// A fitter (about 9 KiB of fixed-size work arrays).
    pub fn new() -> Self {
        GaussFitter {
            jtj: [[0.0; MAX_PARAMS]; MAX_PARAMS],
            jtr: [0.0; MAX_PARAMS],
            factor: [[0.0; MAX_PARAMS]; MAX_PARAMS],
            step: [0.0; MAX_PARAMS],
        }
    }

    /// Residual sum of squares of `comps` against `y`, signal units².
    pub fn rss(y: &[f32], comps: &[Gaussian]) -> f64 {
        let mut rss = 0.0;
        for (i, &v) in y.iter().enumerate() {
            let r = v as f64 - model_at(comps, i as f64);
            rss += r * r;
        }
        rss
    }

    /// Fits `comps` (initial guesses in, fitted parameters out; at most [`MAX_COMPONENTS`],
    /// extra ones are left untouched) to `y` with at most `max_iterations` trial steps, keeping
    /// every parameter inside `bounds`. The guesses are clamped into the bounds first.
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
        let mut rss = self.normal_equations(y, comps);
        let mut lambda = LAMBDA_START;
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
            if predicted <= RELATIVE_TOLERANCE * rss {
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
            let new_rss = Self::rss(y, &trial[..k]);
            if new_rss.is_finite() && new_rss < rss {
                let relative = (rss - new_rss) / rss;
                comps.copy_from_slice(&trial[..k]);
                lambda = (lambda * 0.1).max(LAMBDA_MIN);
                if relative < RELATIVE_TOLERANCE {
                    rss = new_rss;
                    converged = true;
                    break;
                }
                rss = self.normal_equations(y, comps);
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

    /// Accumulates `JᵀJ` (upper triangle) and `Jᵀr` at `comps` and returns the residual sum of
    /// squares. `r = y − model`, so the Gauss-Newton step is `+ (JᵀJ)⁻¹ Jᵀr`.
    fn normal_equations(&mut self, y: &[f32], comps: &[Gaussian]) -> f64 {
        let m = 3 * comps.len();
        for row in self.jtj[..m].iter_mut() {
            row[..m].fill(0.0);
        }
        self.jtr[..m].fill(0.0);
        let mut grad = [0.0f64; MAX_PARAMS];
        let mut active = [0usize; MAX_PARAMS];
        let mut rss = 0.0;
        for (i, &v) in y.iter().enumerate() {
            let t = i as f64;
            let mut model = 0.0;
            let mut n = 0;
            for (k, g) in comps.iter().enumerate() {
                let d = t - g.center_bins;
                if d.abs() > WINDOW_SIGMAS * g.sigma_bins {
                    continue;
                }
                let inv_s2 = 1.0 / (g.sigma_bins * g.sigma_bins);
                let e = (-0.5 * d * d * inv_s2).exp();
                let ae = g.amplitude * e;
                model += ae;
                grad[n] = e;
                grad[n + 1] = ae * d * inv_s2;
                grad[n + 2] = ae * d * d * inv_s2 / g.sigma_bins;
                active[n] = 3 * k;
                active[n + 1] = 3 * k + 1;
                active[n + 2] = 3 * k + 2;
                n += 3;
            }
            let r = v as f64 - model;
            rss += r * r;
            for a in 0..n {
                let (ia, ga) = (active[a], grad[a]);
                self.jtr[ia] += ga * r;
                let row = &mut self.jtj[ia];
                for b in a..n {
                    row[active[b]] += ga * grad[b];
                }
            }
        }
        rss
    }

    /// Solves `(JᵀJ + λ·D) δ = Jᵀr` for the first `m` parameters into `self.step`, with
    /// `D = diag(JᵀJ)` floored at a small fraction of its largest entry (a component whose
    /// amplitude hit 0 has zero centre and width columns). Returns false when the damped matrix
    /// is not positive definite (numerically).
    fn solve_damped(&mut self, m: usize, lambda: f64, frozen: &[bool; MAX_PARAMS]) -> bool {
        let max_diag = (0..m).map(|j| self.jtj[j][j]).fold(0.0f64, f64::max);
        let floor = 1e-12 * max_diag + f64::MIN_POSITIVE;
        for i in 0..m {
            for j in i..m {
                let v = self.jtj[i][j];
                self.factor[i][j] = v;
                self.factor[j][i] = v;
            }
            let d = self.jtj[i][i].max(floor);
            self.factor[i][i] = self.jtj[i][i] + lambda * d + floor;
        }
        let mut rhs = self.jtr;
        for j in 0..m {
            if frozen[j] {
                for i in 0..m {
                    self.factor[i][j] = 0.0;
                    self.factor[j][i] = 0.0;
                }
                self.factor[j][j] = 1.0;
                rhs[j] = 0.0;
            }
        }
        cholesky_solve(&mut self.factor, m, &rhs, &mut self.step)
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
/// (overwritten by its Cholesky factor `L`, lower triangle). Returns false if a pivot is not
/// positive and finite.
// Textbook index notation reads closest to the algorithm for a factorisation.
#[allow(clippy::needless_range_loop)]
pub fn cholesky_solve(
    a: &mut [[f64; MAX_PARAMS]; MAX_PARAMS],
    m: usize,
    b: &[f64; MAX_PARAMS],
    x: &mut [f64; MAX_PARAMS],
) -> bool {
    for j in 0..m {
        let mut d = a[j][j];
        for k in 0..j {
            d -= a[j][k] * a[j][k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let l = d.sqrt();
        a[j][j] = l;
        for i in j + 1..m {
            let mut s = a[i][j];
            for k in 0..j {
                s -= a[i][k] * a[j][k];
            }
            a[i][j] = s / l;
        }
    }
    // Forward: L z = b.
    for i in 0..m {
        let mut s = b[i];
        for k in 0..i {
            s -= a[i][k] * x[k];
        }
        x[i] = s / a[i][i];
    }
    // Backward: Lᵀ x = z.
    for i in (0..m).rev() {
        let mut s = x[i];
        for k in i + 1..m {
            s -= a[k][i] * x[k];
        }
        x[i] = s / a[i][i];
    }
    x[..m].iter().all(|v| v.is_finite())
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
}
