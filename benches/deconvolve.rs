//! Deconvolution of one 256-sample segment by a 16 ns FWHM Gaussian kernel at 1 ns sampling
//! (taps to ±⌈3σ⌉ = ±21 samples: 43 taps; the group keeps its historical name `..._41_taps`
//! so results stay comparable with earlier runs): Richardson-Lucy 20 iterations, Gold 20
//! iterations, the on-board setting (RL 12 from the Wiener start, `RlConfig::onboard`), Wiener
//! fused with the low-pass, with the same kernel every call (its spectrum
//! cached) and with a kernel that changes every call (per-shot kernels: spectrum computed per
//! call). Deconvolution to a 2 ns target pulse (`Targeted`, issue 19): RL-20 by the reduced
//! kernel with the same kernel every call (the reduction cached) and with a kernel that changes
//! every call (the reduction, a regularised spectral division, computed per call).

#[path = "common/waveforms.rs"]
mod waveforms;

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::signal::deconvolve::{
    Deconvolver, Gate, Gated, Gold, GoldConfig, MethodConfig, RichardsonLucy, RlConfig, Wiener,
    WienerConfig, target::Targeted,
};
use fwlidar::signal::kernel::{Kernel, convolve_same};

fn gaussian_kernel(fwhm_ns: f32) -> Kernel {
    let sigma = fwhm_ns / 2.354_82;
    let half = (3.0 * sigma).ceil() as usize;
    let taps: Vec<f32> = (0..=2 * half)
        .map(|j| {
            let d = (j as f32 - half as f32) / sigma;
            (-0.5 * d * d).exp()
        })
        .collect();
    let mut k = Kernel::default();
    k.set_from_taps(&taps, half, 256).expect("valid kernel");
    k
}

fn segment(k: &Kernel) -> Vec<f32> {
    let mut truth = vec![0.0f32; 256];
    truth[90] = 1.0;
    truth[120] = 0.5;
    truth[200] = 0.3;
    let mut y = vec![0.0; 256];
    convolve_same(&truth, k, &mut y);
    // Deterministic small "noise".
    for (i, v) in y.iter_mut().enumerate() {
        *v += 0.001 * (((i * 7919) % 13) as f32 - 6.0);
    }
    y
}

