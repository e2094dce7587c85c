//! The `calibrate` stage: radiometric calibration of every pulse ([`crate::signal::calibrate`]):
//! volts, range, outgoing energy, system constant. Its configuration, [`CalibrateConfig`], is
//! the method's parameter set, defined beside the method; what it leaves to the input (the
//! system constant and the time origin) is filled from the input's facts when the run starts
//! ([`StageKind::prepare`]).

use super::{Advice, BuildError, Products, RunContext, StageKind};
use crate::core::validate::{Validate, Validator, field};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;
use crate::signal::calibrate::Calibrate;
pub use crate::signal::calibrate::CalibrateConfig;

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

impl StageKind for CalibrateConfig {
    fn kind(&self) -> &'static str {
        "calibrate"
    }

    fn changes_waveform(&self) -> bool {
        false
    }

    /// Fills the system constant and the time origin the configuration leaves to the input
    /// ([`CalibrateConfig::resolve_from_input`]) and logs what was decided.
    fn prepare(&mut self, ctx: &RunContext<'_>) {
        self.resolve_from_input(ctx.facts);
        tracing::info!(
            "calibrate: system constant {} (from the input's sensor unless configured); a \
             pulse's time 0 is {}",
            self.system_constant_value.unwrap_or(1.0),
            if self.t0_is_emission.unwrap_or(false) {
                "its emission"
            } else {
                "its first sample, not its emission"
            }
        );
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        Calibrate::try_new(self.clone())
            .map(|c| Box::new(c) as Box<dyn Stage>)
            .map_err(|e| BuildError {
                kind: "calibrate",
                message: e.to_string(),
            })
    }

    fn products(&self) -> Products {
        Products {
            calibrated: true,
            ..Products::default()
        }
    }

    fn note_meaning(&self, note: &str) -> &'static str {
        match note {
            "range_unknown" => "calibrated without the range factor",
            "return_before_emission" => "a return at or before the emission: no backscatter",
            _ => "calibrated without the energy factor",
        }
    }

    fn drop_advice(&self, reason: &str, at: &str) -> Option<Advice> {
        match reason {
            "range_unknown" => Some(Advice::key(
                at,
                "range_unknown",
                "the pulses' emission time is unknown (no outgoing segment, t0 not the \
                 emission); set range_unknown = \"unscaled\", or t0_is_emission = true if it is",
            )),
            "no_outgoing" | "bad_outgoing_energy" => Some(Advice::key(
                at,
                "energy_unknown",
                "the pulses' outgoing energy is unknown; set energy_unknown = \"unscaled\"",
            )),
            _ => None,
        }
    }

    fn note_advice(&self, note: &str, at: &str) -> Option<Advice> {
        match note {
            "range_unknown" => Some(Advice::key(
                at,
                "t0_is_emission",
                "the range factor was left out: the emission time is unknown (no outgoing \
                 segment); set t0_is_emission = true if the input's t0 is the emission",
            )),
            "no_outgoing" | "bad_outgoing_energy" => Some(Advice::key(
                at,
                "energy",
                "the energy factor was left out: the outgoing energy is unknown; set energy = \
                 false to say so",
            )),
            "return_before_emission" => Some(Advice::key(
                at,
                "t0_is_emission",
                "returns lie at or before the emission and got no backscatter; check \
                 t0_is_emission for this input",
            )),
            _ => None,
        }
    }
}

impl Stage for Calibrate {
    fn name(&self) -> &'static str {
        "calibrate"
    }

    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        let verdict = self.calibrate(&mut pulse);
        out.give(pulse, verdict);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::StageConfig;

    #[test]
    fn the_configuration_is_parsed_and_checked_with_field_paths() {
        let s: StageConfig = toml::from_str(
            "type = \"calibrate\"\nrange = false\nsystem_constant_value = 0.5\n\
             range_unknown = \"drop\"\nenergy_unknown = \"unscaled\"",
        )
        .unwrap();
        let StageConfig::Calibrate(c) = &s else {
            panic!("{s:?}")
        };
        assert!(!c.range && c.energy && c.volts && c.system_constant);
        assert_eq!(c.system_constant_value, Some(0.5));
        assert_eq!(c.range_unknown, crate::signal::calibrate::UnknownPolicy::Drop);
        assert_eq!(s.kind(), "calibrate");
        assert_eq!(
            toml::from_str::<StageConfig>(&toml::to_string(&s).unwrap()).unwrap(),
            s
        );
        assert!(toml::from_str::<StageConfig>("type = \"calibrate\"\nbogus = 1").is_err());
        assert!(toml::from_str::<StageConfig>("type = \"calibrate\"\nrange_unknown = \"x\"").is_err());
        let bad = CalibrateConfig {
            reference_range_m: 0.0,
            refractive_index: 0.9,
            ..Default::default()
        };
        let mut v = Validator::new(None);
        Validate::validate(&bad, "s", &mut v);
        let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(paths, ["s.reference_range_m", "s.refractive_index"]);
        assert!(StageConfig::Calibrate(bad).build().is_err());
    }
}
