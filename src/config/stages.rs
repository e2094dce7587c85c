//! Semantic checks of the stage configurations of `[[pipeline.stages]]` (the configurations
//! themselves live with their stages).

use crate::core::validate::{Validate, Validator, field};
use crate::pipeline::registry::StageConfig;
use crate::signal::calibrate::CalibrateConfig;
use crate::signal::decompose::{DecomposeConfig, MAX_RUNNING_MEAN_BINS};
use crate::signal::deconvolve::response::{ResponseError, response_from_flat_target};
use crate::signal::deconvolve::richardson_lucy::MAX_COARSE_ITERATIONS;
use crate::signal::deconvolve::{DeconvolveConfig, GateError, KernelSource, MethodConfig};
use crate::signal::denoise::DenoiseConfig;
use crate::signal::gauss_fit::MAX_COMPONENTS;

/// Largest segment a stage may be configured for, samples.
pub(crate) const MAX_SEGMENT_SAMPLES: usize = 1_048_576;
/// Smallest segment buffer a stage may be configured for, samples.
pub(crate) const MIN_SEGMENT_SAMPLES: usize = 16;

impl Validate for StageConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        match self {
            StageConfig::Passthrough => {}
            StageConfig::Denoise(c) => Validate::validate(c, path, v),
            StageConfig::Deconvolve(c) => Validate::validate(c, path, v),
            StageConfig::Decompose(c) => Validate::validate(c, path, v),
            StageConfig::Calibrate(c) => Validate::validate(c, path, v),
            StageConfig::Metrics(c) => Validate::validate(c, path, v),
        }
    }
}

impl Validate for crate::forest::pulse_metrics::MetricsConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        v.require(
            nonneg(self.smoothing_sigma_ns) && self.smoothing_sigma_ns <= 1000.0,
            field(path, "smoothing_sigma_ns"),
            "must be 0 (the outgoing pulse's σ) or a σ in ns up to 1000",
        );
        v.positive(
            self.front_threshold_sigmas,
            field(path, "front_threshold_sigmas"),
        );
        v.positive(
            self.back_threshold_sigmas,
            field(path, "back_threshold_sigmas"),
        );
        v.positive(self.rho_ratio, field(path, "rho_ratio"));
        v.positive(self.leaf_projection_g, field(path, "leaf_projection_g"));
        v.require(
            self.clumping_omega.is_finite()
                && self.clumping_omega > 0.0
                && self.clumping_omega <= 1.0,
            field(path, "clumping_omega"),
            "must be in (0, 1]",
        );
        v.require(
            nonneg(self.ground_centre_buffer_ns),
            field(path, "ground_centre_buffer_ns"),
            "must be a non-negative number of ns",
        );
        v.positive(self.profile_bin_m, field(path, "profile_bin_m"));
        v.require(
            (1..=crate::forest::pulse_metrics::MAX_PROFILE_BINS).contains(&self.profile_bins),
            field(path, "profile_bins"),
            format!(
                "must be 1..={}",
                crate::forest::pulse_metrics::MAX_PROFILE_BINS
            ),
        );
        v.require(
            self.fhd_bin_m.is_finite() && self.fhd_bin_m >= 0.1,
            field(path, "fhd_bin_m"),
            "must be at least 0.1 m",
        );
        v.require(
            self.crown_energy_fraction > 0.0 && self.crown_energy_fraction <= 1.0,
            field(path, "crown_energy_fraction"),
            "must be in (0, 1]",
        );
        v.positive(self.herbaceous_height_m, field(path, "herbaceous_height_m"));
    }
}

