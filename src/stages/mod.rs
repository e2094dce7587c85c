//! The per-pulse stages as components: one file per stage kind, each holding everything the
//! pipeline needs of it.
//!
//! A stage file (`stages/<kind>.rs`) holds
//!
//! - its **configuration**, the `[[pipeline.stages]]` entry (`serde`, `deny_unknown_fields`,
//!   documented defaults). Where the configuration is also the parameter set of a method that
//!   is called without a pipeline (`fwlidar process`, `fwlidar tradeoff`, the forest rasters),
//!   the struct is defined beside that method in `signal/` or `forest/` and the stage file
//!   names it;
//! - its **validation** ([`Validate`]), run once when the configuration is loaded, every
//!   problem with its field path;
//! - its [`StageKind`] implementation: its kind name, a `prepare` step that takes what the run
//!   decides (the input's facts, the DEM; [`RunContext`]), a fallible `build` of one instance
//!   per worker, and what it tells the rest of the run (what it adds to a pulse, [`Products`];
//!   what its drop reasons and notes mean and which setting governs them, [`Advice`]);
//! - its [`Stage`] implementation: the adapter between the runtime's contract (emit, drop,
//!   reject) and the maths, which stays in `signal/`, `forest/` and `geo/` as plain functions
//!   and types;
//! - its tests.
//!
//! The kinds form one closed list, `stage_kinds!` below: a `#[serde(tag = "type")]` enum,
//! [`StageConfig`]. **Adding a stage is one new file here and one line in that list**
//! (`docs/architecture.md`, "Adding a stage"); nothing else in the crate names a stage kind:
//! whatever needs to know what a chain does asks the [`Chain`].

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::core::facts::SourceFacts;
use crate::core::validate::{Validate, Validator};
use crate::geo::dem::Dem;
use crate::pipeline::edge::FullPolicy;
use crate::pipeline::runner::{PipelineSpec, StageFactory, resolve_workers};
use crate::pipeline::stage::Stage;

/// Largest segment a stage may be configured for, samples.
pub const MAX_SEGMENT_SAMPLES: usize = 1_048_576;
/// Smallest segment buffer a stage may be configured for, samples.
pub const MIN_SEGMENT_SAMPLES: usize = 16;

/// What the run decides before the stages are built and a stage may take: what the opened
/// input states about itself, and the run's DEM (`[georeference] dem`).
#[derive(Clone, Copy, Debug)]
pub struct RunContext<'a> {
    /// The input's sensor, time base, CRS and time origin, as far as known when it is opened.
    pub facts: &'a SourceFacts,
    /// The run's DEM, when one is configured.
    pub dem: Option<&'a Arc<Dem>>,
    /// Whether one of the run's outputs writes the discrete returns ([`Products::returns`]):
    /// LAS or `returns.csv`. Without one, the returns serve only the QC page's waveform viewer
    /// (`pulse::Pulse::qc_sample`).
    pub writes_returns: bool,
    /// The system response learned from the run's input before it started (replay), for the
    /// stages that find echoes against it (`decompose` with `model = "response"` or `"auto"`
    /// and no response file named).
    pub learned_response: Option<&'a std::sync::Arc<crate::signal::learned_response::ResponseFile>>,
}

/// What a stage adds to the pulses that pass it: what the outputs after the chain can rely on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Products {
    /// Discrete returns ([`crate::pulse::Pulse::returns`]): the returns' outputs (LAS, CSV)
    /// have something to write.
    pub returns: bool,
    /// Calibrated backscatter ([`crate::pulse::Pulse::calibration`]): deposited intensities
    /// are calibrated, not volts.
    pub calibrated: bool,
    /// Forest structure metrics ([`crate::pulse::Pulse::metrics`]): `pulse_metrics.csv` and
    /// the metrics rasters have something to write.
    pub metrics: bool,
}

impl Products {
    /// What either produces.
    pub fn or(self, other: Products) -> Products {
        Products {
            returns: self.returns || other.returns,
            calibrated: self.calibrated || other.calibrated,
            metrics: self.metrics || other.metrics,
        }
    }
}

