//! Benchmarks of the Gaussian decomposition at default settings:
//!
//! - `decompose_3_echoes_256`: one 256-sample return with three echoes (two of them 1.5 σ
//!   apart, so the residual refinement runs);
//! - `decompose_survey_line/per_pulse`: the survey line's real mix of empty, sparse and canopy
//!   pulses. [`MIX_PULSES`] pulses of `config/scenes/survey_line.toml` (every
//!   [`MIX_STRIDE`]-th of the scene's first pulses, as `fwlidar simulate` writes them for the
//!   replay benchmark, and as many again over the stand of trees) go through the replay chain's
//!   denoise and Richardson-Lucy stages (`config/replay.toml`) once; the decompose stage is then
//!   timed per pulse. Criterion reports the mean per pulse; the bench also prints the mean, p50,
//!   p99 and p99.9 of single-pulse timings (three passes over all pulses, `Instant` per pulse),
//!   and the same of each pulse's fastest of the three (which leaves out most preemptions on a
//!   shared machine).
//!
//! With `FWLIDAR_DECOMPOSE_DUMP=FILE` the survey-line case writes every fitted return
//! (`pulse,segment,position_bins,amplitude,sigma_bins`) and every truth scatterer of the same
//! pulses (`FILE.truth`: `pulse,return_start_ns,range_m,amplitude_dn`) for comparing two builds.

#[path = "common/survey.rs"]
mod survey;
#[path = "common/waveforms.rs"]
mod waveforms;

use std::hint::black_box;
use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::config::RunConfig;
use fwlidar::pipeline::stage::{DropCounts, Emitter, Stage};
use fwlidar::pipeline::testing::run_stage;
use fwlidar::pulse::{Pulse, PulsePool, SegmentKind};
use fwlidar::signal::DecomposeConfig;
use fwlidar::signal::decompose::Decomposer;
use fwlidar::sim::world::ShotTruth;
use fwlidar::stages::StageConfig;

/// Pulses per half of the survey-line mix.
const MIX_PULSES: usize = 2500;
/// Every this many pulses of the scene is kept (spreads the mix over the scan pattern).
const MIX_STRIDE: usize = 40;

/// Three echoes (A, μ, σ in bins) plus a small deterministic ripple as noise.
fn three_echoes() -> Vec<f32> {
    let echoes = [
        (60.0f64, 60.0f64, 4.0f64),
        (40.0, 130.0, 4.0),
        (35.0, 136.0, 4.0),
    ];
    (0..256)
        .map(|i| {
            let t = i as f64;
            let s: f64 = echoes
                .iter()
                .map(|&(a, mu, s)| a * (-0.5 * ((t - mu) / s).powi(2)).exp())
                .sum();
            let ripple = 0.3 * ((i * 7919 % 13) as f64 / 6.0 - 1.0);
            (s + ripple) as f32
        })
        .collect()
}

/// Survey-line pulses (`count` of them, every `MIX_STRIDE`-th, the line starting at
/// `start_east_m` or where the scene starts it) with their truth.
fn simulate(count: usize, start_east_m: Option<f64>) -> Vec<(Pulse, ShotTruth)> {
    survey::survey_line_pulses(count, MIX_STRIDE, start_east_m)
}

/// The replay chain's stage configurations (`config/replay.toml`): denoise, deconvolve and
/// decompose.
fn replay_stages() -> (StageConfig, StageConfig, StageConfig) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/replay.toml");
    let cfg: RunConfig = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let find = |kind: &str| {
        cfg.pipeline
            .stages
            .iter()
            .find(|s| s.kind() == kind)
            .unwrap_or_else(|| panic!("config/replay.toml has no {kind} stage"))
            .clone()
    };
    (find("denoise"), find("deconvolve"), find("decompose"))
}

