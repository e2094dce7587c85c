//! The per-pulse choice between a sparse and a smooth prior (`method = "nnls_or_rl"`):
//! accelerated Richardson-Lucy runs on every segment, NNLS where RL's fit misfits its echoes,
//! and the one whose fit the data favour is kept.
//!
//! NNLS (non-negative spikes) is the best estimator of the tradeoff sweep on hard, discrete
//! surfaces and the worst on extended canopy; Richardson-Lucy stopped early (a smooth
//! estimate) is the reverse (docs/accuracy.md, "Choosing NNLS or RL per pulse"). RL stopped
//! early under-fits a sharp surface: its residual is then well above NNLS's, which fits every
//! sample to the noise. On canopy both fit to the noise. So, with `χ²` the sum of squared
//! residuals of each method's own fit (NNLS: its spikes blurred by the system kernel; RL: its
//! result blurred by the kernel it deconvolved, the reduced kernel of a target pulse or the
//! system kernel itself; samples left out of the fit take no part):
//!
//! ```text
//! keep NNLS when χ²_RL − χ²_NNLS > threshold · χ²_NNLS      (otherwise keep RL)
//! ```
//!
//! (`threshold` default [`DEFAULT_THRESHOLD`] = 0.5: on the tradeoff sweep and on pulses of
//! another seed it is as good as 0.3 at 3 % noise and better at 1.5 %, docs/accuracy.md; the
//! written comparison needs no division, so a noise-free exact NNLS fit is kept whenever RL
//! misfits at all, and two exact fits keep RL.)
//!
//! RL runs first. When its fit already explains its echoes to the noise, NNLS is not run and
//! RL is kept: the mean squared residual over the samples where RL's fit stands at or above the
//! noise level (its echoes) is at most `nnls_above_noise` (default
//! [`DEFAULT_NNLS_ABOVE_NOISE`] = 1) × the mean squared data over the rest of the segment (the
//! empty range: the noise the data carry, whatever a low-pass upstream left of it; the noise
//! level squared when fewer than 16 samples are empty). The rule above could then keep NNLS only
//! if NNLS fitted the data well below the noise, i.e. fitted the noise; so the test saves NNLS's
//! time without changing what the rule decides (docs/accuracy.md: the tradeoff sweep's RMSE
//! within 0.00005 of NNLS run on every pulse, 14–31 % less mean time). The means are
//! per sample, so a long empty range does not dilute the echoes' misfit. A noise level that is
//! not a positive finite number runs NNLS always, as does `nnls_above_noise = 0`.
//!
//! With a target pulse (`target_fwhm_ns`) each method delivers its result as the target sees it
//! in its own well-posed way ([`crate::signal::deconvolve::target`]: NNLS by synthesis, RL by
//! the reduced kernel); the residuals are those of the fits each method made, so the choice is
//! made the same way with and without a target. RL runs behind the default
//! echo-window gate ([`Gate::default`]), NNLS with its own settings (by default spikes only
//! near echoes, `support_at_noise = 4`).
//!
//! Cost: RL, its residual, and where RL misfits NNLS and its residual; the stated worst case is
//! the sum of both methods, two convolutions and three scans
//! ([`NnlsOrRlConfig::worst_case_flops`]). Units as every method: input volts above baseline
//! per sample, output volts per sample (the cross-section, or its view by the target pulse).

use serde::{Deserialize, Serialize};

use crate::signal::deconvolve::{
    ChoiceCounts, DeconvError, Deconvolver, Gate, Gated, MethodConfig, MethodStats, NnlsConfig,
    RlConfig, Targeted,
};
use crate::signal::kernel::{Kernel, convolve_same};

/// Default share by which RL's squared residual must exceed NNLS's for NNLS to be kept.
pub const DEFAULT_THRESHOLD: f32 = 0.5;

/// Default multiple of the empty range's mean squared data that RL's mean squared residual over
/// its echoes must exceed for NNLS to run at all.
pub const DEFAULT_NNLS_ABOVE_NOISE: f32 = 1.0;

/// Settings of the per-pulse choice (`method = "nnls_or_rl"`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NnlsOrRlConfig {
    /// The sparse prior: NNLS (default: 50 outer iterations, spikes only near echoes at τ = 4).
    pub nnls: NnlsConfig,
    /// The smooth prior: Richardson-Lucy (default: accelerated, 13 iterations after 33 coarse
    /// ones), behind the default echo-window gate.
    pub rl: RlConfig,
    /// NNLS is kept when `χ²_RL − χ²_NNLS > threshold · χ²_NNLS` (dimensionless, ≥ 0; default
    /// [`DEFAULT_THRESHOLD`]).
    pub threshold: f32,
    /// NNLS runs only when RL's mean squared residual over its echoes exceeds this multiple of
    /// the empty range's mean squared data (dimensionless, ≥ 0; 0 runs it on every segment;
    /// default [`DEFAULT_NNLS_ABOVE_NOISE`]).
    pub nnls_above_noise: f32,
}