impl Validate for DenoiseConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        let cutoff = field(path, "cutoff_ghz");
        v.positive(self.cutoff_ghz, &cutoff);
        // A non-positive cut-off is reported once, above, not again against Nyquist.
        let positive = self.cutoff_ghz.is_finite() && self.cutoff_ghz > 0.0;
        let dt_ns = v
            .sample_interval_ns()
            .filter(|dt| dt.is_finite() && *dt > 0.0);
        if let Some(dt_ns) = dt_ns.filter(|_| positive) {
            let nyquist_ghz = 1.0 / (2.0 * dt_ns);
            v.require(
                self.cutoff_ghz < nyquist_ghz,
                cutoff,
                format!(
                    "must be below the Nyquist frequency {nyquist_ghz} GHz of the sensor's \
                     {dt_ns} ns sample interval, got {}",
                    self.cutoff_ghz
                ),
            );
        }
        v.require(
            (MIN_SEGMENT_SAMPLES..=MAX_SEGMENT_SAMPLES).contains(&self.max_samples),
            field(path, "max_samples"),
            format!(
                "must be in {MIN_SEGMENT_SAMPLES}..={MAX_SEGMENT_SAMPLES} samples, got {}",
                self.max_samples
            ),
        );
        v.require(
            self.pretrigger_samples < self.max_samples,
            field(path, "pretrigger_samples"),
            format!(
                "must be less than max_samples ({}), got {}",
                self.max_samples, self.pretrigger_samples
            ),
        );
    }
}

impl Validate for CalibrateConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        for (name, value) in [
            ("system_constant_value", self.system_constant_value),
            ("reference_range_m", Some(self.reference_range_m)),
            ("reference_energy_v_ns", Some(self.reference_energy_v_ns)),
        ] {
            if let Some(x) = value {
                v.positive(x, field(path, name));
            }
        }
        v.require(
            (1.0..=1.001).contains(&self.refractive_index),
            field(path, "refractive_index"),
            format!(
                "must be in 1..=1.001 (1 = vacuum), got {}",
                self.refractive_index
            ),
        );
    }
}

/// Largest iteration budget a deconvolution method may be configured for (per repetition).
pub(crate) const MAX_DECONV_ITERATIONS: u32 = 10_000;
/// Largest kernel a deconvolve stage may be configured for, taps.
pub(crate) const MAX_KERNEL_TAPS: usize = 65_536;

/// Checks a cut-off frequency (GHz) at `path`: positive and below the sensor's Nyquist frequency
/// when the sample interval is known.
fn check_cutoff(cutoff_ghz: f64, path: String, v: &mut Validator) {
    v.positive(cutoff_ghz, path.clone());
    let positive = cutoff_ghz.is_finite() && cutoff_ghz > 0.0;
    let dt_ns = v
        .sample_interval_ns()
        .filter(|dt| dt.is_finite() && *dt > 0.0);
    if let Some(dt_ns) = dt_ns.filter(|_| positive) {
        let nyquist_ghz = 1.0 / (2.0 * dt_ns);
        v.require(
            cutoff_ghz < nyquist_ghz,
            path,
            format!(
                "must be below the Nyquist frequency {nyquist_ghz} GHz of the sensor's \
                 {dt_ns} ns sample interval, got {cutoff_ghz}"
            ),
        );
    }
}

fn check_iterations(n: u32, path: String, v: &mut Validator) {
    v.require(
        (1..=MAX_DECONV_ITERATIONS).contains(&n),
        path,
        format!("must be in 1..={MAX_DECONV_ITERATIONS}, got {n}"),
    );
}

