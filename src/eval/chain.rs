//! A run configuration's per-pulse chain as `fwlidar tradeoff --chain FILE` scores it: the
//! `[[pipeline.stages]]` of the file, built by the stages' own code ([`StageConfig`],
//! [`StageKind`](crate::stages::StageKind), [`Chain`]) and run through the [`Stage`] contract
//! on a [`Pulse`] made from each simulated waveform, as replay would run them.
//!
//! **What runs**: every stage that changes the waveform
//! ([`StageKind::changes_waveform`](crate::stages::StageKind::changes_waveform): denoise,
//! deconvolve, any future kind unless it says otherwise), in the file's order; the stages that
//! only add what they find (decompose, calibrate, metrics) and passthrough are left out, since
//! the score is of the waveform the chain leaves ([`ChainSpec::skipped`] names them).
//!
//! **The pulse**: as a 16-bit digitizer records it. Two segments: the outgoing pulse (the
//! sweep's system pulse, noise-free, its peak at the received waveform's largest value, between
//! [`OUTGOING_PAD`] zero samples on each side so the denoise stage finds its baseline) and the
//! return (the simulated received waveform). Both are quantised to counts with one gain and
//! offset per pulse that map the pulse's range onto [`FULL_SCALE_COUNTS`] counts: the
//! quantisation error is at most 1/120 000 of that range, far below the sweep's noise (a
//! built-in setting sees the same waveform unquantised). A `kernel = "outgoing"` deconvolution
//! then uses the outgoing pulse after the denoise stage, cut to its support, as replay does;
//! the built-in settings deconvolve by the exact system pulse.
//!
//! **Timing** as the built-in settings: the pulse is loaded ([`ChainRunner::load`]) and its
//! waveform read back ([`ChainRunner::unload`]) outside the timed call ([`ChainRunner::run`]);
//! the pulse and every buffer are reused from pulse to pulse, so nothing is allocated there
//! once the stages are warm (their own contract).

use std::path::{Path, PathBuf};

use crate::config::load_run_config;
use crate::core::config_error::ConfigErrors;
use crate::core::facts::SourceFacts;
use crate::pipeline::stage::{DropCounts, Emitter, Stage, StageError};
use crate::pulse::{Pulse, PulsePool, SegmentKind};
use crate::signal::kernel::Kernel;
use crate::stages::{Chain, RunContext, StageConfig};

/// Counts the simulated digitizer spans from the pulse's lowest to its highest value.
pub const FULL_SCALE_COUNTS: f32 = 60_000.0;
/// Zero samples on each side of the outgoing pulse in its segment (more than the denoise
/// stage's default 8 pre-trigger samples, and a quarter of the segment at the narrowest pulse).
pub const OUTGOING_PAD: usize = 16;
/// Drop reason of a pulse a stage kept to itself (a stage that emits only at the end of the
/// stream, which a per-pulse score cannot use).
pub const HELD_BY_STAGE: &str = "held_by_stage";

/// Why a chain could not be taken from a run configuration.
#[derive(Debug, thiserror::Error)]
pub enum ChainError {
    /// The file is not a valid run configuration (each problem with its field and line).
    #[error("{0}")]
    Config(#[from] ConfigErrors),
    /// The chain cannot be scored or a stage cannot be built.
    #[error("{}: {field}: {message}", file.display())]
    Chain {
        /// The run configuration.
        file: PathBuf,
        /// The field at fault, e.g. `pipeline.stages[1]`.
        field: String,
        /// What is wrong.
        message: String,
    },
}

/// A run configuration's chain, ready to be scored: its name and the prepared stages that
/// change the waveform.
#[derive(Clone, Debug)]
pub struct ChainSpec {
    /// The file's stem: the setting's method is `chain:<name>`.
    pub name: String,
    /// The run configuration it came from.
    pub file: PathBuf,
    /// The stages run, prepared and built once (the configuration's order).
    chain: Chain,
    /// The kinds of the stages left out (they do not change the waveform), in order.
    pub skipped: Vec<&'static str>,
}

impl PartialEq for ChainSpec {
    fn eq(&self, other: &Self) -> bool {
        self.name == other.name
            && self.file == other.file
            && self.chain.stages() == other.chain.stages()
            && self.skipped == other.skipped
    }
}

impl ChainSpec {
    /// The chain of the run configuration at `path` (checked as replay checks it).
    pub fn load(path: &Path) -> Result<ChainSpec, ChainError> {
        let config = load_run_config(Some(path))?;
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "chain".into());
        ChainSpec::from_stages(name, path, &config.pipeline.stages)
    }