/// What to do about a counted drop reason or note: the setting that governs it (`None` when
/// the input itself is at fault) and a sentence or two of advice.
#[derive(Clone, Debug, PartialEq)]
pub struct Advice {
    /// The configuration key to change, e.g. `pipeline.stages[1].max_taps`.
    pub setting: Option<String>,
    /// What happened and what to do.
    pub text: String,
}

impl Advice {
    /// Advice naming `key` of the stage at `at` (`pipeline.stages[i]`).
    pub fn key(at: &str, key: &str, text: impl Into<String>) -> Advice {
        Advice {
            setting: Some(format!("{at}.{key}")),
            text: text.into(),
        }
    }
}

/// A stage that could not be built from its (validated) configuration.
#[derive(Debug, thiserror::Error)]
#[error("stage `{kind}`: {message}")]
pub struct BuildError {
    /// The stage kind.
    pub kind: &'static str,
    /// What is wrong.
    pub message: String,
}

/// A stage kind, implemented by its configuration: everything the pipeline and the reports
/// need of the stage, so that nothing else names it.
pub trait StageKind: Validate + Send + Sync {
    /// The kind name, as written in `type = "..."` and shown in telemetry and drop reasons.
    fn kind(&self) -> &'static str;

    /// Takes what the run decides before the stages are built (the input's facts, the DEM).
    /// Called once per run, before [`StageKind::build`]. Default: nothing.
    fn prepare(&mut self, _ctx: &RunContext<'_>) {}

    /// Builds one instance (each worker thread runs its own). The configuration was validated
    /// when it was loaded; an error here is what only building can find.
    fn build(&self) -> Result<Box<dyn Stage>, BuildError>;

    /// What the stage adds to the pulses. Default: nothing the outputs look for.
    fn products(&self) -> Products {
        Products::default()
    }

    /// Whether the stage changes the pulse's waveform ([`crate::pulse::Pulse::signal`]), as
    /// opposed to only reading it and adding what it finds (returns, a calibration, metrics):
    /// the stages `fwlidar tradeoff --chain` runs and times before scoring the waveform.
    /// Default: yes (a new kind is run unless it says otherwise).
    fn changes_waveform(&self) -> bool {
        true
    }

    /// What a note of this stage (a pulse passed on partly unprocessed) means, for the
    /// one-screen summary. Default: "passed on partly unprocessed".
    fn note_meaning(&self, _note: &str) -> &'static str {
        "passed on partly unprocessed"
    }

    /// The setting and advice for one of this stage's drop reasons, the stage being at `at`
    /// (`pipeline.stages[i]`); `None` leaves it to the rules every stage shares
    /// (`run::warnings`).
    fn drop_advice(&self, _reason: &str, _at: &str) -> Option<Advice> {
        None
    }

    /// The setting and advice for one of this stage's notes; `None` for the shared rule.
    fn note_advice(&self, _note: &str, _at: &str) -> Option<Advice> {
        None
    }

    /// Whether a drop reason or note is warned about from its first pulse (a limit that bit),
    /// whatever its share. Default: no.
    fn always_warns(&self, _reason: &str) -> bool {
        false
    }

    /// For a stage that finds the returns ([`Products::returns`]) and found none in any pulse:
    /// the rest of the sentence "the `<kind>` stage found no return in any of the N pulses out"
    /// and the setting to change. Default: none.
    fn no_returns_advice(&self, _at: &str) -> Option<Advice> {
        None
    }

    /// The key of this stage that asks for the run's DEM (`[georeference] dem`), when it does:
    /// a configuration without a DEM is then refused at that key. Default: none.
    fn needs_dem(&self) -> Option<&'static str> {
        None
    }

    /// Lines of `fwlidar validate`'s statement of the stage's worst-case cost. Default: none.
    fn cost_lines(&self) -> Vec<String> {
        Vec::new()
    }
}

