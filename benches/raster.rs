//! Writing a 4096 × 4096 single-band Float32 Cloud-Optimized GeoTIFF (a canopy-height-like
//! field with nodata gaps): tiles of 256, DEFLATE level 6, floating-point predictor, 4
//! overviews, written atomically with fsync to a temporary folder. With one compressing thread
//! (the default) and with two, at DEFLATE level 6 (the default) and 1. Each call's time is also kept, and mean / p50 / p99 over all
//! calls (warm-up included) printed after each case.
//!
//! `metrics_rasters_sink_*`: the run's metrics rasters sink (`MetricsRastersSink`) fed a
//! synthetic flight — two passes, the second back over the same ground 10 s later, 400 000
//! pulses in all, 50 m/s along x over 4000 m, a 300 m swath — with tiles closing as flown
//! (`close_after_s` 2, 64 open) and kept to the end (what the sink did before issue 20 item 3),
//! at 100 m and 1000 m tiles. Each flight is timed whole (finish included); the time of every
//! `write` call is kept and mean / p50 / p99 / max printed (the sink's service time), with the
//! finish's.

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
        if times.is_empty() {
            continue; // filtered out
        }
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

/// One synthetic flight through a fresh sink in `dir`: the durations of its `write` calls
/// (appended to `writes`) and of its `finish`.
fn fly(
    dir: &std::path::Path,
    settings: fwlidar::sink::metrics_rasters::RasterSettings,
    writes: &mut Vec<Duration>,
) -> Duration {
    use fwlidar::pipeline::ports::PulseSink;
    use fwlidar::pulse::Pulse;
    use fwlidar::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
    use fwlidar::sink::metrics_rasters::{MetricsRastersSink, RasterCrs};
    let _ = std::fs::remove_dir_all(dir.join("rasters"));
    let mut sink =
        MetricsRastersSink::new(dir, settings, RasterCrs::Known(Some("EPSG:32618".into())));
    let mut p = Pulse::default();
    let mut m = WaveformMetrics {
        status: MetricsStatus::Ok,
        ..Default::default()
    };
    let n = 200_000u64;
    let dt = 80.0 / n as f64; // 80 s per pass at 50 m/s: 4000 m
    for pass in 0..2u64 {
        for i in 0..n {
            let k = pass * n + i;
            let along = i as f64 * dt * 50.0;
            let (x, t) = if pass == 0 {
                (along, i as f64 * dt)
            } else {
                (3999.9 - along, 90.0 + i as f64 * dt)
            };
            // Scan lines across the swath, 100 pulses each.
            let y = 1000.0 + ((k % 100) as f64 * 3.0 + pass as f64 * 1.3);
            let h = 5.0 + ((k * 7919) % 1000) as f32 / 50.0;
            m.ground_xyz = [x, y, 100.0];
            for (j, v) in m.rh.iter_mut().enumerate() {
                *v = h * j as f32 / 100.0;
            }
            m.canopy_height = h;
            m.cover = (k % 10) as f32 / 10.0;
            p.pulse_id = k;
            p.gps_time = t;
            p.metrics = Some(m);
            let started = Instant::now();
            sink.write(black_box(&p)).unwrap();
            writes.push(started.elapsed());
        }
    }
    let started = Instant::now();
    sink.finish().unwrap();
    started.elapsed()
}

fn bench_sink(c: &mut Criterion) {
    use fwlidar::sink::metrics_rasters::RasterSettings;
    let dir = tempfile::tempdir().unwrap();
    let mut g = c.benchmark_group("raster");
    g.sample_size(10);
    g.throughput(Throughput::Elements(400_000));
    for tile_m in [100.0, 1000.0] {
        for (label, close_after_s, max_open_tiles) in
            [("flown", 2.0, 64usize), ("kept", f64::INFINITY, usize::MAX)]
        {
            let settings = RasterSettings {
                chm_cell_m: 1.0,
                profile_cell_m: 10.0,
                tile_m,
                close_after_s,
                max_open_tiles,
            };
            let mut writes: Vec<Duration> = Vec::new();
            let mut finishes: Vec<Duration> = Vec::new();
            g.bench_function(format!("metrics_rasters_sink_tile{tile_m}_{label}"), |b| {
                b.iter_custom(|iters| {
                    let mut total = Duration::ZERO;
                    for _ in 0..iters {
                        let t = Instant::now();
                        finishes.push(fly(dir.path(), settings, &mut writes));
                        total += t.elapsed();
                    }
                    total
                })
            });
            if writes.is_empty() {
                continue; // filtered out
            }
            writes.sort();
            let us = |d: Duration| d.as_secs_f64() * 1e6;
            let mean = writes.iter().map(|&d| us(d)).sum::<f64>() / writes.len() as f64;
            let pct = |p: f64| us(writes[((writes.len() - 1) as f64 * p).round() as usize]);
            let fin = finishes.iter().map(|&d| us(d) / 1e3).sum::<f64>() / finishes.len() as f64;
            println!(
                "metrics_rasters sink tile {tile_m} m {label}: {} flights, write mean {mean:.3} µs, \
                 p50 {:.3} µs, p99 {:.3} µs, max {:.1} ms; finish mean {fin:.1} ms",
                finishes.len(),
                pct(0.5),
                pct(0.99),
                pct(1.0) / 1e3,
            );
        }
    }
    g.finish();
}

criterion_group!(benches, bench, bench_sink);
criterion_main!(benches);