    /// The chain of `stages` (a configuration's `pipeline.stages`, from `file`), named `name`:
    /// the stages that change the waveform are prepared for a run without input facts, DEM or
    /// outputs and built once; an error names the stage by its index in `stages`.
    pub fn from_stages(
        name: impl Into<String>,
        file: &Path,
        stages: &[StageConfig],
    ) -> Result<ChainSpec, ChainError> {
        let fail = |field: String, message: String| ChainError::Chain {
            file: file.to_path_buf(),
            field,
            message,
        };
        let facts = SourceFacts::default();
        let ctx = RunContext {
            facts: &facts,
            dem: None,
            writes_returns: false,
            learned_response: None,
        };
        let mut kept = Vec::new();
        let mut skipped = Vec::new();
        for (i, s) in stages.iter().enumerate() {
            if !s.as_kind().changes_waveform() {
                skipped.push(s.kind());
                continue;
            }
            let mut s = s.clone();
            s.as_kind_mut().prepare(&ctx);
            s.build()
                .map_err(|e| fail(format!("pipeline.stages[{i}]"), e.to_string()))?;
            kept.push(s);
        }
        if kept.is_empty() {
            return Err(fail(
                "pipeline.stages".into(),
                format!(
                    "no stage changes the waveform (stages: {}); a chain to score needs a \
                     denoise stage at least",
                    stages
                        .iter()
                        .map(|s| s.kind())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            ));
        }
        let chain = Chain::prepare(&kept, &ctx)
            .map_err(|e| fail("pipeline.stages".into(), e.to_string()))?;
        Ok(ChainSpec {
            name: name.into(),
            file: file.to_path_buf(),
            chain,
            skipped,
        })
    }

    /// The setting's method name: `chain:<name>`.
    pub fn method(&self) -> String {
        format!("chain:{}", self.name)
    }

    /// The kinds of the stages run, in order.
    pub fn stage_names(&self) -> Vec<&'static str> {
        self.chain.names()
    }

    /// A fresh instance of the stages (the runner's factory, as each worker builds its own).
    pub fn runner(&self) -> ChainRunner {
        ChainRunner {
            stages: (self.chain.factory())(),
            pool: PulsePool::new(4),
            pulse: None,
            cur: Vec::with_capacity(4),
            next: Vec::with_capacity(4),
            dropped: DropCounts::default(),
            errors: 0,
        }
    }
}

/// The stages of one [`ChainSpec`] with the pulse they work on (see the module documentation).
pub struct ChainRunner {
    stages: Vec<Box<dyn Stage>>,
    pool: PulsePool,
    /// The loaded pulse; after [`ChainRunner::run`], what the chain emitted (`None`: dropped).
    pulse: Option<Box<Pulse>>,
    cur: Vec<Box<Pulse>>,
    next: Vec<Box<Pulse>>,
    dropped: DropCounts,
    errors: u64,
}

/// Index of the return segment in a loaded pulse (the outgoing one is first).
const RETURN_SEGMENT: usize = 1;

