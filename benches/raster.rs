//! Writing a 4096 × 4096 single-band Float32 Cloud-Optimized GeoTIFF (a canopy-height-like
//! field with nodata gaps): tiles of 256, DEFLATE level 6, floating-point predictor, 4
//! overviews, written atomically with fsync to a temporary folder. With one compressing thread
//! (the default) and with two, at DEFLATE level 6 (the default) and 1. Each call's time is also kept, and mean / p50 / p99 over all
//! calls (warm-up included) printed after each case.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::raster::{CogOptions, Raster, write_cog};

fn canopy(n: usize) -> Raster {
    let mut r = Raster::new(n, n, 583_000.0, 4_507_000.0, 1.0, 32618, -9999.0);
    let band = (0..n * n)
        .map(|i| {
            let (c, r) = ((i % n) as f32, (i / n) as f32);
            // Crowns ~ 8 m across over a 25 m stand, gaps where a smooth field dips below 0.
            let crown = ((c * 0.39).sin() * (r * 0.41).cos()).abs() * 9.0;
            let stand = (c * 0.011).sin() * 6.0 + (r * 0.007).cos() * 5.0 + 16.0;
            if (c * 0.003 + r * 0.002).sin() < -0.8 {
                -9999.0
            } else {
                // Centimetre resolution, as a canopy height model carries.
                ((stand + crown) * 100.0).round() / 100.0
            }
        })
        .collect();
    r.push_band("canopy_height", "m", band);
    r
}

fn bench(c: &mut Criterion) {
    let r = canopy(4096);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("chm.tif");
    let mut g = c.benchmark_group("raster");
    g.sample_size(10);
    g.throughput(Throughput::Bytes((r.width * r.height * 4) as u64));
    for (threads, level) in [(1usize, 6u32), (1, 1), (2, 6)] {
        let opt = CogOptions {
            threads,
            deflate_level: level,
            ..CogOptions::default()
        };
        let mut times: Vec<Duration> = Vec::new();
        g.bench_function(
            format!("write_cog_4096x4096_threads{threads}_level{level}"),
            |b| {
                b.iter_custom(|iters| {
                    let mut total = Duration::ZERO;
                    for _ in 0..iters {
                        let t = Instant::now();
                        write_cog(black_box(&path), &r, &opt).unwrap();
                        let d = t.elapsed();
                        times.push(d);
                        total += d;
                    }
                    total
                })
            },
        );
        times.sort();
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        let mean = times.iter().map(|&d| ms(d)).sum::<f64>() / times.len() as f64;
        let pct = |p: f64| ms(times[((times.len() - 1) as f64 * p).round() as usize]);
        let size = std::fs::metadata(&path).unwrap().len();
        println!(
            "write_cog 4096x4096 threads={threads} level={level}: {} calls, mean {mean:.1} ms, p50 {:.1} ms, \
             p99 {:.1} ms; file {:.1} MB ({:.2}:1 against 64 MiB of Float32)",
            times.len(),
            pct(0.5),
            pct(0.99),
            size as f64 / 1e6,
            (r.width * r.height * 4) as f64 / size as f64
        );
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