impl Default for NnlsOrRlConfig {
    fn default() -> Self {
        NnlsOrRlConfig {
            nnls: NnlsConfig {
                support_at_noise: Some(4.0),
                ..NnlsConfig::default()
            },
            rl: RlConfig {
                iterations: 13,
                accelerate: true,
                coarse_iterations: 33,
                ..RlConfig::default()
            },
            threshold: DEFAULT_THRESHOLD,
            nnls_above_noise: DEFAULT_NNLS_ABOVE_NOISE,
        }
    }
}

impl NnlsOrRlConfig {
    /// Worst-case flops for a segment of `n` samples and a kernel of `m` taps: both methods
    /// (RL's gate adds a scan), two "same" convolutions (`2nm` each) and the residual sums
    /// (`3n` each).
    pub fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        let (n64, m64) = (n as u64, m as u64);
        self.nnls
            .worst_case_flops(n, m)
            .saturating_add(self.rl.worst_case_flops(n, m))
            .saturating_add(n64 + 4 * n64 * m64 + 6 * n64)
    }
}

/// The per-pulse choice with every buffer sized at construction (no allocation in `run` once
/// each kernel length has been seen, as [`Targeted`]).
pub struct NnlsOrRl {
    config: NnlsOrRlConfig,
    max_samples: usize,
    max_taps: usize,
    /// NNLS (to the target pulse when one is taken).
    sparse: Targeted,
    /// Richardson-Lucy behind the echo-window gate (to the target pulse when one is taken).
    smooth: Targeted,
    /// NNLS's result and the blurred-back fit, `max_samples` each.
    alt: Vec<f32>,
    fit: Vec<f32>,
    /// Segments run, segments where NNLS ran, and segments where NNLS was kept.
    runs: u64,
    nnls_runs: u64,
    kept_nnls: u64,
}

impl NnlsOrRl {
    /// Builds both methods for segments of up to `max_samples` samples and kernels of up to
    /// `max_taps` taps, without a target pulse ([`Deconvolver::take_target`] sets one).
    pub fn new(config: NnlsOrRlConfig, max_samples: usize, max_taps: usize) -> Self {
        let (sparse, smooth) = Self::methods(&config, None, max_samples, max_taps);
        NnlsOrRl {
            config,
            max_samples,
            max_taps,
            sparse,
            smooth,
            alt: vec![0.0; max_samples],
            fit: vec![0.0; max_samples],
            runs: 0,
            nnls_runs: 0,
            kept_nnls: 0,
        }
    }

    fn methods(
        config: &NnlsOrRlConfig,
        target: Option<f64>,
        max_samples: usize,
        max_taps: usize,
    ) -> (Targeted, Targeted) {
        let nnls = MethodConfig::Nnls(config.nnls.clone());
        let rl = MethodConfig::RichardsonLucy(config.rl.clone());
        let build = |m: &MethodConfig, gate: Gate| {
            let gated = Gated::build(m, gate, max_samples, max_taps);
            Targeted::new(Box::new(gated), target, max_samples, max_taps)
        };
        (build(&nnls, Gate::Off), build(&rl, Gate::default()))
    }

    /// [`Deconvolver::choice_counts`] as a tuple, for the tests: segments run, those where
    /// NNLS ran (RL's residual above the noise), and those where NNLS's result was kept.
    #[cfg(test)]
    fn choices(&self) -> (u64, u64, u64) {
        let c = self.choice_counts().unwrap_or_default();
        (c.segments, c.second_runs, c.second_kept)
    }

