//! Benchmarks of the per-pulse signal stages.
//!
//! - `denoise_outgoing64_return256_1ns` (and its FIR variant): one CAO-like pulse, again and
//!   again;
//! - `denoise_survey_line/all_pulses`: the survey line's mix, [`MIX_PULSES`] pulses of
//!   `config/scenes/survey_line.toml` (every [`MIX_STRIDE`]-th of the scene's first pulses, as
//!   many again over the stand of trees; 34-sample outgoing and 256-sample return segments)
//!   through the replay chain's denoise stage (`config/replay.toml`). Criterion reports the
//!   time per pass; the bench also prints the mean, p50 and p99 of single-pulse timings (three
//!   passes, `Instant` per pulse), the figure issue 18 asks about.

#[path = "common/survey.rs"]
mod survey;
#[path = "common/waveforms.rs"]
mod waveforms;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::config::RunConfig;
use fwlidar::pipeline::{DropCounts, Emitter, Stage};
use fwlidar::pulse::{FittedReturn, Pulse, PulsePool, SegmentKind};
use fwlidar::signal::denoise::LowPass;
use fwlidar::signal::{Calibrate, CalibrateConfig, Denoise, DenoiseConfig};
use fwlidar::stages::StageConfig;
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

/// Pulses per half of the survey-line mix.
const MIX_PULSES: usize = 2500;
/// Every this many pulses of the scene is kept (spreads the mix over the scan pattern).
const MIX_STRIDE: usize = 40;

/// A CAO-like pulse at 1 ns sampling: a 64-sample outgoing pulse (16 ns FWHM) and a 256-sample
/// return with two surfaces on a 12 DN baseline, with a little deterministic ripple as noise.
fn cao_like_pulse() -> Pulse {
    let sigma = 16.0 / 2.354_82;
    let g = |i: usize, mu: f64, a: f64| {
        let d = (i as f64 - mu) / sigma;
        a * (-0.5 * d * d).exp()
    };
    let ripple = |i: usize| 3.0 * ((i * 7919 % 13) as f64 / 6.0 - 1.0);
    let mut p = Pulse {
        sample_ns: 1.0,
        gain_v_per_dn: 0.004,
        ..Pulse::default()
    };
    p.push_segment(
        SegmentKind::Outgoing,
        0,
        -32.0,
        (0..64).map(|i| (12.0 + g(i, 32.0, 200.0) + ripple(i)).round() as u16),
    );
    p.push_segment(
        SegmentKind::Return,
        0,
        6500.0,
        (0..256).map(|i| (12.0 + g(i, 67.0, 40.0) + g(i, 167.0, 36.0) + ripple(i)).round() as u16),
    );
    p
}

fn denoise(c: &mut Criterion) {
    let mut stage = Denoise::new(DenoiseConfig::default());
    let pool = PulsePool::new(4);
    let mut out = Vec::with_capacity(1);
    let mut dropped = DropCounts::default();
    let mut errors = 0u64;
    let p = cao_like_pulse();
    for (s, name) in p
        .segments
        .iter()
        .zip(["denoise_outgoing_u16", "denoise_return_u16"])
    {
        waveforms::dump_u16(name, &p.raw[s.first as usize..(s.first + s.len) as usize]);
    }
    let mut pulse = Some(Box::new(p));
    c.bench_function("denoise_outgoing64_return256_1ns", |b| {
        b.iter(|| {
            let p = pulse.take().expect("the pulse comes back every iteration");
            let mut em = Emitter::new(&mut out, &pool, &mut dropped, &mut errors);
            stage.process(black_box(p), &mut em).expect("denoise");
            pulse = out.pop();
        })
    });
    // The same pulse through the optional FIR low-pass (`filter = "fir"`).
    let mut fir = Denoise::new(DenoiseConfig {
        filter: LowPass::Fir,
        ..DenoiseConfig::default()
    });
    c.bench_function("denoise_fir_outgoing64_return256_1ns", |b| {
        b.iter(|| {
            let p = pulse.take().expect("the pulse comes back every iteration");
            let mut em = Emitter::new(&mut out, &pool, &mut dropped, &mut errors);
            fir.process(black_box(p), &mut em).expect("denoise");
            pulse = out.pop();
        })
    });
    assert_eq!(dropped.total(), 0);
}

/// One stage call on `pulse` (it comes back through `out` every iteration).
fn run_once(stage: &mut dyn Stage, pulse: &mut Option<Box<Pulse>>, pool: &PulsePool) {
    let mut out = Vec::with_capacity(1);
    let mut dropped = DropCounts::default();
    let mut errors = 0u64;
    let p = pulse.take().expect("the pulse comes back every iteration");
    let mut em = Emitter::new(&mut out, pool, &mut dropped, &mut errors);
    stage.process(black_box(p), &mut em).expect("stage");
    *pulse = out.pop();
    assert!(pulse.is_some(), "the pulse was emitted");
}