impl Validate for DeconvolveConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        v.require(
            (MIN_SEGMENT_SAMPLES..=MAX_SEGMENT_SAMPLES).contains(&self.max_samples),
            field(path, "max_samples"),
            format!(
                "must be in {MIN_SEGMENT_SAMPLES}..={MAX_SEGMENT_SAMPLES} samples, got {}",
                self.max_samples
            ),
        );
        v.require(
            (1..=MAX_KERNEL_TAPS).contains(&self.max_taps),
            field(path, "max_taps"),
            format!(
                "must be in 1..={MAX_KERNEL_TAPS} taps, got {}",
                self.max_taps
            ),
        );
        let method = field(path, "method");
        match &self.method {
            MethodConfig::RichardsonLucy(c) => {
                check_iterations(c.iterations, field(&method, "iterations"), v);
                if let Some(tol) = c.early_stop {
                    v.positive(tol as f64, field(&method, "early_stop"));
                }
                if let Some(tau) = c.stop_at_noise {
                    v.positive(tau as f64, field(&method, "stop_at_noise"));
                }
                v.require(
                    c.coarse_iterations <= MAX_COARSE_ITERATIONS,
                    field(&method, "coarse_iterations"),
                    format!(
                        "must be in 0..={MAX_COARSE_ITERATIONS}, got {}",
                        c.coarse_iterations
                    ),
                );
                v.require(
                    c.coarse_fwhm_samples.is_finite() && c.coarse_fwhm_samples >= 1.0,
                    field(&method, "coarse_fwhm_samples"),
                    format!(
                        "must be a finite number of coarse samples ≥ 1, got {}",
                        c.coarse_fwhm_samples
                    ),
                );
            }
            MethodConfig::Gold(c) => {
                check_iterations(c.iterations, field(&method, "iterations"), v);
                check_iterations(c.repetitions, field(&method, "repetitions"), v);
                v.positive(c.boost as f64, field(&method, "boost"));
                if let Some(tau) = c.stop_at_noise {
                    v.positive(tau as f64, field(&method, "stop_at_noise"));
                }
            }
            MethodConfig::Wiener(c) => {
                check_cutoff(c.cutoff_ghz, field(&method, "cutoff_ghz"), v);
                v.require(
                    c.noise_scale.is_finite() && c.noise_scale >= 0.0,
                    field(&method, "noise_scale"),
                    format!("must be a finite number ≥ 0, got {}", c.noise_scale),
                );
                v.positive(c.regularisation as f64, field(&method, "regularisation"));
            }
            MethodConfig::Nnls(c) => {
                check_iterations(c.max_iterations, field(&method, "max_iterations"), v);
                v.require(
                    c.tolerance.is_finite() && c.tolerance >= 0.0 && c.tolerance < 1.0,
                    field(&method, "tolerance"),
                    format!("must be a relative tolerance in 0..1, got {}", c.tolerance),
                );
            }
        }
        if let Some(f) = self.target_fwhm_ns {
            v.positive(f, field(path, "target_fwhm_ns"));
        }
        if let Some(gate) = &self.gate {
            match gate.validate(&self.method) {
                Ok(()) => {}
                Err(e @ GateError::BadThreshold(_)) => v.report(
                    field(&field(path, "gate"), "threshold_noise"),
                    e.to_string(),
                ),
                Err(e) => v.report(field(path, "gate"), e.to_string()),
            }
        }
        if let KernelSource::Taps { taps, center } = &self.kernel {
            let kernel = field(path, "kernel");
            let finite = taps.iter().all(|t| t.is_finite());
            let sum: f64 = taps.iter().map(|&t| t as f64).sum();
            v.require(
                !taps.is_empty() && taps.len() <= self.max_taps,
                field(&kernel, "taps"),
                format!(
                    "must hold 1..={} taps (max_taps), got {}",
                    self.max_taps,
                    taps.len()
                ),
            );
            v.require(
                finite && sum > 0.0,
                field(&kernel, "taps"),
                "must be finite numbers with a positive sum",
            );
            v.require(
                *center < taps.len(),
                field(&kernel, "center"),
                format!("must index one of the {} taps, got {center}", taps.len()),
            );
        }
        if let KernelSource::FlatTarget {
            ground_return,
            outgoing,
        } = &self.kernel
        {
            let at = field(&field(path, "kernel"), "flat_target");
            // Measured here as the stage will measure it, so an unusable record is reported
            // before the run.
            if let Err(e) =
                response_from_flat_target(ground_return, outgoing, &self.method, self.max_taps)
            {
                let (name, reason) = match &e {
                    ResponseError::Outgoing(k) => ("outgoing", k.to_string()),
                    ResponseError::GroundReturn(d) => ("ground_return", d.to_string()),
                    ResponseError::Response(k) => (
                        "ground_return",
                        format!("the response measured from it is unusable: {k}"),
                    ),
                };
                v.report(field(&at, name), reason);
            }
        }
    }
}