/// Declares the closed list of stage kinds: `module => Variant(Config)`, one line each. It
/// declares each module (`stages/<module>.rs`), the [`StageConfig`] enum (serde tag `type`,
/// the variant's name in snake case) and the dispatch to each kind's [`StageKind`].
macro_rules! stage_kinds {
    ($( $(#[$doc:meta])* $module:ident => $variant:ident($config:ty) ),* $(,)?) => {
        $( pub mod $module; )*

        /// One entry of `[[pipeline.stages]]`, selected by its `type` key.
        #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
        #[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
        pub enum StageConfig {
            $( $(#[$doc])* $variant($config), )*
        }

        impl StageConfig {
            /// The stage's [`StageKind`].
            pub fn as_kind(&self) -> &dyn StageKind {
                match self { $( StageConfig::$variant(c) => c, )* }
            }

            /// The stage's [`StageKind`], to prepare it.
            pub fn as_kind_mut(&mut self) -> &mut dyn StageKind {
                match self { $( StageConfig::$variant(c) => c, )* }
            }

            /// Every kind with its default configuration, in the list's order.
            pub fn defaults() -> Vec<StageConfig> {
                vec![ $( StageConfig::$variant(<$config>::default()), )* ]
            }
        }
    };
}

stage_kinds! {
    /// Emits every pulse unchanged (runtime overhead measurement).
    passthrough => Passthrough(passthrough::PassthroughConfig),
    /// FFT low-pass noise reduction.
    denoise => Denoise(crate::signal::denoise::DenoiseConfig),
    /// Deconvolution of the return segments (Richardson-Lucy, Gold, Wiener, NNLS).
    deconvolve => Deconvolve(deconvolve::DeconvolveConfig),
    /// Gaussian decomposition of the return segments into discrete returns.
    decompose => Decompose(crate::signal::decompose::DecomposeConfig),
    /// Radiometric calibration: volts, range, outgoing energy, system constant.
    calibrate => Calibrate(crate::signal::calibrate::CalibrateConfig),
    /// Forest structure metrics per pulse.
    metrics => Metrics(crate::forest::pulse_metrics::MetricsConfig),
}

impl StageConfig {
    /// The kind name, as written in `type = "..."`.
    pub fn kind(&self) -> &'static str {
        self.as_kind().kind()
    }

    /// Builds a fresh stage instance (one per worker thread).
    pub fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        self.as_kind().build()
    }
}

impl Validate for StageConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        self.as_kind().validate(path, v);
    }
}

/// The configured stages, prepared for one run and built once to check that they can be: what
/// the runner runs, and what the rest of the run asks about the chain.
#[derive(Clone, Debug)]
pub struct Chain {
    stages: Vec<StageConfig>,
}

impl Chain {
    /// Prepares each stage for the run ([`StageKind::prepare`]) and builds it once, so that a
    /// stage that cannot be built is reported before the run starts.
    pub fn prepare(stages: &[StageConfig], ctx: &RunContext<'_>) -> Result<Chain, BuildError> {
        let mut stages = stages.to_vec();
        for s in &mut stages {
            s.as_kind_mut().prepare(ctx);
        }
        for s in &stages {
            s.build()?;
        }
        Ok(Chain { stages })
    }

    /// The prepared stage configurations, in order.
    pub fn stages(&self) -> &[StageConfig] {
        &self.stages
    }

