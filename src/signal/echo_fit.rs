//! Echoes found against the learned system response ([`crate::signal::learned_response`]):
//! an echo is the response shifted and scaled — stretched in width only where the data ask for
//! it — and what one echo of that shape explains is one return.
//!
//! Per return segment, in digitizer counts ([`EchoFinder::find`]):
//!
//! 1. **Floor**: the baseline and noise σ of its first samples
//!    ([`crate::signal::learned_response::pretrigger_floor`]), σ never below one count (the
//!    digitizer's quantum: a quantised constant baseline measures as no noise at all, and a
//!    threshold of a few times nothing passes every 1-3 count bump).
//! 2. **Candidates**, strongest first: the sample where the residual (the data less the echoes
//!    found so far, tails included) stands highest above the threshold
//!    `snr × √(σ² + (w/snr)² × u²)`, `u` the spread of the response at that sample scaled by
//!    the amplitudes of the echoes found (`√Σ (Aⱼ spread(t − τⱼ))²`) and `w =`
//!    [`EchoSettings::spread_weight`]: near a strong echo a candidate must also stand above what
//!    the echo's modelled shape can be wrong by.
//! 3. **Fit**: the response's position τ (every 0.5 sample within ±1.5 samples of the
//!    candidate, then every 0.1 sample about the best) and amplitude A (least squares over the samples within ±2.5 half widths of the
//!    candidate, the same samples for every τ) that leave the least residual. When that residual exceeds what the noise and the
//!    response's own error allow (`accept_sigmas × σ² + (model_error × A)²` per sample), the
//!    data ask for a wider echo: the stretches of [`EchoSettings::stretches`] are tried and
//!    the best one that does fit is kept. An echo below `snr × σ` ends the search.
//! 4. The echo's whole shape is subtracted (its tail too) and the search goes on, for at most
//!    `max_echoes`.
//! 5. **Refinement**, after each new echo: every echo found so far is fitted again with the
//!    others subtracted, twice. Echoes that end at the threshold or below are dropped.
//!
//! Costs are fixed by the settings: at most `max_echoes` × (a pass over the segment + 16
//! positions × the core's samples × the stretches + the response's support) plus the
//! refinement's `max_echoes² × 2` fits of 16 positions (7 coarse, 9 fine). Buffers are sized
//! once ([`EchoFinder::new`]); finding allocates nothing.

use crate::signal::learned_response::{LearnedResponse, pretrigger_floor};

/// Settings of the search (the `decompose` stage's with `model = "response"`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EchoSettings {
    /// Detection threshold, noise σ (the stage's `min_snr`).
    pub snr: f32,
    /// Weight of the found echoes' modelled error in the threshold.
    pub spread_weight: f32,
    /// Most echoes per segment.
    pub max_echoes: usize,
    /// A fit is acceptable when its mean squared residual is at most this many σ² ...
    pub accept_sigmas: f32,
    /// ... plus (this fraction × A)²: the response's own error.
    pub model_error: f32,
}

impl Default for EchoSettings {
    fn default() -> Self {
        EchoSettings {
            snr: 5.0,
            spread_weight: 3.0,
            max_echoes: 8,
            accept_sigmas: 2.0,
            model_error: 0.05,
        }
    }
}

/// Width stretches tried when the data ask for a wider echo than the response.
pub const STRETCHES: [f32; 6] = [1.0, 1.25, 1.5, 2.0, 2.5, 3.0];
/// Positions tried either side of a candidate, samples, and their spacing.
const SHIFT_SPAN: f32 = 1.5;
const SHIFT_STEP: f32 = 0.1;
/// The coarse spacing of positions tried before the fine one, samples.
const COARSE_STEP: f32 = 0.5;
/// Refinement sweeps over the echoes found ([`EchoFinder::refine`]).
const REFINE_SWEEPS: usize = 2;
/// Half width of the fitted core, in half widths at half maximum of the response.
const CORE_HALF_WIDTHS: f32 = 2.5;

/// One echo: the response at `position` samples from the segment's first sample, scaled by
/// `amplitude` counts above the baseline, stretched by `stretch`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Echo {
    /// Peak position, samples from the segment's first sample (fractional).
    pub position: f32,
    /// Peak amplitude above the baseline, counts.
    pub amplitude: f32,
    /// Width relative to the response (1: a hard target).
    pub stretch: f32,
}

/// What one search found besides the echoes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EchoStats {
    /// Baseline of the segment, counts.
    pub baseline: f32,
    /// Noise σ of the segment, counts (at least one).
    pub sigma: f32,
    /// RMS of the data less the echoes over the segment, counts.
    pub rms_residual: f32,
}

