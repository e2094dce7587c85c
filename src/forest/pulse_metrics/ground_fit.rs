//! The ground echo's model and fit (step 5 of the metrics): an extended (skewed) Gaussian
//! fitted to the raw waveform by bounded Levenberg-Marquardt.
//!
//! The fit evaluates the model at every sample of its window for the cost of each trial
//! step, and again with its gradient at the accepted step. The terms that both share — `u`,
//! `exp(−u²/2)` and `1 + erf(γu/√2)`, the same `f64` expressions in both — are kept per sample
//! from the cost of the accepted step ([`FitScratch`]) instead of evaluated twice, and with
//! γ = 0 (the start) `1 + erf(0)` and `exp(−γ²u²/2) = 1` are taken once; every value and
//! derivative is then the same expression of the same numbers as evaluated afresh, so the fit
//! is the same bit for bit.

// The 4 × 4 normal equations and the solver index rows and columns by number, as written.
#![allow(clippy::needless_range_loop)]

use std::f64::consts::FRAC_1_SQRT_2;

/// √(2π).
pub(super) const SQRT_2PI: f64 = 2.506_628_274_631_000_7;

/// An extended (skewed) Gaussian `f(x) = area / (σ √(2π)) · exp(−u²/2) · (1 + erf(γ u / √2))`,
/// `u = (x − centre) / σ`: its integral is `area` whatever γ.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExtGauss {
    /// Integral, signal units × bins.
    pub area: f64,
    /// Location, bins.
    pub centre: f64,
    /// Width σ, bins.
    pub sigma: f64,
    /// Skewness γ (0: a Gaussian; > 0: the tail is on the later side).
    pub gamma: f64,
}

impl ExtGauss {
    /// Value at `x` bins.
    pub fn value(&self, x: f64) -> f64 {
        let u = (x - self.centre) / self.sigma;
        self.area / (self.sigma * SQRT_2PI)
            * (-0.5 * u * u).exp()
            * (1.0 + erf(self.gamma * u * FRAC_1_SQRT_2))
    }

    /// This echo convolved with a unit-area Gaussian of σ `sigma_bins` (exact for the
    /// skew-normal shape).
    pub fn smoothed(&self, sigma_bins: f64) -> ExtGauss {
        if sigma_bins.is_nan() || sigma_bins <= 0.0 {
            return *self;
        }
        let s2 = (self.sigma * self.sigma + sigma_bins * sigma_bins).sqrt();
        let delta = self.gamma / (1.0 + self.gamma * self.gamma).sqrt() * self.sigma / s2;
        ExtGauss {
            area: self.area,
            centre: self.centre,
            sigma: s2,
            gamma: delta / (1.0 - delta * delta).max(1e-12).sqrt(),
        }
    }

    /// The terms of the value at `x` bins ([`ExtGauss::value`]'s); `skew_at_zero` is
    /// `1 + erf(0)`, used when γ is zero.
    fn terms(&self, x: f64, skew_at_zero: f64) -> Terms {
        let u = (x - self.centre) / self.sigma;
        let phi = (-0.5 * u * u).exp();
        // γ = ±0 and a finite u: the argument of erf is ±0, whose erf is erf(0).
        let skew = if self.gamma == 0.0 && u.is_finite() {
            skew_at_zero
        } else {
            1.0 + erf(self.gamma * u * FRAC_1_SQRT_2)
        };
        Terms { u, phi, skew }
    }

    /// Value and partial derivatives by (area, centre, sigma, gamma) from the terms `t` of
    /// the value at the same `x`.
    fn value_and_gradient(&self, t: Terms) -> (f64, [f64; 4]) {
        let s = self.sigma;
        let (u, phi, e) = (t.u, t.phi, t.skew);
        let k = 1.0 / (s * SQRT_2PI);
        // exp(−γ²u²/2): exp(±0) = 1 for γ = ±0 and a finite u.
        let gauss_skew = if self.gamma == 0.0 && u.is_finite() {
            1.0
        } else {
            (-0.5 * self.gamma * self.gamma * u * u).exp()
        };
        let g = gauss_skew * (2.0 / std::f64::consts::PI).sqrt();
        let f = self.area * k * phi * e;
        let df_du = self.area * k * (-u * phi * e + phi * self.gamma * g);
        (
            f,
            [
                k * phi * e,
                -df_du / s,
                -f / s - df_du * u / s,
                self.area * k * phi * u * g,
            ],
        )
    }
}

/// The terms of the model's value at one sample that its gradient shares.
#[derive(Clone, Copy, Debug, Default)]
struct Terms {
    /// `(x − centre) / σ`.
    u: f64,
    /// `exp(−u²/2)`.
    phi: f64,
    /// `1 + erf(γ u / √2)`.
    skew: f64,
}

/// Work buffers of [`fit_ext_gauss`]: the terms of the accepted step's and of the trial
/// step's model at every sample of the window (no allocation once they have held the
/// longest window).
#[derive(Debug, Default)]
pub(super) struct FitScratch {
    accepted: Vec<Terms>,
    trial: Vec<Terms>,
}

