//! The `denoise` stage: each pulse through the noise reduction of [`crate::signal::denoise`]
//! (counts to volts, baseline and noise level, the seed's level shift and low-pass). Its
//! configuration, [`DenoiseConfig`], is the method's parameter set (also used by `fwlidar
//! process` and `fwlidar tradeoff`), defined beside the method.

use super::{Advice, BuildError, MAX_SEGMENT_SAMPLES, MIN_SEGMENT_SAMPLES, StageKind};
use crate::core::validate::{Validate, Validator, field};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;
pub use crate::signal::denoise::DenoiseConfig;
use crate::signal::denoise::Denoise;

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

impl StageKind for DenoiseConfig {
    fn kind(&self) -> &'static str {
        "denoise"
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        Denoise::try_new(self.clone())
            .map(|d| Box::new(d) as Box<dyn Stage>)
            .map_err(|e| BuildError {
                kind: "denoise",
                message: e.to_string(),
            })
    }

    fn drop_advice(&self, reason: &str, at: &str) -> Option<Advice> {
        match reason {
            "cutoff_above_nyquist" => Some(Advice::key(
                at,
                "cutoff_ghz",
                "the low-pass cut-off is not below the Nyquist frequency of these pulses' \
                 sampling (1 / (2 x sample interval)); lower cutoff_ghz",
            )),
            "no_segments" => Some(Advice {
                setting: None,
                text: "the pulses carry no waveform segment".into(),
            }),
            _ => None,
        }
    }
}

impl Stage for Denoise {
    fn name(&self) -> &'static str {
        "denoise"
    }

    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        let verdict = self.denoise_pulse(&mut pulse);
        out.give(pulse, verdict);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
