//! Waveform synthesis: Gaussian echoes and receiver ringing added into a sampled window.

use super::scene::Ringing;

/// Adds `amp · exp(−(t − t_e)² / 2σ²)` to the samples `out[i]` at `t = start + i·dt` (ns),
/// over ±7σ around `t_e`. The exponential is evaluated once and then advanced by the
/// recurrence `g(t + dt) = g(t) · r(t)`, `r(t + dt) = r(t) · exp(−dt²/σ²)` (two multiplies a
/// sample, relative error below 1e-12 over the span).
pub fn add_gaussian(out: &mut [f64], start: f64, dt: f64, t_e: f64, amp: f64, sigma: f64) {
    if amp == 0.0 || out.is_empty() {
        return;
    }
    let half = 7.0 * sigma;
    let i0 = (((t_e - half - start) / dt).ceil()).max(0.0);
    let i1 = (((t_e + half - start) / dt).floor()).min(out.len() as f64 - 1.0);
    if i0.is_nan() || i1.is_nan() || i0 > i1 {
        return;
    }
    let (i0, i1) = (i0 as usize, i1 as usize);
    let inv2s2 = 0.5 / (sigma * sigma);
    let x0 = start + i0 as f64 * dt - t_e;
    let mut g = amp * (-x0 * x0 * inv2s2).exp();
    // g(x + dt) / g(x) = exp(−(2 x dt + dt²) / 2σ²).
    let mut r = (-(2.0 * x0 * dt + dt * dt) * inv2s2).exp();
    let c = (-2.0 * dt * dt * inv2s2).exp();
    for v in &mut out[i0..=i1] {
        *v += g;
        g *= r;
        r *= c;
    }
}