fn bench(c: &mut Criterion) {
    let k = gaussian_kernel(16.0);
    let y = segment(&k);
    waveforms::dump_f32("deconvolve_segment_f32", &y);
    waveforms::dump_f32("deconvolve_kernel_f32", &k.taps);
    let k2 = gaussian_kernel(16.5);
    waveforms::dump_f32("deconvolve_kernel2_f32", &k2.taps);
    let mut out = vec![0.0f32; 256];
    let mut methods: Vec<(&str, Box<dyn Deconvolver>)> = vec![
        (
            "richardson_lucy_20",
            Box::new(RichardsonLucy::new(RlConfig::default(), 4096, 256)),
        ),
        // The stop by the noise at a τ that never triggers: the residual's cost per iteration.
        (
            "richardson_lucy_20_stop_at_noise_inert",
            Box::new(RichardsonLucy::new(
                RlConfig {
                    stop_at_noise: Some(1e-6),
                    ..RlConfig::default()
                },
                4096,
                256,
            )),
        ),
        // The on-board setting (config/onboard.toml, issue 35): 12 iterations from the Wiener
        // start by the kernel to a 4 ns target, with the output's noise floor.
        (
            "richardson_lucy_12_wiener_start_onboard",
            Box::new(RichardsonLucy::new(RlConfig::onboard(), 4096, 256)),
        ),
        (
            "gold_20",
            Box::new(Gold::new(GoldConfig::default(), 4096, 256)),
        ),
        (
            "gold_20_stop_at_noise_inert",
            Box::new(Gold::new(
                GoldConfig {
                    stop_at_noise: Some(1e-6),
                    ..GoldConfig::default()
                },
                4096,
                256,
            )),
        ),
        (
            "wiener_fused_same_kernel",
            Box::new(Wiener::new(WienerConfig::default(), 4096, 256)),
        ),
    ];
    let mut group = c.benchmark_group("deconvolve_256_samples_41_taps");
    for (name, m) in methods.iter_mut() {
        group.bench_function(*name, |b| {
            b.iter(|| {
                m.run(black_box(&y), black_box(&k), 0.002, 1.0, &mut out)
                    .expect("runs");
                black_box(&out);
            })
        });
    }
    // Per-shot kernels: alternate two kernels so the Wiener kernel-spectrum cache never hits.
    let mut w = Wiener::new(WienerConfig::default(), 4096, 256);
    let mut flip = false;
    group.bench_function("wiener_fused_per_shot_kernel", |b| {
        b.iter(|| {
            flip = !flip;
            let kk = if flip { &k } else { &k2 };
            w.run(black_box(&y), black_box(kk), 0.002, 1.0, &mut out)
                .expect("runs");
            black_box(&out);
        })
    });
    // Deconvolution to a 2 ns target pulse: RL by the reduced kernel.
    let rl = || Box::new(RichardsonLucy::new(RlConfig::default(), 4096, 256));
    let mut targeted = Targeted::new(rl(), Some(2.0), 4096, 256);
    group.bench_function("richardson_lucy_20_target_2ns", |b| {
        b.iter(|| {
            targeted
                .run(black_box(&y), black_box(&k), 0.002, 1.0, &mut out)
                .expect("runs");
            black_box(&out);
        })
    });
    let mut targeted = Targeted::new(rl(), Some(2.0), 4096, 256);
    group.bench_function("richardson_lucy_20_target_2ns_per_shot_kernel", |b| {
        b.iter(|| {
            flip = !flip;
            let kk = if flip { &k } else { &k2 };
            targeted
                .run(black_box(&y), black_box(kk), 0.002, 1.0, &mut out)
                .expect("runs");
            black_box(&out);
        })
    });
    group.finish();
}

/// A 256-sample return of the survey line's kinds at 1 ns with an 8 ns pulse: `echoes`
/// (centre, amplitude) blurred by `k`, plus deterministic noise of ±0.01 (noise level about
/// 0.006 after a denoise).
fn survey_segment(k: &Kernel, echoes: &[(usize, f32)]) -> Vec<f32> {
    let mut truth = vec![0.0f32; 256];
    for &(i, a) in echoes {
        truth[i] = a;
    }
    let mut y = vec![0.0; 256];
    convolve_same(&truth, k, &mut y);
    let mut x = 0x9e37_79b9u32;
    for v in y.iter_mut() {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        *v += 0.01 * ((x as f32 / u32::MAX as f32) * 2.0 - 1.0);
    }
    y
}

/// Richardson-Lucy 20 behind the echo-window gate (the deconvolve stage's default) and without
/// it, on an empty, a sparse (one ground echo) and a canopy (echoes over ~60 samples above the
/// ground) return.
fn gated(c: &mut Criterion) {
    let k = gaussian_kernel(8.0);
    let rl = MethodConfig::RichardsonLucy(RlConfig::default());
    let cases = [
        ("empty", survey_segment(&k, &[])),
        ("sparse", survey_segment(&k, &[(150, 2.0)])),
        (
            "canopy",
            survey_segment(
                &k,
                &[(90, 0.4), (104, 0.6), (118, 0.3), (135, 0.5), (160, 1.5)],
            ),
        ),
    ];
    let mut out = vec![0.0f32; 256];
    let mut group = c.benchmark_group("deconvolve_gate_256_samples_8ns");
    for (gate, name) in [(Gate::default(), "gated"), (Gate::Off, "whole")] {
        let mut m = Gated::build(&rl, gate, 1024, 96);
        for (kind, y) in &cases {
            group.bench_function(format!("richardson_lucy_20_{name}_{kind}"), |b| {
                b.iter(|| {
                    m.run(black_box(y), black_box(&k), 0.006, 1.0, &mut out)
                        .expect("runs");
                    black_box(&out);
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench, gated);
criterion_main!(benches);