/// The calibrate stage on the denoised CAO-like pulse with its two returns (outgoing energy and
/// peak, two backscatter values), and the per-bin factor over its 256 return bins (what a
/// consumer of `Pulse::calibration` pays per bin).
fn calibrate(c: &mut Criterion) {
    let pool = PulsePool::new(4);
    let mut pulse = Some(Box::new(cao_like_pulse()));
    run_once(
        &mut Denoise::new(DenoiseConfig::default()),
        &mut pulse,
        &pool,
    );
    let p = pulse.as_mut().expect("denoised");
    for (bin, amplitude) in [(67.0f32, 0.16f32), (167.0, 0.144)] {
        p.returns.push(FittedReturn {
            segment: 1,
            position_bins: bin,
            time_ns: 6500.0 + bin as f64,
            amplitude,
            sigma_bins: 6.8,
            ..Default::default()
        });
    }
    let mut stage = Calibrate::new(CalibrateConfig::default());
    // Calibrated once here too, so that the per-bin case below has its factor when a filter
    // skips this case.
    run_once(&mut stage, &mut pulse, &pool);
    c.bench_function("calibrate_outgoing64_return256_2returns", |b| {
        b.iter(|| run_once(&mut stage, &mut pulse, &pool))
    });
    let p = pulse.as_ref().expect("calibrated");
    let cal = p.calibration.expect("calibrated");
    let seg = p.segments[1];
    let bins = p.signal_of(1);
    c.bench_function("calibrate_factor_at_256_bins", |b| {
        b.iter(|| {
            let cal = black_box(cal);
            let mut sum = 0.0f32;
            for (i, &v) in bins.iter().enumerate() {
                sum += cal.calibrated(v, seg.start_ns + i as f64 * p.sample_ns);
            }
            sum
        })
    });
}

/// Survey-line pulses (`count` of them, every `MIX_STRIDE`-th, the line starting at
/// `start_east_m` or where the scene starts it), raw as `fwlidar simulate` writes them.
fn simulate(count: usize, start_east_m: Option<f64>) -> Vec<Pulse> {
    survey::survey_line_pulses(count, MIX_STRIDE, start_east_m)
        .into_iter()
        .map(|(p, _)| p)
        .collect()
}

/// The replay chain's denoise stage configuration (`config/replay.toml`).
fn replay_denoise() -> StageConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/replay.toml");
    let cfg: RunConfig = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    cfg.pipeline
        .stages
        .iter()
        .find(|s| s.kind() == "denoise")
        .expect("config/replay.toml has a denoise stage")
        .clone()
}

/// The denoise stage on the survey line's mix of pulses (per-pulse figures printed).
fn denoise_survey_line(c: &mut Criterion) {
    let mut pulses = simulate(MIX_PULSES, None);
    pulses.extend(simulate(MIX_PULSES, Some(-100.0)));
    let outgoing = pulses[0].segments[0].len;
    let ret = pulses[0].segments.get(1).map_or(0, |s| s.len);
    let mut stage = replay_denoise()
        .build()
        .expect("the replay denoise stage builds");
    let pool = PulsePool::new(4);
    let mut slots: Vec<Option<Box<Pulse>>> =
        pulses.into_iter().map(|p| Some(Box::new(p))).collect();
    let (mut out, mut dropped, mut errors) = (Vec::with_capacity(1), DropCounts::default(), 0u64);
    // One stage call, the pulse coming back into its slot (no allocation).
    let mut one = |stage: &mut dyn Stage, slot: &mut Option<Box<Pulse>>| {
        let p = slot.take().expect("the pulse comes back every pass");
        let mut em = Emitter::new(&mut out, &pool, &mut dropped, &mut errors);
        stage.process(black_box(p), &mut em).expect("denoise");
        *slot = out.pop();
        assert!(slot.is_some(), "denoise dropped a pulse");
    };
    for s in slots.iter_mut() {
        one(stage.as_mut(), s);
    }
    let mut times: Vec<u64> = Vec::with_capacity(3 * slots.len());
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
    println!(
        "denoise_survey_line: {} pulses (outgoing {outgoing}, return {ret} samples): per pulse \
         mean {mean:.3} µs, p50 {:.3} µs, p99 {:.3} µs, p99.9 {:.3} µs",
        slots.len(),
        q(0.5),
        q(0.99),
        q(0.999)
    );
    let mut g = c.benchmark_group("denoise_survey_line");
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
            total
        })
    });
    g.finish();
}

criterion_group!(benches, denoise, denoise_survey_line, calibrate);
criterion_main!(benches);