    /// The kind names, in order.
    pub fn names(&self) -> Vec<&'static str> {
        self.stages.iter().map(|s| s.kind()).collect()
    }

    /// What the chain adds to the pulses, all stages together.
    pub fn products(&self) -> Products {
        self.stages
            .iter()
            .fold(Products::default(), |p, s| p.or(s.as_kind().products()))
    }

    /// The configuration of the first `metrics` stage (its profile bins shape
    /// `pulse_metrics.csv`), if the chain has one.
    pub fn metrics_config(&self) -> Option<&crate::forest::pulse_metrics::MetricsConfig> {
        self.stages.iter().find_map(|s| match s {
            StageConfig::Metrics(m) => Some(m),
            _ => None,
        })
    }

    /// The stage at position `i` (as `summary.json`'s `stages[i]`), if any.
    pub fn stage(&self, i: usize) -> Option<&dyn StageKind> {
        self.stages.get(i).map(|s| s.as_kind())
    }

    /// Builds each worker's chain (called once per worker thread).
    pub fn factory(&self) -> StageFactory {
        let stages = Arc::new(self.stages.clone());
        Arc::new(move || {
            stages
                .iter()
                // Each was built once by `prepare`, from the same configuration.
                .map(|s| s.build().expect("a stage built once builds again"))
                .collect()
        })
    }

    /// How to run the chain: `workers` (0: one per core, [`resolve_workers`]), the edges'
    /// capacity and the input edge's policy.
    pub fn spec(
        &self,
        workers: usize,
        queue_capacity: usize,
        input_policy: FullPolicy,
    ) -> PipelineSpec {
        PipelineSpec {
            workers: resolve_workers(workers),
            queue_capacity,
            input_policy,
            stages: self.factory(),
            stage_names: self.names(),
        }
    }
}

/// Whether a run of `stages` must learn the system response from its input first: a
/// `decompose` stage with `model = "response"` or `"auto"` and no response file, or a
/// `deconvolve` stage with `kernel = "learned"`.
pub fn wants_learned_response(stages: &[StageConfig]) -> bool {
    stages.iter().any(|s| match s {
        StageConfig::Decompose(d) => d.wants_learned_response(),
        StageConfig::Deconvolve(d) => {
            d.kernel == deconvolve::KernelSource::Learned && d.learned.is_none()
        }
        _ => false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::testing::{SyntheticSource, run_stage};

    /// Every kind builds from its default configuration, its name is its `type` key, its
    /// default passes validation, and it honours the stage contract on a pulse.
    #[test]
    fn every_stage_kind_builds_from_its_default_config() {
        let defaults = StageConfig::defaults();
        assert!(defaults.len() >= 6, "{defaults:?}");
        let facts = SourceFacts::default();
        let chain = Chain::prepare(
            &defaults,
            &RunContext {
                facts: &facts,
                dem: None,
                writes_returns: true,
                learned_response: None,
            },
        )
        .unwrap();
        for (config, name) in defaults.iter().zip(chain.names()) {
            let text = toml::to_string(config).unwrap();
            assert!(
                text.contains(&format!("type = \"{name}\"")),
                "{name}: {text}"
            );
            let back: StageConfig = toml::from_str(&text).unwrap();
            assert_eq!(&back, config, "{name} round-trips through TOML");
            let mut v = Validator::new(None);
            config.validate("s", &mut v);
            assert!(v.issues().is_empty(), "{name}: {:?}", v.issues());
            let mut stage = config.build().unwrap();
            assert_eq!(stage.name(), name);
            let pulses = SyntheticSource::pulses(2);
            let run = run_stage(stage.as_mut(), pulses).unwrap();
            assert_eq!(run.emitted.len() as u64 + run.dropped.total(), 2, "{name}");
        }
        // Every kind is in the list once.
        let mut names = chain.names();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), defaults.len());
    }

    #[test]
    fn the_chain_says_what_it_produces() {
        let facts = SourceFacts::default();
        let ctx = RunContext {
            facts: &facts,
            dem: None,
            writes_returns: true,
            learned_response: None,
        };
        let parse = |text: &str| -> Vec<StageConfig> {
            #[derive(Deserialize)]
            struct L {
                stages: Vec<StageConfig>,
            }
            toml::from_str::<L>(text).unwrap().stages
        };
        let chain = Chain::prepare(
            &parse("[[stages]]\ntype = \"denoise\"\n[[stages]]\ntype = \"decompose\"\n"),
            &ctx,
        )
        .unwrap();
        assert_eq!(
            chain.products(),
            Products {
                returns: true,
                ..Products::default()
            }
        );
        let chain = Chain::prepare(&StageConfig::defaults(), &ctx).unwrap();
        assert_eq!(
            chain.products(),
            Products {
                returns: true,
                calibrated: true,
                metrics: true
            }
        );
    }
}
