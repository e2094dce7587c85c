//! Benchmark of NNLS deconvolution on a CAO-like 256-sample return at 1 ns sampling with a
//! 16 ns FWHM Gaussian system response (taps to ±3σ: 41 taps). Target: ≤ 200 µs median.

#[path = "common/waveforms.rs"]
mod waveforms;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::signal::deconvolve::{Deconvolver, Nnls, NnlsConfig, NnlsOrRlConfig, Targeted};
use fwlidar::signal::kernel::Kernel;
use std::hint::black_box;

/// The 16 ns FWHM Gaussian kernel at 1 ns (41 taps, centred).
fn kernel() -> Kernel {
    let sigma = 16.0 / 2.354_82;
    let half = (3.0f64 * sigma).round() as i64;
    let taps: Vec<f32> = (-half..=half)
        .map(|i| (-0.5 * (i as f64 / sigma).powi(2)).exp() as f32)
        .collect();
    let mut k = Kernel::with_capacity(taps.len());
    k.set_from_taps(&taps, half as usize, taps.len())
        .expect("kernel");
    k
}

/// Two surfaces (16 ns wide returns, 40 and 36 DN) with ±3 DN deterministic ripple, in volts
/// above baseline (0.004 V/DN).
fn segment(ripple: bool) -> Vec<f32> {
    let sigma = 16.0 / 2.354_82;
    let g = |i: usize, mu: f64, a: f64| {
        let d = (i as f64 - mu) / sigma;
        a * (-0.5 * d * d).exp()
    };
    let r = |i: usize| {
        if ripple {
            3.0 * ((i * 7919 % 13) as f64 / 6.0 - 1.0)
        } else {
            0.0
        }
    };
    (0..256)
        .map(|i| (0.004 * (g(i, 67.0, 40.0) + g(i, 167.0, 36.0) + r(i))) as f32)
        .collect()
}

fn nnls(c: &mut Criterion) {
    let k = kernel();
    assert_eq!(k.len(), 41);
    waveforms::dump_f32("nnls_kernel_f32", &k.taps);
    waveforms::dump_f32("nnls_noisy_f32", &segment(true));
    waveforms::dump_f32("nnls_clean_f32", &segment(false));
    let mut d = Nnls::new(NnlsConfig::default(), 256, 64);
    let mut out = vec![0.0f32; 256];
    for (name, y) in [
        ("nnls_return256_gauss16ns_noisy", segment(true)),
        ("nnls_return256_gauss16ns_clean", segment(false)),
    ] {
        let stats = d.run(&y, &k, 0.012, 1.0, &mut out).expect("nnls");
        println!("{name}: {stats:?}");
    }
    for (name, y) in [
        ("nnls_return256_gauss16ns_noisy", segment(true)),
        ("nnls_return256_gauss16ns_clean", segment(false)),
    ] {
        c.bench_function(name, |b| {
            b.iter(|| {
                d.run(black_box(&y), &k, 0.012, 1.0, &mut out)
                    .expect("nnls");
                black_box(&out);
            })
        });
    }
    // The budget-bound case: no early stop, up to all 50 iterations (the worst case's shape).
    let mut full = Nnls::new(
        NnlsConfig {
            max_iterations: 50,
            tolerance: 0.0,
            ..Default::default()
        },
        256,
        64,
    );
    // Rougher noise (±8 DN, pseudo-random) so that the true optimum needs more non-zeros.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let y: Vec<f32> = segment(true)
        .iter()
        .map(|&v| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            v + 0.004 * 16.0 * ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) as f32
        })
        .collect();
    waveforms::dump_f32("nnls_full_budget_f32", &y);
    let stats = full.run(&y, &k, 0.012, 1.0, &mut out).expect("nnls");
    println!("no-early-stop run: {stats:?}");
    c.bench_function("nnls_return256_gauss16ns_noisy_full_budget", |b| {
        b.iter(|| {
            full.run(black_box(&y), &k, 0.012, 1.0, &mut out)
                .expect("nnls");
            black_box(&out);
        })
    });
}

/// A dense canopy: 80 pseudo-random non-negative scatterers convolved with the kernel, no
/// early stop, so every one of the 50 iterations runs (the budget-bound case).
fn nnls_cap(c: &mut Criterion) {
    let k = kernel();
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut truth = [0.0f64; 256];
    for _ in 0..80 {
        truth[(next() * 256.0) as usize] += next();
    }
    let half = k.center as isize;
    let y: Vec<f32> = (0..256isize)
        .map(|i| {
            let mut acc = 0.0;
            for (j, &t) in k.taps.iter().enumerate() {
                let s = i + half - j as isize;
                if (0..256).contains(&s) {
                    acc += t as f64 * truth[s as usize];
                }
            }
            (acc + 0.01 * (next() - 0.5)) as f32
        })
        .collect();
    let mut d = Nnls::new(
        NnlsConfig {
            max_iterations: 50,
            tolerance: 0.0,
            ..Default::default()
        },
        256,
        64,
    );
    let mut out = vec![0.0f32; 256];
    waveforms::dump_f32("nnls_dense_canopy_f32", &y);
    let stats = d.run(&y, &k, 0.01, 1.0, &mut out).expect("nnls");
    println!("dense canopy run: {stats:?}");
    c.bench_function("nnls_return256_gauss16ns_dense_canopy_cap", |b| {
        b.iter(|| {
            d.run(black_box(&y), &k, 0.01, 1.0, &mut out).expect("nnls");
            black_box(&out);
        })
    });
}

