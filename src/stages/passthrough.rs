//! The `passthrough` stage: emits every pulse unchanged. It measures the runtime's own overhead
//! and is the simplest example of the stage contract (and of a stage file).

use serde::{Deserialize, Serialize};

use super::{BuildError, StageKind};
use crate::core::validate::{Validate, Validator};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;

/// Configuration of the `passthrough` stage: it has no keys (`type = "passthrough"` alone).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PassthroughConfig {}

impl Validate for PassthroughConfig {
    fn validate(&self, _path: &str, _v: &mut Validator) {}
}

impl StageKind for PassthroughConfig {
    fn kind(&self) -> &'static str {
        "passthrough"
    }

    fn changes_waveform(&self) -> bool {
        false
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        Ok(Box::new(Passthrough))
    }
}

/// The identity stage: emits every pulse unchanged. Used to measure the runtime's own overhead
/// and as the simplest example of the contract.
#[derive(Debug, Default, Clone, Copy)]
pub struct Passthrough;

impl Stage for Passthrough {
    fn name(&self) -> &'static str {
        "passthrough"
    }

    fn process(&mut self, pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        out.emit(pulse);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::StageConfig;

    #[test]
    fn passthrough_takes_no_keys() {
        let s: StageConfig = toml::from_str("type = \"passthrough\"").unwrap();
        assert_eq!(s, StageConfig::Passthrough(PassthroughConfig {}));
        let e = toml::from_str::<StageConfig>("type = \"passthrough\"\nbogus = 1").unwrap_err();
        assert!(e.message().contains("bogus"), "{e}");
        assert_eq!(toml::to_string(&s).unwrap().trim(), "type = \"passthrough\"");
    }
}