/// Adds receiver ringing after an echo of amplitude `amp` at `t_e`:
/// `amp · A · exp(−τ/decay) · sin(2π τ / period)` for `τ = t − t_e > 0`, over 8 decay times.
pub fn add_ringing(out: &mut [f64], start: f64, dt: f64, t_e: f64, amp: f64, r: &Ringing) {
    if amp == 0.0 || r.amplitude == 0.0 {
        return;
    }
    let i0 = ((t_e - start) / dt).floor().max(-1.0) + 1.0;
    let i1 = (((t_e + 8.0 * r.decay_ns - start) / dt).floor()).min(out.len() as f64 - 1.0);
    if i0.is_nan() || i1.is_nan() || i0 > i1 {
        return;
    }
    let w = std::f64::consts::TAU / r.period_ns;
    for (i, v) in out
        .iter_mut()
        .enumerate()
        .take(i1 as usize + 1)
        .skip(i0 as usize)
    {
        let tau = start + i as f64 * dt - t_e;
        if tau > 0.0 {
            *v += amp * r.amplitude * (-tau / r.decay_ns).exp() * (w * tau).sin();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_recurrence_matches_the_formula() {
        let mut out = vec![0.0; 300];
        add_gaussian(&mut out, 1000.0, 1.0, 1123.37, 42.0, 6.79);
        for (i, v) in out.iter().enumerate() {
            let x = 1000.0 + i as f64 - 1123.37;
            let want = if x.abs() <= 7.0 * 6.79 {
                42.0 * (-0.5 * (x / 6.79) * (x / 6.79)).exp()
            } else {
                0.0
            };
            assert!((v - want).abs() < 1e-10, "{i}: {v} vs {want}");
        }
        // Echoes at the window's edges stay inside it.
        let mut out = vec![0.0; 10];
        add_gaussian(&mut out, 0.0, 1.0, -3.0, 1.0, 1.0);
        add_gaussian(&mut out, 0.0, 1.0, 12.0, 1.0, 1.0);
        assert!(out[0] > 0.0 && out[9] > 0.0);
        add_gaussian(&mut out, 0.0, 1.0, 1e9, 1.0, 1.0);
    }

    #[test]
    fn ringing_follows_the_echo_and_decays() {
        let r = Ringing {
            amplitude: 0.2,
            period_ns: 10.0,
            decay_ns: 15.0,
        };
        let mut out = vec![0.0; 200];
        add_ringing(&mut out, 0.0, 1.0, 50.0, 100.0, &r);
        assert!(out[..=50].iter().all(|&v| v == 0.0));
        assert!(
            (out[52] - 100.0 * 0.2 * (-2.0f64 / 15.0).exp() * (0.4 * std::f64::consts::PI).sin())
                .abs()
                < 1e-9
        );
        assert!(out[180..].iter().all(|v| v.abs() < 0.01));
    }
}

/// The received echo of a point target of unit amplitude: the outgoing pulse (peak 1) seen
/// through the receiver's impulse response (a Gaussian of unit area).
#[derive(Clone, Debug)]
pub enum EchoShape {
    /// Both Gaussians: a Gaussian of `sigma` and peak `gain` (`σ_out / σ`, area preserved).
    Gaussian {
        /// Standard deviation, ns.
        sigma: f64,
        /// Peak of the unit echo.
        gain: f64,
    },
    /// Any other outgoing pulse: the convolution tabulated every `step` ns from `first` ns
    /// (linear interpolation between entries).
    Table {
        /// Values.
        table: Vec<f64>,
        /// Time of `table[0]` relative to the echo's reference, ns.
        first: f64,
        /// Spacing, ns.
        step: f64,
    },
}

impl EchoShape {
    /// The shape for an outgoing pulse `outgoing(t)` (peak 1 at t = 0) over `support` ns and a
    /// receiver Gaussian of `sigma_rx` ns (0: ideal), tabulated every `step` ns.
    pub fn tabulate(
        outgoing: impl Fn(f64) -> f64,
        support: (f64, f64),
        sigma_rx: f64,
        step: f64,
    ) -> EchoShape {
        let pad = 7.0 * sigma_rx;
        let first = support.0 - pad;
        let n = ((support.1 + pad - first) / step).ceil() as usize + 1;
        let o: Vec<f64> = (0..n).map(|i| outgoing(first + i as f64 * step)).collect();
        let table = if sigma_rx <= 0.0 {
            o
        } else {
            // Unit-area Gaussian taps at the table's step.
            let m = (pad / step).ceil() as isize;
            let taps: Vec<f64> = (-m..=m)
                .map(|k| {
                    let z = k as f64 * step / sigma_rx;
                    (-0.5 * z * z).exp()
                })
                .collect();
            let sum: f64 = taps.iter().sum();
            (0..n as isize)
                .map(|i| {
                    taps.iter()
                        .enumerate()
                        .map(|(j, w)| {
                            let src = i - (j as isize - m);
                            if src >= 0 && (src as usize) < n {
                                o[src as usize] * w
                            } else {
                                0.0
                            }
                        })
                        .sum::<f64>()
                        / sum
                })
                .collect()
        };
        EchoShape::Table { table, first, step }
    }

    /// The unit echo `x` ns after its reference time.
    #[inline]
    pub fn value(&self, x: f64) -> f64 {
        match self {
            EchoShape::Gaussian { sigma, gain } => {
                let z = x / sigma;
                if z.abs() <= 7.0 {
                    gain * (-0.5 * z * z).exp()
                } else {
                    0.0
                }
            }
            EchoShape::Table { table, first, step } => {
                let f = (x - first) / step;
                if !(f >= 0.0 && f < (table.len() - 1) as f64) {
                    return 0.0;
                }
                let i = f as usize;
                let w = f - i as f64;
                table[i] * (1.0 - w) + table[i + 1] * w
            }
        }
    }

    /// How far the echo reaches on either side of its reference, ns.
    pub fn reach(&self) -> f64 {
        match self {
            EchoShape::Gaussian { sigma, .. } => 7.0 * sigma,
            EchoShape::Table { table, first, step } => {
                first.abs().max(first + step * table.len() as f64)
            }
        }
    }

    /// Adds `amp ×` the unit echo at `t_e` to the samples `out[i]` at `start + i·dt`.
    pub fn add(&self, out: &mut [f64], start: f64, dt: f64, t_e: f64, amp: f64) {
        match self {
            EchoShape::Gaussian { sigma, gain } => {
                add_gaussian(out, start, dt, t_e, amp * gain, *sigma)
            }
            EchoShape::Table { .. } => {
                if amp == 0.0 || out.is_empty() {
                    return;
                }
                let r = self.reach();
                let i0 = ((t_e - r - start) / dt).ceil().max(0.0);
                let i1 = ((t_e + r - start) / dt).floor().min(out.len() as f64 - 1.0);
                if i0.is_nan() || i1.is_nan() || i0 > i1 {
                    return;
                }
                for (i, v) in out
                    .iter_mut()
                    .enumerate()
                    .take(i1 as usize + 1)
                    .skip(i0 as usize)
                {
                    *v += amp * self.value(start + i as f64 * dt - t_e);
                }
            }
        }
    }
}