/// `fwlidar process --method nnls`'s setting (budget 128, the noise-weighted refit) on rows of
/// the noise-model benchmark's shape: an 8 ns Gaussian pulse at 1 ns (29 taps), 256 samples,
/// a ground echo, three canopy echoes and a close pair 6 ns apart; white noise (σ = 0.03 of the
/// peak: no refit), shot noise (variance ∝ signal, 200 photo-electrons at the peak: the refit
/// runs) and the same row clipped at 0.6 of its peak (7 samples left out).
fn nnls_process(c: &mut Criterion) {
    let sigma = 8.0 / 2.354_82f64;
    let taps: Vec<f32> = (-14..=14)
        .map(|i| (-0.5 * (i as f64 / sigma).powi(2)).exp() as f32)
        .collect();
    let sum: f32 = taps.iter().sum();
    let taps: Vec<f32> = taps.iter().map(|t| t / sum).collect();
    let mut k = Kernel::with_capacity(taps.len());
    k.set_from_taps(&taps, 14, taps.len()).expect("kernel");
    let echoes = [
        (62.0, 0.4),
        (68.0, 0.35),
        (101.0, 0.2),
        (140.0, 0.3),
        (222.0, 0.9),
    ];
    let clean: Vec<f64> = (0..256)
        .map(|i| {
            echoes
                .iter()
                .map(|&(c, a)| a * (-0.5 * ((i as f64 - c) / sigma).powi(2)).exp())
                .sum()
        })
        .collect();
    let peak = clean.iter().fold(0.0f64, |a, &v| a.max(v));
    let mut state = 0x853c_49e6_748f_ea9bu64;
    let mut gauss = move || {
        let mut u = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let (u1, u2) = (u(), u());
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    };
    let white: Vec<f32> = clean
        .iter()
        .map(|&v| (v + 0.03 * peak * gauss()) as f32)
        .collect();
    let gain = 200.0 / peak;
    let shot: Vec<f32> = clean
        .iter()
        .map(|&v| (v + ((v * gain + 2.0).sqrt() * gauss()) / gain) as f32)
        .collect();
    let clipped: Vec<f32> = white.iter().map(|&v| v.min((0.6 * peak) as f32)).collect();
    let mut excluded = Vec::new();
    let flagged = fwlidar::signal::drift::flag_saturated(&clipped, &mut excluded);
    waveforms::dump_f32("nnls_process_kernel_f32", &k.taps);
    waveforms::dump_f32("nnls_process_white_f32", &white);
    waveforms::dump_f32("nnls_process_shot_f32", &shot);
    waveforms::dump_f32("nnls_process_clipped_f32", &clipped);
    // As `process` runs it: the row's noise level from its first differences (a mean absolute
    // deviation, σ √(2/π)), spikes only near echoes (τ = 4); and the same without the mask.
    let mut drift = fwlidar::signal::drift::DriftBaseline::with_capacity(256);
    let mut noise_of =
        |y: &[f32]| (drift.difference_sigma(y) * (2.0 / std::f64::consts::PI).sqrt()) as f32;
    let rows = [
        ("white", &white, &none_flags(), noise_of(&white)),
        ("shot", &shot, &none_flags(), noise_of(&shot)),
        ("clipped", &clipped, &excluded, noise_of(&clipped)),
    ];
    for (suffix, support) in [("", Some(4.0)), ("_anywhere", None)] {
        let cfg = NnlsConfig {
            max_iterations: 128,
            noise_weights: true,
            support_at_noise: support,
            ..Default::default()
        };
        let mut d = Nnls::new(cfg, 256, 64);
        let mut out = vec![0.0f32; 256];
        for (row, y, ex, noise_v) in &rows {
            let name = format!("nnls_process_8ns_{row}{suffix}");
            let stats = d
                .run_excluding(y, &k, *noise_v, 1.0, ex, &mut out)
                .expect("nnls");
            println!("{name}: {stats:?} ({flagged} clipped samples in the clipped row)");
            c.bench_function(&name, |b| {
                b.iter(|| {
                    d.run_excluding(black_box(y), &k, *noise_v, 1.0, ex, &mut out)
                        .expect("nnls");
                    black_box(&out);
                })
            });
        }
    }
    // The per-pulse choice between NNLS and accelerated RL, to a 2 ns target, on the same rows
    // (as `process --method nnls_or_rl` runs it, without its low-pass): as configured (NNLS
    // only where RL's residual is above the noise), and with NNLS run on every row.
    for (label, above) in [("nnls_or_rl", 1.0), ("nnls_or_rl_always", 0.0)] {
        let choice = fwlidar::signal::deconvolve::MethodConfig::NnlsOrRl(NnlsOrRlConfig {
            nnls: NnlsConfig {
                max_iterations: 128,
                noise_weights: true,
                support_at_noise: Some(4.0),
                ..Default::default()
            },
            nnls_above_noise: above,
            ..NnlsOrRlConfig::default()
        });
        let mut d = Targeted::new(choice.build(256, 64), Some(2.0), 256, 64);
        let mut out = vec![0.0f32; 256];
        for (row, y, ex, noise_v) in &rows {
            let name = format!("{label}_2ns_8ns_{row}");
            d.run_excluding(y, &k, *noise_v, 1.0, ex, &mut out)
                .expect("nnls_or_rl");
            c.bench_function(&name, |b| {
                b.iter(|| {
                    d.run_excluding(black_box(y), &k, *noise_v, 1.0, ex, &mut out)
                        .expect("nnls_or_rl");
                    black_box(&out);
                })
            });
        }
    }
}

/// No sample flagged.
fn none_flags() -> Vec<bool> {
    vec![false; 256]
}

criterion_group!(benches, nnls, nnls_cap, nnls_process);
criterion_main!(benches);