impl ChainRunner {
    /// Loads a pulse: `received` (the return waveform, signal units) and the outgoing pulse
    /// `outgoing` (the sweep's system pulse: its taps, any scale), sampled every `sample_ns` ns,
    /// as a 16-bit digitizer records them. Reuses the pulse's buffers.
    pub fn load(&mut self, received: &[f32], outgoing: &Kernel, sample_ns: f64) {
        let mut p = self.pulse.take().unwrap_or_else(|| self.pool.take());
        p.reset();
        let (lo, hi) = received
            .iter()
            .fold((0.0f32, 0.0f32), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        let tap_max = outgoing.taps.iter().fold(0.0f32, |m, &v| m.max(v));
        let scale = if tap_max > 0.0 { hi / tap_max } else { 0.0 };
        let gain = if hi > lo {
            (hi - lo) / FULL_SCALE_COUNTS
        } else {
            1.0 / FULL_SCALE_COUNTS
        };
        // Two counts of margin below the lowest value.
        let offset = lo - 2.0 * gain;
        let count = |v: f32| ((v - offset) / gain).round().clamp(0.0, u16::MAX as f32) as u16;
        let pad = std::iter::repeat_n(0.0f32, OUTGOING_PAD);
        let start_ns = -((OUTGOING_PAD + outgoing.center) as f64) * sample_ns;
        let samples = pad
            .clone()
            .chain(outgoing.taps.iter().map(|&t| t * scale))
            .chain(pad);
        p.push_segment(SegmentKind::Outgoing, 0, start_ns, samples.map(count));
        p.push_segment(
            SegmentKind::Return,
            0,
            0.0,
            received.iter().map(|&v| count(v)),
        );
        p.sample_ns = sample_ns;
        p.gain_v_per_dn = gain;
        p.offset_v = offset;
        p.bits = 16;
        self.pulse = Some(p);
    }

    /// Runs every stage, in order, on the loaded pulse (what is timed). A pulse a stage drops
    /// or rejects is counted by reason ([`ChainRunner::dropped`]); an `Err` is a stage's fatal
    /// failure.
    pub fn run(&mut self) -> Result<(), StageError> {
        let Some(p) = self.pulse.take() else {
            return Ok(());
        };
        let before = self.dropped.total();
        self.cur.push(p);
        for stage in &mut self.stages {
            for p in self.cur.drain(..) {
                let mut em = Emitter::new(
                    &mut self.next,
                    &self.pool,
                    &mut self.dropped,
                    &mut self.errors,
                );
                stage.process(p, &mut em)?;
            }
            std::mem::swap(&mut self.cur, &mut self.next);
        }
        self.pulse = self.cur.pop();
        for extra in self.cur.drain(..) {
            self.pool.give(extra);
        }
        if self.pulse.is_none() && self.dropped.total() == before {
            self.dropped.add(HELD_BY_STAGE, 1);
        }
        Ok(())
    }

    /// Writes the return waveform the chain left into `out` (its length): the pulse's signal,
    /// or zeros when the pulse was dropped or no stage produced a signal.
    pub fn unload(&self, out: &mut [f32]) {
        match self.pulse.as_deref() {
            Some(p) if p.signal.len() == p.raw.len() && p.segments.len() > RETURN_SEGMENT => {
                let w = p.signal_of(RETURN_SEGMENT);
                let n = w.len().min(out.len());
                out[..n].copy_from_slice(&w[..n]);
                out[n..].fill(0.0);
            }
            _ => out.fill(0.0),
        }
    }

    /// Pulses dropped or rejected so far, by reason (`<stage>.<reason>`-free: the stages'
    /// own reasons).
    pub fn dropped(&self) -> &DropCounts {
        &self.dropped
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::tradeoff::{
        Processing, Setting, SweepConfig, default_settings, run_sweep, summarise,
    };
    use crate::sim::truth::{TruthFamily, gaussian_pulse};

    fn stages(text: &str) -> Vec<StageConfig> {
        #[derive(serde::Deserialize)]
        struct L {
            stages: Vec<StageConfig>,
        }
        toml::from_str::<L>(text).unwrap().stages
    }

    /// The adapter proven: a chain of the denoise stage and a Richardson-Lucy 20 deconvolve
    /// stage with the sweep's own system pulse as its calibrated kernel scores like the
    /// built-in `rl iterations=20` on the same pulses; only the 16-bit digitizer's
    /// quantisation (1/60 000 of each pulse's range) separates them.
    #[test]
    fn a_denoise_rl20_chain_scores_like_the_built_in_rl20() {
        let width = 8.0;
        let k = gaussian_pulse(width, 1.0).unwrap();
        let taps: Vec<String> = k.taps.iter().map(|t| format!("{t:e}")).collect();
        let text = format!(
            "[[stages]]\ntype = \"denoise\"\n[[stages]]\ntype = \"deconvolve\"\n\
             method = {{ method = \"richardson_lucy\", iterations = 20 }}\n\
             kernel = {{ taps = {{ taps = [{}], center = {} }} }}\n\
             [[stages]]\ntype = \"decompose\"\n",
            taps.join(", "),
            k.center
        );
        let spec = ChainSpec::from_stages("rl20", Path::new("rl20.toml"), &stages(&text)).unwrap();
        assert_eq!(spec.stage_names(), ["denoise", "deconvolve"]);
        assert_eq!(spec.skipped, ["decompose"]);
        let builtin = default_settings()
            .into_iter()
            .find(|s| s.label() == "rl iterations=20")
            .unwrap();
        let settings = vec![builtin, Setting::chain(spec)];
        assert!(matches!(settings[1].processing, Processing::Chain(_)));
        assert_eq!(settings[1].label(), "chain:rl20");
        let config = SweepConfig {
            pulses: 200,
            widths_ns: vec![width],
            families: TruthFamily::ALL.to_vec(),
            ..SweepConfig::default()
        };
        let cases = run_sweep(&config, &settings, |_| {}).unwrap();
        for pair in cases.chunks(2) {
            let (b, c) = (&pair[0], &pair[1]);
            assert_eq!((b.setting, c.setting), (0, 1));
            assert_eq!(c.dropped, 0);
            assert_eq!(b.truth_peaks, c.truth_peaks);
            let (rb, rc) = (b.rmse.rmse(), c.rmse.rmse());
            assert!((rb - rc).abs() < 1e-4 * rb, "RMSE {rb} vs {rc}");
            assert!((b.rmse_2ns.rmse() - c.rmse_2ns.rmse()).abs() < 1e-4 * rb);
            assert!((b.sam_deg - c.sam_deg).abs() < 1e-3, "SAM");
            let near = |x: u32, y: u32| x.abs_diff(y) <= 1 + x / 500;
            assert!(
                near(b.peaks.true_detections, c.peaks.true_detections)
                    && near(b.peaks.false_detections, c.peaks.false_detections),
                "{:?} vs {:?}",
                b.peaks,
                c.peaks
            );
        }
        let s = summarise(&settings, &cases);
        assert!((s[0].rmse - s[1].rmse).abs() < 1e-4 * s[0].rmse);
        assert_eq!(s[0].pulses, s[1].pulses);
    }

    #[test]
    fn the_outgoing_kernel_and_the_skipped_stages() {
        let spec = ChainSpec::from_stages(
            "board",
            Path::new("board.toml"),
            &stages(
                "[[stages]]\ntype = \"denoise\"\n[[stages]]\ntype = \"deconvolve\"\n\
                 method = { method = \"richardson_lucy\", iterations = 20 }\n\
                 [[stages]]\ntype = \"decompose\"\n[[stages]]\ntype = \"calibrate\"\n",
            ),
        )
        .unwrap();
        assert_eq!(spec.skipped, ["decompose", "calibrate"]);
        let k = gaussian_pulse(4.0, 1.0).unwrap();
        let mut r = spec.runner();
        let received: Vec<f32> = (0..225)
            .map(|i| 2.0 * (-((i as f32 - 100.0) / 2.0).powi(2)).exp() + 0.01 * ((i % 3) as f32))
            .collect();
        let mut out = vec![f32::NAN; 225];
        for _ in 0..3 {
            r.load(&received, &k, 1.0);
            r.run().unwrap();
            r.unload(&mut out);
        }
        assert_eq!(r.dropped().total(), 0);
        let peak = (0..225).max_by(|&a, &b| out[a].total_cmp(&out[b])).unwrap();
        assert!(
            (99..=101).contains(&peak),
            "the return stays in place: {peak}"
        );
    }

    #[test]
    fn a_chain_without_a_waveform_stage_is_refused_naming_the_field() {
        let e = ChainSpec::from_stages(
            "x",
            Path::new("x.toml"),
            &stages("[[stages]]\ntype = \"passthrough\"\n"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.starts_with("x.toml: pipeline.stages: no stage changes"),
            "{e}"
        );
        let e = ChainSpec::load(Path::new("/nonexistent/c.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent/c.toml"), "{e}");
    }
}