/// Denoised and deconvolved survey-line pulses, ready for the decompose stage, with their truth.
// The stage API moves boxed pulses.
#[allow(clippy::vec_box)]
fn survey_line_mix() -> (Vec<Box<Pulse>>, Vec<ShotTruth>, StageConfig) {
    let (denoise, deconvolve, decompose) = replay_stages();
    let mut raw = simulate(MIX_PULSES, None);
    raw.extend(simulate(MIX_PULSES, Some(-100.0)));
    let (pulses, truth): (Vec<Pulse>, Vec<ShotTruth>) = raw.into_iter().unzip();
    let mut d = denoise.build().expect("denoise builds");
    let mut r = deconvolve.build().expect("deconvolve builds");
    let den = run_stage(d.as_mut(), pulses).unwrap();
    assert_eq!(den.emitted.len(), truth.len(), "denoise dropped pulses");
    let dec = run_stage(r.as_mut(), den.emitted.into_iter().map(|p| *p)).unwrap();
    assert_eq!(dec.emitted.len(), truth.len(), "deconvolve dropped pulses");
    (dec.emitted, truth, decompose)
}

/// Runs `stage` on `pulse` (emitted back into `slot`).
// The stage API moves boxed pulses.
#[allow(clippy::vec_box)]
fn process(
    stage: &mut dyn Stage,
    pulse: Box<Pulse>,
    out: &mut Vec<Box<Pulse>>,
    pool: &PulsePool,
    dropped: &mut DropCounts,
    errors: &mut u64,
) {
    let mut em = Emitter::new(out, pool, dropped, errors);
    stage.process(pulse, &mut em).unwrap();
}

fn dump(path: &str, pulses: &[Box<Pulse>], truth: &[ShotTruth]) {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    writeln!(f, "pulse,segment,position_bins,amplitude,sigma_bins").unwrap();
    for (i, p) in pulses.iter().enumerate() {
        for r in &p.returns {
            writeln!(
                f,
                "{i},{},{},{},{}",
                r.segment, r.position_bins, r.amplitude, r.sigma_bins
            )
            .unwrap();
        }
    }
    let mut f = std::io::BufWriter::new(std::fs::File::create(format!("{path}.truth")).unwrap());
    writeln!(f, "pulse,return_start_ns,range_m,amplitude_dn").unwrap();
    for (i, t) in truth.iter().enumerate() {
        for s in &t.scatterers {
            writeln!(
                f,
                "{i},{},{},{}",
                t.return_start_ns, s.range_m, s.amplitude_dn
            )
            .unwrap();
        }
    }
}

