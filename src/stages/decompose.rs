//! The `decompose` stage: the Gaussian decomposition of every return segment of a denoised pulse
//! into discrete returns ([`crate::signal::decompose`]). Its configuration,
//! [`DecomposeConfig`], is the method's parameter set (also used by `fwlidar process`), defined
//! beside the method.
//!
//! **Which pulses** (`pulses`, [`DecomposePulses`]): the returns are read by the returns'
//! outputs (LAS, `returns.csv`) and by the QC page's waveform viewer, which shows the returns of
//! the pulses the pipeline's source marks for it (`Pulse::qc_sample`, about four a second on
//! board). With the default `"auto"`, [`StageKind::prepare`] decides from the run: every pulse
//! when one of its outputs writes the returns ([`RunContext::writes_returns`]), otherwise only
//! the marked ones (`"qc_sampled"`): on board without LAS, the ~5-10 µs fit of every other
//! pulse is saved. The pulses left out pass the same checks (a pulse the decomposition would
//! drop is dropped all the same) and go on without returns.

use super::{
    Advice, BuildError, MAX_SEGMENT_SAMPLES, MIN_SEGMENT_SAMPLES, Products, RunContext, StageKind,
};
use crate::core::validate::{Validate, Validator, field};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;
pub use crate::signal::decompose::{DecomposeConfig, DecomposePulses, EchoModel};
use crate::signal::decompose::{Decompose, MAX_RUNNING_MEAN_BINS};
use crate::signal::gauss_fit::MAX_COMPONENTS;

/// Most Levenberg-Marquardt steps a decomposition may be configured for (bounds the per-pulse
/// cost).
pub(crate) const MAX_DECOMPOSE_ITERATIONS: u32 = 10_000;
/// Most residual refinement rounds.
pub(crate) const MAX_REFINE_PASSES: u32 = MAX_COMPONENTS as u32;

impl Validate for DecomposeConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        if let Some(file) = &self.response {
            v.require(
                file.is_file(),
                field(path, "response"),
                format!(
                    "no response file {} (paths are from the working folder; `fwlidar response \
                     learn INPUT --out FILE` writes one)",
                    file.display()
                ),
            );
        }
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

    fn prepare(&mut self, ctx: &RunContext<'_>) {
        let asked = self.model;
        self.resolve_response(ctx.learned_response);
        if asked != EchoModel::Gaussian {
            match (&self.model, &self.learned) {
                (EchoModel::Response, Some(r)) => tracing::info!(
                    "decompose: echoes are found against the system response ({}), not as free \
                     Gaussians",
                    response_words(r)
                ),
                (EchoModel::Gaussian, Some(r)) => tracing::info!(
                    "decompose: the system response is Gaussian ({}): free Gaussians are fitted",
                    response_words(r)
                ),
                (EchoModel::Gaussian, None) => tracing::info!(
                    "decompose: no system response could be learned from the input: free \
                     Gaussians are fitted"
                ),
                _ => {}
            }
        }
        if self.pulses == DecomposePulses::Auto {
            self.pulses = if ctx.writes_returns {
                DecomposePulses::All
            } else {
                DecomposePulses::QcSampled
            };
            tracing::info!(
                "{}",
                if ctx.writes_returns {
                    "decompose: every pulse is decomposed into returns (an output writes them)"
                } else {
                    "decompose: only the pulses the QC waveform viewer shows are decomposed (no \
                     output writes returns)"
                }
            );
        }
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        self.checked_response().map_err(|message| BuildError {
            kind: "decompose",
            message,
        })?;
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
        // `auto` is decided per run (`fwlidar validate` does not know the run's outputs).
        let which = match self.pulses {
            DecomposePulses::QcSampled => ", only for the QC waveform viewer's ~4 pulses a second",
            DecomposePulses::Auto | DecomposePulses::All => "",
        };
        vec![format!(
            "decompose: at most {} Levenberg-Marquardt steps and {} components per return \
             segment of <= {} samples{which}",
            self.max_iterations, self.max_components, self.max_samples
        )]
    }
}

/// A response in a few words: its channels' widths and what it was learned from.
fn response_words(r: &crate::signal::learned_response::ResponseFile) -> String {
    let widths: Vec<String> = r
        .responses
        .iter()
        .map(|x| {
            format!(
                "channel {}: FWHM {:.1} ns from {} echoes",
                x.channel,
                f64::from(x.fwhm_samples) * x.sample_ns,
                x.echoes
            )
        })
        .collect();
    format!("{}; {}", widths.join(", "), r.learned_from)
}