/// Most Levenberg-Marquardt steps a decomposition may be configured for (bounds the per-pulse
/// cost).
pub(crate) const MAX_DECOMPOSE_ITERATIONS: u32 = 10_000;
/// Most residual refinement rounds.
pub(crate) const MAX_REFINE_PASSES: u32 = MAX_COMPONENTS as u32;

impl Validate for DecomposeConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        v.require(
            (1..=MAX_COMPONENTS).contains(&self.max_components),
            field(path, "max_components"),
            format!(
                "must be in 1..={MAX_COMPONENTS}, got {}",
                self.max_components
            ),
        );
        v.require(
            self.min_snr.is_finite() && self.min_snr > 0.0,
            field(path, "min_snr"),
            format!("must be a positive number, got {}", self.min_snr),
        );
        v.require(
            self.min_relative_amplitude.is_finite()
                && (0.0..1.0).contains(&self.min_relative_amplitude),
            field(path, "min_relative_amplitude"),
            format!(
                "must be a fraction in 0..1 of the segment's maximum, got {}",
                self.min_relative_amplitude
            ),
        );
        v.require(
            self.min_prominence_snr.is_finite() && self.min_prominence_snr >= 0.0,
            field(path, "min_prominence_snr"),
            format!(
                "must be a non-negative multiple of the noise level, got {}",
                self.min_prominence_snr
            ),
        );
        v.require(
            self.min_separation_bins >= 1,
            field(path, "min_separation_bins"),
            "must be at least 1 bin",
        );
        let sigma_min_ok = self.sigma_min_bins.is_finite() && self.sigma_min_bins > 0.0;
        v.require(
            sigma_min_ok,
            field(path, "sigma_min_bins"),
            format!(
                "must be a positive number of bins, got {}",
                self.sigma_min_bins
            ),
        );
        v.require(
            self.sigma_max_bins.is_finite()
                && (!sigma_min_ok || self.sigma_max_bins > self.sigma_min_bins),
            field(path, "sigma_max_bins"),
            format!(
                "must be a finite number of bins above sigma_min_bins ({}), got {}",
                self.sigma_min_bins, self.sigma_max_bins
            ),
        );
        v.require(
            (1..=MAX_DECOMPOSE_ITERATIONS).contains(&self.max_iterations),
            field(path, "max_iterations"),
            format!(
                "must be in 1..={MAX_DECOMPOSE_ITERATIONS}, got {}",
                self.max_iterations
            ),
        );
        v.require(
            self.refine_passes <= MAX_REFINE_PASSES,
            field(path, "refine_passes"),
            format!(
                "must be at most {MAX_REFINE_PASSES}, got {}",
                self.refine_passes
            ),
        );
        v.require(
            self.running_mean_bins <= 1
                || (self.running_mean_bins % 2 == 1
                    && self.running_mean_bins <= MAX_RUNNING_MEAN_BINS),
            field(path, "running_mean_bins"),
            format!(
                "must be 0 (no running mean) or an odd number of bins up to \
                 {MAX_RUNNING_MEAN_BINS}, got {}",
                self.running_mean_bins
            ),
        );
        v.require(
            (MIN_SEGMENT_SAMPLES..=MAX_SEGMENT_SAMPLES).contains(&self.max_samples),
            field(path, "max_samples"),
            format!(
                "must be in {MIN_SEGMENT_SAMPLES}..={MAX_SEGMENT_SAMPLES} samples, got {}",
                self.max_samples
            ),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stage(text: &str) -> Result<StageConfig, toml::de::Error> {
        toml::from_str(text)
    }

    #[test]
    fn stage_config_rejects_unknown_key_in_denoise() {
        let e = stage("type = \"denoise\"\nbogus = 1").unwrap_err();
        assert!(e.message().contains("unknown field `bogus`"), "{e}");
    }

    #[test]
    fn stage_config_rejects_unknown_key_in_passthrough() {
        let e = stage("type = \"passthrough\"\nbogus = 1").unwrap_err();
        assert!(e.message().contains("bogus"), "{e}");
    }

    #[test]
    fn stage_config_denoise_alone_gets_defaults() {
        assert_eq!(
            stage("type = \"denoise\"").unwrap(),
            StageConfig::Denoise(DenoiseConfig::default())
        );
        assert_eq!(
            stage("type = \"passthrough\"").unwrap(),
            StageConfig::Passthrough
        );
    }

    #[test]
    fn stage_config_rejects_unknown_and_missing_type() {
        assert!(stage("type = \"wavelet\"").is_err());
        assert!(stage("cutoff_ghz = 0.2").is_err());
    }

    #[test]
    fn stage_config_round_trips() {
        for s in [
            StageConfig::Passthrough,
            StageConfig::Denoise(DenoiseConfig::default()),
            StageConfig::Decompose(DecomposeConfig::default()),
        ] {
            let text = toml::to_string(&s).unwrap();
            assert_eq!(stage(&text).unwrap(), s, "{text}");
        }
    }

    fn check(c: &DenoiseConfig, dt_ns: Option<f64>) -> Vec<String> {
        let mut v = Validator::new(None);
        v.set_sample_interval_ns(dt_ns);
        Validate::validate(c, "s", &mut v);
        v.issues()
            .iter()
            .map(|(p, r)| format!("{p}: {r}"))
            .collect()
    }

    #[test]
    fn stage_config_deconvolve_round_trips_and_checks() {
        use crate::signal::deconvolve::{GoldConfig, RlConfig, WienerConfig};
        let s = stage("type = \"deconvolve\"\nmethod = { method = \"gold\" }").unwrap();
        assert_eq!(
            s,
            StageConfig::Deconvolve(DeconvolveConfig::with_method(MethodConfig::Gold(
                GoldConfig::default()
            )))
        );
        assert_eq!(s.kind(), "deconvolve");
        let text = toml::to_string(&s).unwrap();
        assert_eq!(stage(&text).unwrap(), s, "{text}");
        assert!(stage("type = \"deconvolve\"\nmethod = { method = \"gold\" }\nbogus = 1").is_err());
        let mut v = Validator::new(None);
        v.set_sample_interval_ns(Some(4.0));
        let bad = DeconvolveConfig {
            kernel: KernelSource::Taps {
                taps: vec![0.0, f32::NAN],
                center: 5,
            },
            max_samples: 8,
            max_taps: 0,
            ..DeconvolveConfig::with_method(MethodConfig::Wiener(WienerConfig {
                cutoff_ghz: 0.2,
                noise_scale: -1.0,
                regularisation: 0.0,
            }))
        };
        Validate::validate(&bad, "s", &mut v);
        let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            [
                "s.max_samples",
                "s.max_taps",
                "s.method.cutoff_ghz",
                "s.method.noise_scale",
                "s.method.regularisation",
                "s.kernel.taps",
                "s.kernel.taps",
                "s.kernel.center"
            ]
        );
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
            iterations: 0,
            early_stop: Some(-1.0),
            accelerate: false,
            stop_at_noise: Some(f32::NAN),
            ..RlConfig::default()
        }));
        Validate::validate(&bad, "s", &mut v);
        assert_eq!(v.issues().len(), 3);
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
            coarse_iterations: MAX_COARSE_ITERATIONS + 1,
            coarse_fwhm_samples: 0.5,
            ..RlConfig::default()
        }));
        Validate::validate(&bad, "s", &mut v);
        let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            ["s.method.coarse_iterations", "s.method.coarse_fwhm_samples"]
        );
        for fwhm in [f32::NAN, f32::INFINITY] {
            let mut v = Validator::new(None);
            let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
                coarse_iterations: 10,
                coarse_fwhm_samples: fwhm,
                ..RlConfig::default()
            }));
            Validate::validate(&bad, "s", &mut v);
            assert_eq!(v.issues().len(), 1, "{fwhm}");
        }
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::Gold(GoldConfig {
            iterations: 1,
            repetitions: 0,
            boost: f32::INFINITY,
            stop_at_noise: Some(0.0),
        }));
        Validate::validate(&bad, "s", &mut v);
        assert_eq!(v.issues().len(), 3);
        let mut v = Validator::new(None);
        Validate::validate(
            &DeconvolveConfig::with_method(MethodConfig::Wiener(WienerConfig::default())),
            "s",
            &mut v,
        );
        assert!(v.issues().is_empty());
    }

    #[test]
    fn stage_config_deconvolve_gate_is_parsed_and_checked() {
        use crate::signal::deconvolve::Gate;
        let StageConfig::Deconvolve(c) = stage(
            "type = \"deconvolve\"\nmethod = { method = \"richardson_lucy\" }\ngate = \"off\"",
        )
        .unwrap() else {
            panic!("not a deconvolve stage")
        };
        assert_eq!(c.gate, Some(Gate::Off));
        assert_eq!(c.effective_gate(), Gate::Off);
        let e = stage("type = \"deconvolve\"\nmethod = { method = \"gold\" }\ngate = { k = 1 }")
            .unwrap_err()
            .to_string();
        assert!(e.contains("threshold_noise"), "{e}");
        let issues = |text: &str| {
            let StageConfig::Deconvolve(c) = stage(text).unwrap() else {
                panic!("not a deconvolve stage")
            };
            let mut v = Validator::new(None);
            Validate::validate(&c, "s", &mut v);
            v.issues()
                .iter()
                .map(|(p, _)| p.clone())
                .collect::<Vec<_>>()
        };
        assert!(issues("type = \"deconvolve\"\nmethod = { method = \"gold\" }\ngate = { threshold_noise = 2.0 }").is_empty());
        assert!(issues("type = \"deconvolve\"\nmethod = { method = \"wiener\" }").is_empty());
        assert_eq!(
            issues(
                "type = \"deconvolve\"\nmethod = { method = \"richardson_lucy\" }\ngate = { threshold_noise = 0.0 }"
            ),
            ["s.gate.threshold_noise"]
        );
        assert_eq!(
            issues("type = \"deconvolve\"\nmethod = { method = \"nnls\" }\ngate = \"on\""),
            ["s.gate"]
        );
    }

    #[test]
    fn stage_config_flat_target_kernel_is_parsed_and_checked() {
        let text = "type = \"deconvolve\"\nmethod = { method = \"gold\" }\n\
                    kernel = { flat_target = { ground_return = [200.0, 200.0, 900.0, 400.0, 200.0], \
                    outgoing = [200.0, 200.0, 700.0, 300.0, 200.0] } }";
        let s = stage(text).unwrap();
        let StageConfig::Deconvolve(c) = &s else {
            panic!("{s:?}")
        };
        assert!(matches!(c.kernel, KernelSource::FlatTarget { .. }));
        assert_eq!(stage(&toml::to_string(&s).unwrap()).unwrap(), s);
        let mut v = Validator::new(None);
        Validate::validate(c, "s", &mut v);
        assert!(v.issues().is_empty(), "{:?}", v.issues());
        // A flat outgoing pulse (no energy above its baseline) and a NaN in the return.
        for (ground, out, path) in [
            (
                vec![200.0, 900.0, 200.0],
                vec![5.0; 4],
                "s.kernel.flat_target.outgoing",
            ),
            (
                vec![200.0, f32::NAN],
                vec![0.0, 3.0, 0.0],
                "s.kernel.flat_target.ground_return",
            ),
        ] {
            let bad = DeconvolveConfig {
                kernel: KernelSource::FlatTarget {
                    ground_return: ground,
                    outgoing: out,
                },
                ..c.clone()
            };
            let mut v = Validator::new(None);
            Validate::validate(&bad, "s", &mut v);
            let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
            assert_eq!(paths, [path], "{:?}", v.issues());
        }
    }

    #[test]
    fn denoise_config_checks_ranges_and_nyquist() {
        let ok = DenoiseConfig::default();
        assert!(check(&ok, None).is_empty());
        assert!(check(&ok, Some(1.0)).is_empty());
        // 0.2 GHz is above the 0.125 GHz Nyquist of 4 ns sampling.
        let issues = check(&ok, Some(4.0));
        assert_eq!(issues.len(), 1, "{issues:?}");
        assert!(issues[0].starts_with("s.cutoff_ghz: must be below the Nyquist"));
        // At Nyquist exactly is rejected too.
        let at = DenoiseConfig {
            cutoff_ghz: 0.5,
            ..ok.clone()
        };
        assert_eq!(check(&at, Some(1.0)).len(), 1);
        let bad = DenoiseConfig {
            cutoff_ghz: f64::NAN,
            max_samples: 8,
            pretrigger_samples: 8,
            ..ok
        };
        let issues = check(&bad, Some(1.0));
        assert_eq!(issues.len(), 3, "{issues:?}");
        assert!(issues[0].starts_with("s.cutoff_ghz: must be a positive number"));
        assert!(issues[1].starts_with("s.max_samples: must be in 16..=1048576"));
        assert!(issues[2].starts_with("s.pretrigger_samples: must be less than"));
    }

    fn check_decompose(c: &DecomposeConfig) -> Vec<String> {
        let mut v = Validator::new(None);
        Validate::validate(c, "s", &mut v);
        v.issues()
            .iter()
            .map(|(p, r)| format!("{p}: {r}"))
            .collect()
    }

    #[test]
    fn decompose_config_defaults_and_ranges() {
        assert_eq!(
            stage("type = \"decompose\"").unwrap(),
            StageConfig::Decompose(DecomposeConfig::default())
        );
        let e = stage("type = \"decompose\"\nbogus = 1").unwrap_err();
        assert!(e.message().contains("unknown field `bogus`"), "{e}");
        assert!(check_decompose(&DecomposeConfig::default()).is_empty());
        let bad = DecomposeConfig {
            max_components: 9,
            min_snr: f32::NAN,
            min_relative_amplitude: 1.5,
            min_prominence_snr: -1.0,
            min_separation_bins: 0,
            sigma_min_bins: 0.0,
            sigma_max_bins: f32::INFINITY,
            max_iterations: 0,
            refine_passes: 99,
            shoulders: false,
            max_samples: 8,
            running_mean_bins: 4,
            ..Default::default()
        };
        let issues = check_decompose(&bad);
        assert_eq!(issues.len(), 11, "{issues:?}");
        for (i, name) in [
            "max_components",
            "min_snr",
            "min_relative_amplitude",
            "min_prominence_snr",
            "min_separation_bins",
            "sigma_min_bins",
            "sigma_max_bins",
            "max_iterations",
            "refine_passes",
            "running_mean_bins",
            "max_samples",
        ]
        .iter()
        .enumerate()
        {
            assert!(issues[i].starts_with(&format!("s.{name}: ")), "{issues:?}");
        }
        for (width, ok) in [
            (0, true),
            (1, true),
            (3, true),
            (63, true),
            (2, false),
            (65, false),
        ] {
            let c = DecomposeConfig {
                running_mean_bins: width,
                ..Default::default()
            };
            assert_eq!(
                check_decompose(&c).is_empty(),
                ok,
                "running_mean_bins {width}"
            );
        }
        // The waveformlidar-compatible options parse from their names.
        let c = stage(
            "type = \"decompose\"\nbaseline = \"record_minimum_minus_one\"\n\
             running_mean_bins = 3\nstart_values = \"peak_spacing\"\n\
             peak_rule = \"not_below_left\"",
        )
        .unwrap();
        let StageConfig::Decompose(c) = c else {
            panic!("{c:?}")
        };
        assert_eq!(
            c.baseline,
            crate::signal::DecomposeBaseline::RecordMinimumMinusOne
        );
        assert_eq!(c.start_values, crate::signal::StartValues::PeakSpacing);
        assert_eq!(c.peak_rule, crate::signal::peaks::PeakRule::NotBelowLeft);
        assert_eq!(c.running_mean_bins, 3);
        assert!(check_decompose(&c).is_empty());
        let inverted = DecomposeConfig {
            sigma_min_bins: 5.0,
            sigma_max_bins: 4.0,
            ..Default::default()
        };
        let issues = check_decompose(&inverted);
        assert_eq!(issues.len(), 1, "{issues:?}");
        assert!(issues[0].starts_with("s.sigma_max_bins: "));
    }
}