    fn run_with(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: Option<&[bool]>,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let n = y.len();
        if n > self.max_samples {
            return Err(DeconvError::TooLong {
                len: n,
                max: self.max_samples,
            });
        }
        let excluded = excluded.filter(|e| e.len() == n);
        let smooth = super::run_flagged(&mut self.smooth, y, k, noise_v, sample_ns, excluded, out)?;
        self.runs += 1;
        let fit = &mut self.fit[..n];
        // RL's own fit kernel: the reduced kernel its wrapper computed for this run, if any.
        let h = self.smooth.reduced_kernel().unwrap_or(k);
        let rl_fit = residuals(y, out, h, excluded, noise_v, fit);
        let chi_rl = rl_fit.total();
        let above = self.config.nnls_above_noise;
        if above > 0.0 && rl_fit.within_noise(above, noise_v) {
            return Ok(smooth);
        }
        let alt = &mut self.alt[..n];
        let sparse = super::run_flagged(&mut self.sparse, y, k, noise_v, sample_ns, excluded, alt)?;
        self.nnls_runs += 1;
        let spikes = self.sparse.last_spikes(n).unwrap_or(&self.alt[..n]);
        let chi_nnls = residuals(y, spikes, k, excluded, noise_v, fit).total();
        if chi_rl - chi_nnls > f64::from(self.config.threshold) * chi_nnls {
            self.kept_nnls += 1;
            out.copy_from_slice(&self.alt[..n]);
            return Ok(sparse);
        }
        Ok(smooth)
    }
}

/// Fewest samples of a segment's empty range (fit below the noise level) from which the noise
/// left in the data is measured; below it the noise level passed in stands for it.
const MIN_EMPTY_SAMPLES: usize = 16;

/// The squared residual `(y − x ⊛ h)²` of a fit, summed over the samples where the fit stands
/// at or above the noise level (its echoes) and where it does not (the empty range), samples
/// left out of the fit excluded; in `f64`, volts².
#[derive(Clone, Copy, Debug, Default)]
struct Residuals {
    echo: f64,
    echo_samples: usize,
    empty: f64,
    empty_samples: usize,
}

impl Residuals {
    /// `Σ (y − x ⊛ h)²` over every sample fitted.
    fn total(&self) -> f64 {
        self.echo + self.empty
    }

    /// Whether the fit explains its echoes to the noise: their mean squared residual at most
    /// `factor` × that of the empty range (the noise the data carry, whatever the low-pass left
    /// of it), or × `noise_v²` when the empty range is shorter than [`MIN_EMPTY_SAMPLES`].
    /// A segment without echoes is explained; without a noise level (not a positive finite
    /// number) nothing is.
    fn within_noise(&self, factor: f32, noise_v: f32) -> bool {
        if !(noise_v.is_finite() && noise_v > 0.0) {
            return false;
        }
        if self.echo_samples == 0 {
            return true;
        }
        let floor = if self.empty_samples >= MIN_EMPTY_SAMPLES {
            self.empty / self.empty_samples as f64
        } else {
            f64::from(noise_v).powi(2)
        };
        floor.is_finite() && self.echo <= f64::from(factor) * floor * self.echo_samples as f64
    }
}

/// The [`Residuals`] of the fit `x ⊛ h` to `y` (`fit` as scratch, as long as `y`), echoes
/// where the fit is at least `noise_v`.
fn residuals(
    y: &[f32],
    x: &[f32],
    h: &Kernel,
    excluded: Option<&[bool]>,
    noise_v: f32,
    fit: &mut [f32],
) -> Residuals {
    convolve_same(x, h, fit);
    let mut r = Residuals::default();
    for (i, (&a, &b)) in y.iter().zip(fit.iter()).enumerate() {
        if excluded.is_some_and(|e| e[i]) {
            continue;
        }
        let sq = (f64::from(a) - f64::from(b)).powi(2);
        if b >= noise_v {
            r.echo += sq;
            r.echo_samples += 1;
        } else {
            r.empty += sq;
            r.empty_samples += 1;
        }
    }
    r
}