impl Stage for Decompose {
    fn name(&self) -> &'static str {
        "decompose"
    }

    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        let verdict = if self.wants(&pulse) {
            self.decompose_pulse(&mut pulse)
        } else {
            self.pass_pulse(&mut pulse)
        };
        out.give(pulse, verdict);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::facts::SourceFacts;
    use crate::pipeline::testing::run_stage;
    use crate::stages::StageConfig;

    /// `pulses = "auto"` decided by the run's outputs: every pulse when one writes the
    /// returns, else the QC viewer's marked pulses alone.
    #[test]
    fn auto_decomposes_every_pulse_only_when_an_output_writes_the_returns() {
        let facts = SourceFacts::default();
        let prepared = |pulses: DecomposePulses, writes_returns: bool| {
            let mut c = DecomposeConfig {
                pulses,
                ..Default::default()
            };
            c.prepare(&RunContext {
                facts: &facts,
                dem: None,
                writes_returns,
                learned_response: None,
            });
            c.pulses
        };
        assert_eq!(DecomposeConfig::default().pulses, DecomposePulses::Auto);
        assert_eq!(prepared(DecomposePulses::Auto, true), DecomposePulses::All);
        assert_eq!(
            prepared(DecomposePulses::Auto, false),
            DecomposePulses::QcSampled
        );
        // An explicit choice stays.
        assert_eq!(prepared(DecomposePulses::All, false), DecomposePulses::All);
        // The key parses; `auto` is not written back.
        let c = stage("type = \"decompose\"\npulses = \"qc_sampled\"").unwrap();
        let StageConfig::Decompose(d) = &c else {
            panic!("{c:?}")
        };
        assert_eq!(d.pulses, DecomposePulses::QcSampled);
        assert!(toml::to_string(&c).unwrap().contains("pulses = \"qc_sampled\""));
        let text = toml::to_string(&StageConfig::Decompose(DecomposeConfig::default())).unwrap();
        assert!(!text.contains("pulses"), "{text}");
        assert!(stage("type = \"decompose\"\npulses = \"some\"").is_err());
    }

    /// With `qc_sampled`, the marked pulses get their returns, the others pass on without
    /// them (after the same checks); with `all`, every pulse gets them.
    #[test]
    fn qc_sampled_decomposes_the_marked_pulses_alone() {
        // Denoised pulses with one echo each (signal in volts, raw counts alongside).
        let pulses: Vec<Pulse> = (0..9)
            .map(|i| {
                let mut p = Pulse::default();
                p.push_segment(crate::pulse::SegmentKind::Return, 0, 0.0, [0u16; 128]);
                p.signal = (0..128)
                    .map(|k| (-((k as f32 - 60.0 - i as f32) / 3.0).powi(2) / 2.0).exp())
                    .collect();
                p.noise.noise_v = 0.01;
                p.qc_sample = i % 3 == 0;
                p
            })
            .collect();
        let run = |which: DecomposePulses| {
            let mut d = DecomposeConfig {
                pulses: which,
                ..Default::default()
            }
            .build()
            .unwrap();
            run_stage(d.as_mut(), pulses.clone()).unwrap()
        };
        let all = run(DecomposePulses::All);
        assert_eq!(all.emitted.len(), 9);
        assert!(all.emitted.iter().all(|p| p.returns.len() == 1));
        let sampled = run(DecomposePulses::QcSampled);
        assert_eq!(sampled.emitted.len(), 9);
        for (a, s) in all.emitted.iter().zip(&sampled.emitted) {
            if s.qc_sample {
                let fit = |p: &Pulse| -> Vec<[f32; 3]> {
                    p.returns
                        .iter()
                        .map(|r| [r.position_bins, r.amplitude, r.sigma_bins])
                        .collect()
                };
                assert_eq!(fit(a), fit(s), "the same returns for a marked pulse");
            } else {
                assert!(s.returns.is_empty());
            }
        }
        // A pulse the decomposition cannot use is refused all the same.
        let mut undenoised = pulses[1].clone();
        undenoised.signal.clear();
        let mut d = DecomposeConfig {
            pulses: DecomposePulses::QcSampled,
            ..Default::default()
        }
        .build()
        .unwrap();
        let r = run_stage(d.as_mut(), [undenoised]).unwrap();
        assert_eq!(r.dropped.get("not_denoised"), 1);
    }

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
