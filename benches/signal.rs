//! Benchmarks of the per-pulse signal stages.

#[path = "common/waveforms.rs"]
mod waveforms;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::pipeline::{DropCounts, Emitter, Stage};
use fwlidar::pulse::{FittedReturn, Pulse, PulsePool, SegmentKind};
use fwlidar::signal::denoise::LowPass;
use fwlidar::signal::{Calibrate, CalibrateConfig, Denoise, DenoiseConfig};
use std::hint::black_box;

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

criterion_group!(benches, denoise, calibrate);
criterion_main!(benches);
