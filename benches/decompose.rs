//! Benchmark of the Gaussian decomposition: one 256-sample return with three echoes (two of
//! them 1.5 σ apart, so the residual refinement runs), at default settings.

#[path = "common/waveforms.rs"]
mod waveforms;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::signal::DecomposeConfig;
use fwlidar::signal::decompose::Decomposer;
use std::hint::black_box;

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

fn decompose(c: &mut Criterion) {
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

criterion_group!(benches, decompose);
criterion_main!(benches);