/// Bounds of the fitted centre and σ, bins.
#[derive(Clone, Copy, Debug)]
pub(super) struct FitBounds {
    /// Lowest and highest centre, bins.
    pub centre: (f64, f64),
    /// Smallest and largest σ, bins.
    pub sigma: (f64, f64),
}

/// Error function, Abramowitz & Stegun 7.1.26 (absolute error below 1.5 × 10⁻⁷).
pub(super) fn erf(x: f64) -> f64 {
    let sign = if x < 0.0 { -1.0 } else { 1.0 };
    let x = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    sign * (1.0 - poly * (-x * x).exp())
}

/// Sum of squared residuals of `p` against `y − mean` over samples `from..=to`, the terms of
/// its value at each sample into `terms`.
fn cost_into(
    p: &ExtGauss,
    y: &[f32],
    mean: f64,
    (from, to): (usize, usize),
    terms: &mut Vec<Terms>,
) -> f64 {
    terms.clear();
    let skew_at_zero = if p.gamma == 0.0 {
        1.0 + erf(0.0)
    } else {
        f64::NAN
    };
    let scale = p.area / (p.sigma * SQRT_2PI);
    let mut sum = 0.0;
    for i in from..=to {
        let t = p.terms(i as f64, skew_at_zero);
        let r = f64::from(y[i]) - mean - scale * t.phi * t.skew;
        sum += r * r;
        terms.push(t);
    }
    sum
}

/// Fits an [`ExtGauss`] to `y − mean` over samples `from..=to` by bounded Levenberg-Marquardt
/// (at most 15 steps; area ≥ 0, centre and σ within `bounds`, |γ| ≤ 5). Returns the start
/// when the window is empty.
pub(super) fn fit_ext_gauss(
    scratch: &mut FitScratch,
    y: &[f32],
    mean: f64,
    from: usize,
    to: usize,
    start: ExtGauss,
    bounds: FitBounds,
) -> ExtGauss {
    if to <= from + 3 || to >= y.len() {
        return start;
    }
    let clamp = |p: ExtGauss| ExtGauss {
        area: p.area.max(0.0),
        centre: p.centre.clamp(bounds.centre.0, bounds.centre.1),
        sigma: p.sigma.clamp(bounds.sigma.0, bounds.sigma.1),
        gamma: p.gamma.clamp(-5.0, 5.0),
    };
    let FitScratch { accepted, trial } = scratch;
    let mut p = clamp(start);
    let mut c = cost_into(&p, y, mean, (from, to), accepted);
    let mut lambda = 1e-3;
    for _ in 0..15 {
        let mut jtj = [[0.0f64; 4]; 4];
        let mut jtr = [0.0f64; 4];
        for (i, &t) in (from..=to).zip(accepted.iter()) {
            let (f, g) = p.value_and_gradient(t);
            let r = f64::from(y[i]) - mean - f;
            for a in 0..4 {
                jtr[a] += g[a] * r;
                for b in a..4 {
                    jtj[a][b] += g[a] * g[b];
                }
            }
        }
        for a in 0..4 {
            for b in 0..a {
                jtj[a][b] = jtj[b][a];
            }
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut m = jtj;
            for (a, row) in m.iter_mut().enumerate() {
                row[a] += lambda * (jtj[a][a] + 1e-12);
            }
            let Some(d) = solve4(m, jtr) else {
                lambda *= 10.0;
                continue;
            };
            let q = clamp(ExtGauss {
                area: p.area + d[0],
                centre: p.centre + d[1],
                sigma: p.sigma + d[2],
                gamma: p.gamma + d[3],
            });
            let cq = cost_into(&q, y, mean, (from, to), trial);
            if cq < c {
                let rel = (c - cq) / c.max(1e-300);
                p = q;
                c = cq;
                std::mem::swap(accepted, trial);
                lambda = (lambda * 0.3).max(1e-9);
                improved = rel > 1e-5;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    p
}

/// Solves a 4 × 4 system by Gaussian elimination with partial pivoting; `None` if singular.
fn solve4(mut a: [[f64; 4]; 4], mut b: [f64; 4]) -> Option<[f64; 4]> {
    for col in 0..4 {
        let mut piv = col;
        for r in col + 1..4 {
            if a[r][col].abs() > a[piv][col].abs() {
                piv = r;
            }
        }
        if a[piv][col].is_nan() || a[piv][col].abs() <= 1e-300 {
            return None;
        }
        a.swap(col, piv);
        b.swap(col, piv);
        for r in col + 1..4 {
            let f = a[r][col] / a[col][col];
            for c in col..4 {
                a[r][c] -= f * a[col][c];
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0.0; 4];
    for r in (0..4).rev() {
        let mut s = b[r];
        for c in r + 1..4 {
            s -= a[r][c] * x[c];
        }
        x[r] = s / a[r][r];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}