/// Finds echoes in segments of up to a fixed length; buffers sized once.
pub struct EchoFinder {
    settings: EchoSettings,
    max_samples: usize,
    residual: Vec<f32>,
    variance: Vec<f32>,
}

impl EchoFinder {
    /// A finder for segments of up to `max_samples`.
    pub fn new(settings: EchoSettings, max_samples: usize) -> Self {
        EchoFinder {
            settings,
            max_samples,
            residual: Vec::with_capacity(max_samples),
            variance: Vec::with_capacity(max_samples),
        }
    }

    /// The settings.
    pub fn settings(&self) -> &EchoSettings {
        &self.settings
    }

    /// Finds the echoes of `response` in `y` (counts; at most `max_samples`, longer ones are
    /// cut), strongest first into `out` (cleared), which the caller reuses.
    pub fn find(
        &mut self,
        y: &[f32],
        response: &LearnedResponse,
        out: &mut Vec<Echo>,
    ) -> EchoStats {
        out.clear();
        let y = &y[..y.len().min(self.max_samples)];
        let n = y.len();
        let (baseline, sigma) = pretrigger_floor(y, 1.0);
        let mut stats = EchoStats {
            baseline,
            sigma,
            rms_residual: 0.0,
        };
        if n == 0 {
            return stats;
        }
        self.residual.clear();
        self.residual.extend(y.iter().map(|v| v - baseline));
        self.variance.clear();
        self.variance.resize(n, 0.0);
        let s = self.settings;
        let half = 0.5 * response.fwhm_samples.max(0.5);
        let core = (CORE_HALF_WIDTHS * half).ceil().max(3.0);
        let ratio = s.spread_weight / s.snr;
        for _ in 0..s.max_echoes {
            let Some(i) = self.strongest_candidate(sigma, ratio) else {
                break;
            };
            let e = fit_one(&self.residual, i, sigma, core, response, &s);
            if e.amplitude.is_nan() || e.amplitude <= s.snr * sigma {
                break;
            }
            self.subtract(&e, response);
            out.push(e);
            self.refine(out, core, response);
        }
        self.drop_weak(out, sigma, response);
        let ss: f64 = self.residual.iter().map(|v| f64::from(*v).powi(2)).sum();
        stats.rms_residual = (ss / n as f64).sqrt() as f32;
        stats
    }

    /// The sample standing highest above the threshold (then the highest residual within two
    /// samples of it), `None` when none exceeds it.
    fn strongest_candidate(&self, sigma: f32, ratio: f32) -> Option<usize> {
        let snr = self.settings.snr;
        let mut best: Option<(f32, usize)> = None;
        for (i, (&r, &u2)) in self.residual.iter().zip(&self.variance).enumerate() {
            let thr = snr * (sigma * sigma + ratio * ratio * u2).sqrt();
            let over = r - thr;
            if over > 0.0 && best.is_none_or(|b| over > b.0) {
                best = Some((over, i));
            }
        }
        let (_, i) = best?;
        let lo = i.saturating_sub(2);
        let hi = (i + 3).min(self.residual.len());
        let mut at = i;
        for k in lo..hi {
            if self.residual[k] > self.residual[at] {
                at = k;
            }
        }
        Some(at)
    }

    /// Refits every echo with the others subtracted (its height and position, its stretch
    /// kept), in the order found, [`REFINE_SWEEPS`] times, after each new echo: an echo
    /// fitted before a close neighbour was found sat a little off, and left a flank that looked
    /// like a third echo.
    fn refine(&mut self, out: &mut [Echo], core: f32, r: &LearnedResponse) {
        let Some(&newest) = out.last() else {
            return;
        };
        if out.len() < 2 {
            return;
        }
        // Only the echoes whose fitted cores reach the newest one's can have moved.
        let reach = 2.0 * core * STRETCHES[STRETCHES.len() - 1];
        for _ in 0..REFINE_SWEEPS {
            for e in out.iter_mut() {
                if (e.position - newest.position).abs() > reach {
                    continue;
                }
                let old = *e;
                self.shift_residual(&old, r, 1.0);
                let at = old
                    .position
                    .round()
                    .clamp(0.0, (self.residual.len() - 1) as f32) as usize;
                let (_, new) = fit_stretch(&self.residual, at, core, old.stretch, r);
                let new = if new.amplitude > 0.0 { new } else { old };
                self.shift_residual(&new, r, -1.0);
                *e = new;
            }
        }
    }

