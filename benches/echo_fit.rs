//! The decompose stage on a real instrument's pulses, both echo models side by side: the 2368
//! pulses of the RIEGL LMS-Q680i fixture (`tests/data/waveform/riegl_q680i/*.pls`) go through
//! the replay chain's denoise and Richardson-Lucy stages once; the decompose stage is then timed
//! per pulse with `model = "gaussian"` (free Gaussians on the deconvolved signal, what replay
//! ran before issue 55) and `model = "response"` (echoes against the response learned from the
//! same file, what the embedded configuration runs now).
//!
//! Criterion reports each pass over all pulses; the bench also prints per-pulse means, p50,
//! p99 and p99.9 (three passes, `Instant` per pulse) and the returns each model finds.

use std::hint::black_box;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::config::RunConfig;
use fwlidar::pipeline::ports::SourceEvent;
use fwlidar::pipeline::stage::{DropCounts, Emitter, Stage};
use fwlidar::pipeline::testing::run_stage;
use fwlidar::pulse::{Pulse, PulsePool};
use fwlidar::signal::decompose::EchoModel;
use fwlidar::signal::learned_response::ResponseLearner;
use fwlidar::stages::StageConfig;

/// The fixture's pulses, denoised and deconvolved as replay does, and the response learned
/// from them.
// The stage API moves boxed pulses.
#[allow(clippy::vec_box)]
fn riegl() -> (
    Vec<Box<Pulse>>,
    Arc<fwlidar::signal::learned_response::ResponseFile>,
    StageConfig,
) {
    let path = fwlidar::fixtures::path("waveform/riegl_q680i/100429_152240_2535pt_UTM.pls");
    let mut source = fwlidar::source::open_file(&path).unwrap();
    let pool = PulsePool::new(4);
    let mut pulses = Vec::new();
    let mut learner = ResponseLearner::new();
    loop {
        match source.next(&pool).unwrap() {
            SourceEvent::End => break,
            SourceEvent::Pulse(p) => {
                learner.add_pulse(&p);
                pulses.push((*p).clone());
            }
            _ => {}
        }
    }
    let response = Arc::new(learner.finish("bench").unwrap());
    let cfg_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/replay.toml");
    let cfg: RunConfig = toml::from_str(&std::fs::read_to_string(cfg_path).unwrap()).unwrap();
    let find = |kind: &str| {
        cfg.pipeline
            .stages
            .iter()
            .find(|s| s.kind() == kind)
            .unwrap()
            .clone()
    };
    let mut d = find("denoise").build().unwrap();
    let mut r = find("deconvolve").build().unwrap();
    let den = run_stage(d.as_mut(), pulses).unwrap();
    let dec = run_stage(r.as_mut(), den.emitted.into_iter().map(|p| *p)).unwrap();
    (dec.emitted, response, find("decompose"))
}

fn per_pulse(c: &mut Criterion) {
    let (pulses, response, decompose) = riegl();
    let StageConfig::Decompose(base) = decompose else {
        panic!("no decompose stage")
    };
    let pool = PulsePool::new(4);
    let mut g = c.benchmark_group("decompose_riegl_q680i");
    g.throughput(Throughput::Elements(pulses.len() as u64));
    for (name, model) in [
        ("gaussian", EchoModel::Gaussian),
        ("response", EchoModel::Response),
    ] {
        let config = StageConfig::Decompose(fwlidar::signal::DecomposeConfig {
            model,
            learned: Some(response.clone()),
            ..base.clone()
        });
        let mut stage = config.build().unwrap();
        let mut slots: Vec<Option<Box<Pulse>>> = pulses.iter().cloned().map(Some).collect();
        let (mut dropped, mut errors) = (DropCounts::default(), 0u64);
        let mut out = Vec::with_capacity(1);
        let mut one = |stage: &mut dyn Stage, slot: &mut Option<Box<Pulse>>| {
            let mut em = Emitter::new(&mut out, &pool, &mut dropped, &mut errors);
            stage.process(slot.take().unwrap(), &mut em).unwrap();
            *slot = out.pop();
        };
        for s in slots.iter_mut() {
            one(stage.as_mut(), s);
        }
        let mut times = Vec::with_capacity(3 * slots.len());
        for _ in 0..3 {
            for s in slots.iter_mut() {
                let t0 = Instant::now();
                one(stage.as_mut(), s);
                times.push(t0.elapsed().as_nanos() as u64);
            }
        }
        times.sort_unstable();
        let q = |f: f64| times[((times.len() - 1) as f64 * f).round() as usize] as f64 / 1e3;
        let mean = times.iter().sum::<u64>() as f64 / times.len() as f64 / 1e3;
        let returns: usize = slots
            .iter()
            .map(|s| s.as_ref().unwrap().returns.len())
            .sum();
        println!(
            "decompose_riegl_q680i/{name}: {} pulses, {returns} returns; per pulse mean \
             {mean:.2} µs, p50 {:.2} µs, p99 {:.2} µs, p99.9 {:.2} µs, max {:.1} µs",
            slots.len(),
            q(0.5),
            q(0.99),
            q(0.999),
            q(1.0)
        );
        g.bench_function(name, |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    let t0 = Instant::now();
                    for s in slots.iter_mut() {
                        one(stage.as_mut(), s);
                    }
                    total += t0.elapsed();
                }
                black_box(&slots);
                total
            })
        });
    }
    g.finish();
}

criterion_group!(benches, per_pulse);
criterion_main!(benches);