fn survey_line(c: &mut Criterion) {
    let (pulses, truth, config) = survey_line_mix();
    let mut stage = config.build().expect("the stage builds");
    let pool = PulsePool::new(4);
    let (mut dropped, mut errors) = (DropCounts::default(), 0u64);
    let mut slots: Vec<Option<Box<Pulse>>> = pulses.into_iter().map(Some).collect();
    let mut out = Vec::with_capacity(1);
    let mut one = |stage: &mut dyn Stage, slot: &mut Option<Box<Pulse>>| {
        process(
            stage,
            slot.take().unwrap(),
            &mut out,
            &pool,
            &mut dropped,
            &mut errors,
        );
        *slot = out.pop();
        assert!(slot.is_some(), "the decompose stage dropped a pulse");
    };

    // Per-pulse timings: one warm-up pass, then three timed passes.
    for s in slots.iter_mut() {
        one(stage.as_mut(), s);
    }
    let mut times: Vec<u64> = Vec::with_capacity(3 * slots.len());
    let mut fastest = vec![u64::MAX; slots.len()];
    for _ in 0..3 {
        for (s, f) in slots.iter_mut().zip(fastest.iter_mut()) {
            let t0 = Instant::now();
            one(stage.as_mut(), s);
            let t = t0.elapsed().as_nanos() as u64;
            times.push(t);
            *f = (*f).min(t);
        }
    }
    times.sort_unstable();
    fastest.sort_unstable();
    let q = |f: f64| times[((times.len() - 1) as f64 * f).round() as usize] as f64 / 1e3;
    let mean = times.iter().sum::<u64>() as f64 / times.len() as f64 / 1e3;
    let done: Vec<Box<Pulse>> = slots.iter().map(|s| s.clone().unwrap()).collect();
    let returns: usize = done.iter().map(|p| p.returns.len()).sum();
    let empty = done.iter().filter(|p| p.returns.is_empty()).count();
    println!(
        "decompose_survey_line: {} pulses ({empty} without returns, {returns} returns): \
         per pulse mean {mean:.2} µs, p50 {:.2} µs, p99 {:.2} µs, p99.9 {:.2} µs, max {:.1} µs",
        done.len(),
        q(0.5),
        q(0.99),
        q(0.999),
        q(1.0)
    );
    // The same per pulse, each pulse's fastest of the three passes: on a shared machine this
    // leaves out most preemptions (which land in the tail of the figures above).
    let fq = |f: f64| fastest[((fastest.len() - 1) as f64 * f).round() as usize] as f64 / 1e3;
    println!(
        "decompose_survey_line: fastest of 3 passes per pulse: mean {:.2} µs, p50 {:.2} µs, \
         p99 {:.2} µs, p99.9 {:.2} µs, max {:.1} µs",
        fastest.iter().sum::<u64>() as f64 / fastest.len() as f64 / 1e3,
        fq(0.5),
        fq(0.99),
        fq(0.999),
        fq(1.0)
    );
    // What the fits did: LM trial steps and components per pulse.
    if let StageConfig::Decompose(cfg) = &config {
        let mut d = Decomposer::new(cfg.clone(), cfg.max_samples);
        let mut scratch = Vec::with_capacity(8);
        let (mut iters, mut at_cap, mut none_above, mut comps) = (0u64, 0usize, 0usize, 0u64);
        for p in &done {
            for seg in p.segments.iter().filter(|s| s.kind == SegmentKind::Return) {
                scratch.clear();
                let st = d
                    .fit(&p.signal[seg.range()], p.noise.noise_v, &mut scratch)
                    .unwrap();
                iters += st.iterations as u64;
                at_cap += (st.iterations >= cfg.max_iterations) as usize;
                none_above += (st.peaks == 0 && st.components == 0) as usize;
                comps += st.components as u64;
            }
        }
        println!(
            "decompose_survey_line: LM steps per pulse {:.2}, segments at the {}-step budget {at_cap}, \
             segments without a peak {none_above}, components per pulse {:.2}",
            iters as f64 / done.len() as f64,
            cfg.max_iterations,
            comps as f64 / done.len() as f64
        );
    }
    if let Ok(path) = std::env::var("FWLIDAR_DECOMPOSE_DUMP") {
        dump(&path, &done, &truth);
    }

    let mut g = c.benchmark_group("decompose_survey_line");
    g.throughput(Throughput::Elements(slots.len() as u64));
    g.bench_function("all_pulses", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let t0 = Instant::now();
                for s in slots.iter_mut() {
                    one(stage.as_mut(), s);
                }
                total += t0.elapsed();
            }
            // Criterion's figure is per pass; the printed line above is per pulse.
            total
        })
    });
    g.finish();
}

fn three(c: &mut Criterion) {
    let y = three_echoes();
    waveforms::dump_f32("decompose_3_echoes_f32", &y);
    let mut d = Decomposer::new(DecomposeConfig::default(), 4096);
    let mut out = Vec::with_capacity(8);
    c.bench_function("decompose_3_echoes_256", |b| {
        b.iter(|| {
            out.clear();
            let stats = d.fit(black_box(&y), 0.15, &mut out).unwrap();
            black_box(stats)
        })
    });
}

criterion_group!(benches, three, survey_line);
criterion_main!(benches);