    /// Drops the echoes that refinement left at `snr × σ` or below (their shape given back to
    /// the residual).
    fn drop_weak(&mut self, out: &mut Vec<Echo>, sigma: f32, r: &LearnedResponse) {
        let floor = self.settings.snr * sigma;
        let mut k = 0;
        while k < out.len() {
            if out[k].amplitude <= floor {
                let e = out.remove(k);
                self.shift_residual(&e, r, 1.0);
            } else {
                k += 1;
            }
        }
    }

    /// Adds `sign` × echo `e` (its whole shape) to the residual.
    fn shift_residual(&mut self, e: &Echo, r: &LearnedResponse, sign: f32) {
        let n = self.residual.len();
        let from = (e.position + e.stretch * r.start_samples).floor().max(0.0) as usize;
        let to = ((e.position + e.stretch * r.end_samples()).ceil().max(0.0) as usize + 1).min(n);
        for k in from..to {
            let x = (k as f32 - e.position) / e.stretch;
            self.residual[k] += sign * e.amplitude * r.value_at(x);
        }
    }

    /// Removes echo `e` (its whole shape) from the residual and adds its modelled error to the
    /// variance map.
    fn subtract(&mut self, e: &Echo, r: &LearnedResponse) {
        let n = self.residual.len();
        let from = (e.position + e.stretch * r.start_samples).floor().max(0.0) as usize;
        let to = ((e.position + e.stretch * r.end_samples()).ceil().max(0.0) as usize + 1).min(n);
        for k in from..to {
            let x = (k as f32 - e.position) / e.stretch;
            self.residual[k] -= e.amplitude * r.value_at(x);
            let u = e.amplitude * r.spread_at(x);
            self.variance[k] += u * u;
        }
    }
}

/// The best echo of `response` near sample `i` of `res` (module doc, step 3).
fn fit_one(
    res: &[f32],
    i: usize,
    sigma: f32,
    core: f32,
    response: &LearnedResponse,
    s: &EchoSettings,
) -> Echo {
    let mut best = fit_stretch(res, i, core, 1.0, response);
    let acceptable =
        |e: f32, a: f32| e <= s.accept_sigmas * sigma * sigma + (s.model_error * a).powi(2);
    if acceptable(best.0, best.1.amplitude) {
        return best.1;
    }
    for &stretch in &STRETCHES[1..] {
        let c = fit_stretch(res, i, core, stretch, response);
        if acceptable(c.0, c.1.amplitude) && c.0 < best.0 {
            best = c;
        }
    }
    best.1
}