impl Deconvolver for NnlsOrRl {
    fn name(&self) -> &'static str {
        "nnls_or_rl"
    }

    fn choice_counts(&self) -> Option<ChoiceCounts> {
        Some(ChoiceCounts {
            segments: self.runs,
            second_runs: self.nnls_runs,
            second_kept: self.kept_nnls,
        })
    }

    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.run_with(y, k, noise_v, sample_ns, None, out)
    }

    fn run_excluding(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: &[bool],
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        self.run_with(y, k, noise_v, sample_ns, Some(excluded), out)
    }

    fn take_target(&mut self, fwhm_ns: f64) -> bool {
        let (sparse, smooth) =
            Self::methods(&self.config, Some(fwhm_ns), self.max_samples, self.max_taps);
        self.sparse = sparse;
        self.smooth = smooth;
        true
    }

    fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        let (n64, m64) = (n as u64, m as u64);
        self.sparse
            .worst_case_flops(n, m)
            .saturating_add(self.smooth.worst_case_flops(n, m))
            .saturating_add(4 * n64 * m64 + 6 * n64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit-sum Gaussian pulse of `fwhm_ns` at `sample_ns` per sample.
    fn gaussian_pulse(
        fwhm_ns: f64,
        sample_ns: f64,
    ) -> Result<Kernel, crate::signal::kernel::KernelError> {
        let mut k = Kernel::with_capacity(64);
        k.set_gaussian(fwhm_ns, sample_ns)?;
        Ok(k)
    }

    /// A deterministic uniform noise in ±`amp`.
    fn noise(n: usize, amp: f32, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * amp
            })
            .collect()
    }

    fn blurred(x: &[f32], k: &Kernel) -> Vec<f32> {
        let mut y = vec![0.0; x.len()];
        convolve_same(x, k, &mut y);
        y
    }

    /// `x ⊛ k` plus [`noise`] of half-range `amp`.
    fn received(x: &[f32], k: &Kernel, amp: f32, seed: u64) -> Vec<f32> {
        let y = blurred(x, k);
        y.iter()
            .zip(noise(y.len(), amp, seed))
            .map(|(a, b)| a + b)
            .collect()
    }

    /// Two hard surfaces 6 ns apart under an 8 ns pulse, uniform noise of half-range 0.003.
    fn sharp_surfaces() -> (Kernel, Vec<f32>) {
        let k = gaussian_pulse(8.0, 1.0).unwrap();
        let mut x = vec![0.0f32; 160];
        x[70] = 1.0;
        x[76] = 0.7;
        let y = received(&x, &k, 0.003, 1);
        (k, y)
    }

    /// Two hard surfaces 6 ns apart under an 8 ns pulse: RL stopped early under-fits them, so
    /// NNLS is kept; its result is the one returned.
    #[test]
    fn keeps_nnls_on_sharp_surfaces() {
        let (k, y) = sharp_surfaces();
        let mut chooser = NnlsOrRl::new(NnlsOrRlConfig::default(), 256, 64);
        let mut out = vec![0.0; 160];
        chooser.run(&y, &k, 0.0015, 1.0, &mut out).unwrap();
        assert_eq!(chooser.choices(), (1, 1, 1));
        let mut nnls = MethodConfig::Nnls(NnlsOrRlConfig::default().nnls).build(256, 64);
        let mut want = vec![0.0; 160];
        nnls.run(&y, &k, 0.0015, 1.0, &mut want).unwrap();
        assert_eq!(out, want);
    }

    /// A wide extended return (canopy: a smooth profile over 40 ns) under uniform noise of
    /// half-range `amp` (σ = amp / √3).
    fn extended_return() -> (Kernel, Vec<f32>, f32) {
        let k = gaussian_pulse(8.0, 1.0).unwrap();
        let x: Vec<f32> = (0..200)
            .map(|i| {
                let t = (i as f32 - 100.0) / 14.0;
                0.05 * (-0.5 * t * t).exp()
            })
            .collect();
        let amp = 0.01;
        (k.clone(), received(&x, &k, amp, 2), amp / 3f32.sqrt())
    }

    /// On the extended return RL fits to the noise: NNLS is not run, RL is kept.
    #[test]
    fn keeps_rl_on_an_extended_return_without_running_nnls() {
        let (k, y, sigma) = extended_return();
        let mut chooser = NnlsOrRl::new(NnlsOrRlConfig::default(), 256, 64);
        let mut out = vec![0.0; 200];
        chooser.run(&y, &k, sigma, 1.0, &mut out).unwrap();
        assert_eq!(chooser.choices(), (1, 0, 0));
        let mut rl = Gated::build(
            &MethodConfig::RichardsonLucy(NnlsOrRlConfig::default().rl),
            Gate::default(),
            256,
            64,
        );
        let mut want = vec![0.0; 200];
        rl.run(&y, &k, sigma, 1.0, &mut want).unwrap();
        assert_eq!(out, want);
    }

    /// With NNLS run on every segment (`nnls_above_noise = 0`) both fit to the noise on the
    /// extended return and the residual rule keeps RL; with the noise level underestimated
    /// tenfold NNLS runs and the rule still keeps RL.
    #[test]
    fn the_rule_keeps_rl_on_an_extended_return_when_nnls_runs() {
        let (k, y, sigma) = extended_return();
        let always = NnlsOrRlConfig {
            nnls_above_noise: 0.0,
            ..NnlsOrRlConfig::default()
        };
        let mut out = vec![0.0; 200];
        for (config, level) in [(always, sigma), (NnlsOrRlConfig::default(), sigma / 10.0)] {
            let mut chooser = NnlsOrRl::new(config, 256, 64);
            chooser.run(&y, &k, level, 1.0, &mut out).unwrap();
            assert_eq!(chooser.choices(), (1, 1, 0));
        }
    }

    /// The noise RL's echoes are held to is the empty range's, not the level passed in: with
    /// that level three times the data's noise (as the noise above a low-pass cut-off can
    /// overstate the noise left below it) NNLS still runs on sharp surfaces and is kept.
    #[test]
    fn the_noise_floor_comes_from_the_empty_range() {
        let (k, y) = sharp_surfaces();
        let sigma = 0.003 / 3f32.sqrt();
        let mut chooser = NnlsOrRl::new(NnlsOrRlConfig::default(), 256, 64);
        let mut out = vec![0.0; 160];
        chooser.run(&y, &k, 3.0 * sigma, 1.0, &mut out).unwrap();
        assert_eq!(chooser.choices(), (1, 1, 1));
    }

    /// A segment of noise alone: no echo for RL to misfit, so NNLS is not run — unless
    /// `nnls_above_noise = 0`, which runs it on every segment.
    #[test]
    fn noise_alone_runs_nnls_only_when_asked_to() {
        let k = gaussian_pulse(8.0, 1.0).unwrap();
        let y = noise(120, 0.01, 5);
        let sigma = 0.01 / 3f32.sqrt();
        let mut out = vec![0.0; 120];
        let mut chooser = NnlsOrRl::new(NnlsOrRlConfig::default(), 256, 64);
        chooser.run(&y, &k, sigma, 1.0, &mut out).unwrap();
        assert_eq!(chooser.choices().1, 0);
        let always = NnlsOrRlConfig {
            nnls_above_noise: 0.0,
            ..NnlsOrRlConfig::default()
        };
        let mut chooser = NnlsOrRl::new(always, 256, 64);
        chooser.run(&y, &k, sigma, 1.0, &mut out).unwrap();
        assert_eq!(chooser.choices().1, 1);
    }

    /// A noise level far above the data's makes the choice fall back to RL on sharp surfaces
    /// (NNLS not run), never to NNLS.
    #[test]
    fn an_overestimated_noise_level_falls_back_to_rl() {
        let (k, y) = sharp_surfaces();
        let mut chooser = NnlsOrRl::new(NnlsOrRlConfig::default(), 256, 64);
        let mut out = vec![0.0; 160];
        chooser.run(&y, &k, 0.5, 1.0, &mut out).unwrap();
        assert_eq!(chooser.choices(), (1, 0, 0));
    }

    /// With a target pulse both results are the target's view, and the choice is made through
    /// the reduced kernel: on sharp surfaces NNLS's synthesis is kept.
    #[test]
    fn takes_the_target_pulse_for_both_methods() {
        let k = gaussian_pulse(8.0, 1.0).unwrap();
        let mut x = vec![0.0f32; 160];
        x[60] = 1.0;
        x[67] = 0.5;
        let y = blurred(&x, &k);
        let mut chooser = Targeted::new(
            Box::new(NnlsOrRl::new(NnlsOrRlConfig::default(), 256, 64)),
            Some(2.0),
            256,
            64,
        );
        let mut out = vec![0.0; 160];
        chooser.run(&y, &k, 1e-4, 1.0, &mut out).unwrap();
        let t = gaussian_pulse(2.0, 1.0).unwrap();
        let truth = blurred(&x, &t);
        let err = out
            .iter()
            .zip(&truth)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 0.02, "largest error {err}");
        assert_eq!(chooser.target_fwhm_ns(), Some(2.0));
    }

    #[test]
    fn worst_case_is_the_sum_of_both_methods() {
        let c = NnlsOrRlConfig::default();
        let both = c.nnls.worst_case_flops(256, 41) + c.rl.worst_case_flops(256, 41);
        let wc = c.worst_case_flops(256, 41);
        assert!(wc > both && wc < both + 50_000, "{wc} vs {both}");
        let built = NnlsOrRl::new(c.clone(), 256, 64);
        assert!(built.worst_case_flops(256, 41) >= both);
    }

    #[test]
    fn config_rejects_unknown_fields_and_has_defaults() {
        let c: NnlsOrRlConfig =
            toml::from_str("threshold = 0.5\n[nnls]\nmax_iterations = 20\n").expect("parses");
        assert_eq!(c.threshold, 0.5);
        assert_eq!(c.nnls_above_noise, DEFAULT_NNLS_ABOVE_NOISE);
        assert_eq!(c.nnls.max_iterations, 20);
        assert_eq!(c.rl, NnlsOrRlConfig::default().rl);
        assert!(toml::from_str::<NnlsOrRlConfig>("thresold = 0.5\n").is_err());
    }
}
