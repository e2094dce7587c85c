//! The `decompose` stage: the Gaussian decomposition of every return segment of a denoised pulse
//! into discrete returns ([`crate::signal::decompose`]). Its configuration,
//! [`DecomposeConfig`], is the method's parameter set (also used by `fwlidar process`), defined
//! beside the method.

use super::{Advice, BuildError, MAX_SEGMENT_SAMPLES, MIN_SEGMENT_SAMPLES, Products, StageKind};
use crate::core::validate::{Validate, Validator, field};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;
pub use crate::signal::decompose::DecomposeConfig;
use crate::signal::decompose::{Decompose, MAX_RUNNING_MEAN_BINS};
use crate::signal::gauss_fit::MAX_COMPONENTS;

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

impl StageKind for DecomposeConfig {
    fn kind(&self) -> &'static str {
        "decompose"
    }

    fn changes_waveform(&self) -> bool {
        false
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        Ok(Box::new(Decompose::new(self.clone())))
    }

    fn products(&self) -> Products {
        Products {
            returns: true,
            ..Products::default()
        }
    }

    fn no_returns_advice(&self, at: &str) -> Option<Advice> {
        Some(Advice::key(
            at,
            "min_snr",
            " (no peak min_snr noise levels above the baseline); lower min_snr, or check the \
             stages before it",
        ))
    }

    fn cost_lines(&self) -> Vec<String> {
        vec![format!(
            "decompose: at most {} Levenberg-Marquardt steps and {} components per return \
             segment of <= {} samples",
            self.max_iterations, self.max_components, self.max_samples
        )]
    }
}

impl Stage for Decompose {
    fn name(&self) -> &'static str {
        "decompose"
    }

    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        let verdict = self.decompose_pulse(&mut pulse);
        out.give(pulse, verdict);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::StageConfig;

    fn stage(text: &str) -> Result<StageConfig, toml::de::Error> {
        toml::from_str(text)
    }

    #[test]
    fn stage_is_registered() {
        let c = stage("type = \"decompose\"\nmin_snr = 4.0").unwrap();
        assert_eq!(c.kind(), "decompose");
        assert_eq!(c.build().unwrap().name(), "decompose");
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