/// The least-squares echo of stretch `stretch` near `i`: (mean squared residual over the core,
/// the echo). Positions are searched coarse to fine: every [`COARSE_STEP`] within
/// ±[`SHIFT_SPAN`] of `i`, then every [`SHIFT_STEP`] within a coarse step of the best.
fn fit_stretch(
    res: &[f32],
    i: usize,
    core: f32,
    stretch: f32,
    response: &LearnedResponse,
) -> (f32, Echo) {
    let n = res.len() as f32;
    // One window for every position tried, so that their residuals compare.
    let half = core * stretch;
    let lo = (i as f32 - half).ceil().max(0.0) as usize;
    let hi = (i as f32 + half).floor().min(n - 1.0).max(0.0) as usize;
    let window = &res[lo..=hi.max(lo)];
    let yy: f32 = window.iter().map(|v| v * v).sum();
    let count = window.len() as f32;
    let at = |tau: f32| -> Option<(f32, Echo)> {
        let (mut hy, mut hh) = (0.0f32, 0.0f32);
        for (j, &v) in window.iter().enumerate() {
            let h = response.value_at(((lo + j) as f32 - tau) / stretch);
            hy += h * v;
            hh += h * h;
        }
        if hh.is_nan() || hh <= 0.0 {
            return None;
        }
        let a = hy / hh;
        let e = ((yy - a * hy) / count).max(0.0);
        Some((
            e,
            Echo {
                position: tau,
                amplitude: a,
                stretch,
            },
        ))
    };
    let mut best = (
        f32::INFINITY,
        Echo {
            position: i as f32,
            amplitude: res[i],
            stretch,
        },
    );
    let keep = |c: Option<(f32, Echo)>, best: &mut (f32, Echo)| {
        if let Some(c) = c
            && c.0 < best.0
        {
            *best = c;
        }
    };
    let coarse = (2.0 * SHIFT_SPAN / COARSE_STEP).round() as i32;
    for k in 0..=coarse {
        keep(
            at(i as f32 - SHIFT_SPAN + k as f32 * COARSE_STEP),
            &mut best,
        );
    }
    let centre = best.1.position;
    let fine = (COARSE_STEP / SHIFT_STEP).round() as i32;
    for k in -fine + 1..fine {
        if k != 0 {
            keep(at(centre + k as f32 * SHIFT_STEP), &mut best);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::learned_response::ResponseLearner;
    use crate::signal::learned_response::tests::{riegl_like, segments};
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn learned() -> LearnedResponse {
        let mut l = ResponseLearner::new();
        for y in segments(1500, 11) {
            l.add_segment(1, 1.0, &y, 255.0);
        }
        l.finish("t").unwrap().responses.remove(0)
    }

    /// An 8-bit segment: baseline 3, quantised noise of σ `noise`, the given echoes.
    fn segment(echoes: &[(f64, f64)], noise: f64, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..80)
            .map(|i| {
                let s: f64 = echoes
                    .iter()
                    .map(|&(a, at)| a * riegl_like(i as f64 - at))
                    .sum();
                let e: f64 = rng.random_range(-1.0..1.0) * noise * 3f64.sqrt();
                (3.0 + s + e).round().clamp(0.0, 255.0) as f32
            })
            .collect()
    }

    /// One strong echo with its bump and tail is one return, at its peak; the tail and bump
    /// are not echoes.
    #[test]
    fn a_strong_echo_with_its_tail_is_one_return() {
        let r = learned();
        let mut f = EchoFinder::new(EchoSettings::default(), 256);
        let mut out = Vec::new();
        for seed in 0..40 {
            let y = segment(&[(170.0, 20.3)], 0.6, seed);
            f.find(&y, &r, &mut out);
            assert_eq!(out.len(), 1, "seed {seed}: {out:?}");
            assert!((out[0].position - 20.3).abs() < 0.2, "{out:?}");
            assert!((out[0].amplitude - 170.0).abs() < 6.0, "{out:?}");
            assert_eq!(out[0].stretch, 1.0);
        }
    }

    /// Two echoes 6 samples apart are two returns; a weak echo 25 samples after a strong one
    /// stands above the tail and is found.
    #[test]
    fn close_and_weak_echoes_are_found() {
        let r = learned();
        let mut f = EchoFinder::new(EchoSettings::default(), 256);
        let mut out = Vec::new();
        let y = segment(&[(150.0, 20.0), (110.0, 26.0)], 0.6, 3);
        f.find(&y, &r, &mut out);
        let mut at: Vec<f32> = out.iter().map(|e| e.position).collect();
        at.sort_by(f32::total_cmp);
        assert_eq!(at.len(), 2, "{out:?}");
        assert!(
            (at[0] - 20.0).abs() < 0.4 && (at[1] - 26.0).abs() < 0.4,
            "{at:?}"
        );
        let y = segment(&[(160.0, 15.0), (12.0, 40.0)], 0.6, 4);
        f.find(&y, &r, &mut out);
        assert_eq!(out.len(), 2, "{out:?}");
        assert!((out[1].position - 40.0).abs() < 0.6, "{out:?}");
    }

    /// A quantised baseline with 1-3 count bumps and no echo gives nothing.
    #[test]
    fn quantised_noise_is_no_echo() {
        let r = learned();
        let mut f = EchoFinder::new(EchoSettings::default(), 256);
        let mut out = Vec::new();
        let mut y = vec![3.0f32; 80];
        for (k, v) in [(20, 5.0), (33, 6.0), (50, 4.0), (61, 5.0)] {
            y[k] = v;
        }
        let st = f.find(&y, &r, &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert_eq!(st.sigma, 1.0);
        for seed in 0..50 {
            let y = segment(&[], 0.6, 100 + seed);
            f.find(&y, &r, &mut out);
            assert!(out.is_empty(), "seed {seed}: {out:?}");
        }
    }

    /// A wide echo (a slanted surface: the response stretched 2×) is one stretched return.
    #[test]
    fn a_stretched_echo_is_one_return() {
        let r = learned();
        let mut f = EchoFinder::new(EchoSettings::default(), 256);
        let mut out = Vec::new();
        let y: Vec<f32> = (0..80)
            .map(|i| (3.0 + 120.0 * riegl_like((i as f64 - 30.0) / 2.0)).round() as f32)
            .collect();
        f.find(&y, &r, &mut out);
        assert_eq!(out.len(), 1, "{out:?}");
        assert!(out[0].stretch >= 1.5, "{out:?}");
    }
}
