//! Cost of the forest structure metrics per pulse (`src/forest/pulse_metrics.rs`, the `metrics`
//! stage of `config/replay.toml`):
//!
//! - `metrics/gedi_shot`: the 32 real GEDI shots of the fixture (760–823 samples, 6.5 ns
//!   smoothing), one at a time;
//! - `gedi_l2a/shot_six_groups`: NASA's L2A algorithm (`forest::gedi_l2a`) on the same shots,
//!   all six setting groups per shot;
//! - `metrics/survey_line`: the survey line's mix of raw simulated pulses (1 000, every 4th of
//!   the first 4 000 of `config/scenes/survey_line.toml`) through the stage as replay runs it;
//! - `metrics/survey_line_dem_edge`: the same with `ground = "dem"` (each pulse given a nadir
//!   geometry that crosses a flat 1 m DEM inside its window) and `top = "leading_edge"`.
//!
//! - `metrics/csv_row`: one row of `pulse_metrics.csv` (`forest::products::format_row`, 150
//!   columns with 20 PAVD bins) for the survey line's metrics, as the run's sink writes it;
//! - `fixed_text/push_fixed` against `fixed_text/std_format`: the 150 numbers of such rows
//!   written with `core::fixed_text::push_fixed` and with `write!("{:.N}")` (same text).
//!
//! Criterion reports the mean per pulse (throughput); the bench also prints the mean, p50, p99
//! and p99.9 of single-pulse timings (three passes, `Instant` per pulse) for the tail.

#[path = "common/survey.rs"]
mod survey;

use std::hint::black_box;
use std::time::Instant;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::forest::measure::Metrics;
use fwlidar::forest::pulse_metrics::{MetricsComputer, MetricsConfig, WaveformInput};
use fwlidar::format::gedi::GediL1b;

fn tail(name: &str, mut times: Vec<u64>) {
    times.sort_unstable();
    let q = |f: f64| times[((times.len() - 1) as f64 * f).round() as usize] as f64 / 1e3;
    let mean = times.iter().sum::<u64>() as f64 / times.len() as f64 / 1e3;
    println!(
        "{name}: {} timings: mean {mean:.2} µs, p50 {:.2}, p99 {:.2}, p99.9 {:.2}, max {:.2} µs",
        times.len(),
        q(0.5),
        q(0.99),
        q(0.999),
        q(1.0)
    );
}

/// The fixture's 32 GEDI shots: received waveform (counts), noise mean and σ.
fn gedi_shots() -> Vec<(Vec<f32>, f64, f64)> {
    let g = GediL1b::open(&fwlidar::fixtures::path(
        "waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5",
    ))
    .unwrap();
    let mut shots = Vec::new();
    for name in g.beams() {
        let beam = g.read_beam(name).unwrap();
        let (mut rx, mut tx) = (Vec::new(), Vec::new());
        g.read_waveforms(&beam, 0..beam.shots.len(), &mut rx, &mut tx)
            .unwrap();
        let base = beam.shots[0].rx_start;
        for s in &beam.shots {
            let off = (s.rx_start - base) as usize;
            shots.push((
                rx[off..off + s.rx_count as usize].to_vec(),
                s.noise_mean,
                s.noise_stddev,
            ));
        }
    }
    shots
}

fn gedi(c: &mut Criterion) {
    let shots = gedi_shots();
    let config = MetricsConfig::default();
    let mut computer = MetricsComputer::with_capacity(2048);
    let one = |i: usize| {
        let (w, mean, sd) = &shots[i % shots.len()];
        computer.compute(
            &config,
            &WaveformInput {
                pulse_sigma_ns: 0.0,
                samples: w,
                start_ns: 0.0,
                sample_ns: 1.0,
                noise_mean: *mean,
                noise_sd: *sd,
                smoothing_ns: 6.5,
                geometry: None,
                geographic: false,
            },
        )
    };
    per_shot(c, "metrics/gedi_shot", shots.len(), one);
}

/// Times `one(i)` on each of `n` shots 20 times (the tail), then criterion's mean.
fn per_shot<R>(c: &mut Criterion, name: &str, n: usize, mut one: impl FnMut(usize) -> R) {
    let mut times = Vec::new();
    for _ in 0..20 {
        for i in 0..n {
            let t0 = Instant::now();
            black_box(one(i));
            times.push(t0.elapsed().as_nanos() as u64);
        }
    }
    tail(name, times);
    let mut i = 0;
    c.bench_function(name, |b| {
        b.iter(|| {
            i += 1;
            black_box(one(i))
        })
    });
}

/// NASA's L2A algorithm (`src/forest/gedi_l2a.rs`) on each of the fixture's 32 shots, all six
/// setting groups at once (what L2A computes per shot), 0.15 m per sample.
fn gedi_l2a(c: &mut Criterion) {
    use fwlidar::forest::gedi_l2a::{GROUPS, process_groups};
    let shots = gedi_shots();
    let one = |i: usize| {
        let (w, mean, sd) = &shots[i % shots.len()];
        process_groups(w, *mean as f32, *sd as f32, 0.15, &GROUPS)
    };
    per_shot(c, "gedi_l2a/shot_six_groups", shots.len(), one);
}

fn survey_line(c: &mut Criterion) {
    let pulses: Vec<_> = survey::survey_line_pulses(1000, 4, None)
        .into_iter()
        .map(|(p, _)| p)
        .collect();
    let mut stage = Metrics::new(MetricsConfig::default());
    let mut times = Vec::new();
    for _ in 0..3 {
        for p in &pulses {
            let t0 = Instant::now();
            black_box(stage.measure(p));
            times.push(t0.elapsed().as_nanos() as u64);
        }
    }
    tail("metrics/survey_line", times);
    let mut i = 0;
    c.bench_function("metrics/survey_line", |b| {
        b.iter(|| {
            i += 1;
            black_box(stage.measure(&pulses[i % pulses.len()]))
        })
    });
}

fn survey_line_dem_edge(c: &mut Criterion) {
    use fwlidar::forest::pulse_metrics::{RunDem, TopFrom};
    use fwlidar::pulse::waveform_metrics::GroundFrom;
    use fwlidar::pulse::{PulseGeometry, SegmentKind};
    let half_c = fwlidar::core::units::HALF_C_M_PER_NS;
    let pulses: Vec<_> = survey::survey_line_pulses(1000, 4, None)
        .into_iter()
        .map(|(mut p, _)| {
            // Nadir, over (500, 500), the DEM (z = 0) crossed 2/3 into the return window.
            let ret = p
                .segments
                .iter()
                .find(|s| s.kind == SegmentKind::Return)
                .copied();
            if let Some(s) = ret {
                let t = s.start_ns + 2.0 / 3.0 * s.len as f64 * p.sample_ns;
                p.geometry = Some(PulseGeometry {
                    anchor: [500.0, 500.0, t * half_c],
                    direction: [0.0, 0.0, -half_c],
                });
            }
            p
        })
        .collect();
    let dem = fwlidar::geo::dem::Dem::from_heights(
        (100, 100),
        [450.5, 549.5],
        [1.0, 1.0],
        None,
        vec![0.0; 10_000],
    )
    .unwrap();
    let config = MetricsConfig {
        ground: GroundFrom::Dem,
        top: TopFrom::LeadingEdge,
        dem: Some(RunDem(std::sync::Arc::new(dem))),
        ..MetricsConfig::default()
    };
    let mut stage = Metrics::new(config);
    let mut times = Vec::new();
    for _ in 0..3 {
        for p in &pulses {
            let t0 = Instant::now();
            black_box(stage.measure(p));
            times.push(t0.elapsed().as_nanos() as u64);
        }
    }
    tail("metrics/survey_line_dem_edge", times);
    let mut i = 0;
    c.bench_function("metrics/survey_line_dem_edge", |b| {
        b.iter(|| {
            i += 1;
            black_box(stage.measure(&pulses[i % pulses.len()]))
        })
    });
}

fn csv_row(c: &mut Criterion) {
    use fwlidar::core::fixed_text::push_fixed;
    use fwlidar::forest::products::format_row;
    use std::fmt::Write as _;
    let pulses: Vec<_> = survey::survey_line_pulses(1000, 4, None)
        .into_iter()
        .map(|(p, _)| p)
        .collect();
    let mut stage = Metrics::new(MetricsConfig::default());
    let metrics: Vec<_> = pulses.iter().map(|p| stage.measure(p)).collect();
    let mut line = String::with_capacity(4096);
    let mut times = Vec::new();
    for _ in 0..3 {
        for (i, m) in metrics.iter().enumerate() {
            let t0 = Instant::now();
            format_row(
                &mut line,
                i as u64,
                Some(1.0e5 + i as f64 * 2.5e-6),
                false,
                m,
                20,
                f32::NAN,
            );
            black_box(&line);
            times.push(t0.elapsed().as_nanos() as u64);
        }
    }
    tail("metrics/csv_row", times);
    let mut i = 0;
    c.bench_function("metrics/csv_row", |b| {
        b.iter(|| {
            i += 1;
            let m = &metrics[i % metrics.len()];
            format_row(
                &mut line,
                i as u64,
                Some(1.0e5 + i as f64 * 2.5e-6),
                false,
                m,
                20,
                f32::NAN,
            );
            black_box(line.len())
        })
    });
    // The numbers of those rows with their decimals, written both ways.
    let numbers: Vec<(f64, usize)> = metrics
        .iter()
        .flat_map(|m| {
            let mut v: Vec<(f64, usize)> = m.rh.iter().map(|&x| (f64::from(x), 3)).collect();
            v.extend(m.pavd[..20].iter().map(|&x| (f64::from(x), 6)));
            v.extend(m.ground_xyz.iter().map(|&x| (x, 3)));
            v.extend([(f64::from(m.cover), 5), (f64::from(m.energy_total), 2)]);
            v
        })
        .filter(|(x, _)| x.is_finite())
        .collect();
    let per_row = numbers.len() / metrics.len().max(1);
    let mut group = c.benchmark_group("fixed_text");
    group.throughput(criterion::Throughput::Elements(per_row as u64));
    let mut j = 0;
    group.bench_function("push_fixed", |b| {
        b.iter(|| {
            line.clear();
            for _ in 0..per_row {
                let (x, d) = numbers[j % numbers.len()];
                j += 1;
                push_fixed(&mut line, x, d);
            }
            black_box(line.len())
        })
    });
    let mut j = 0;
    group.bench_function("std_format", |b| {
        b.iter(|| {
            line.clear();
            for _ in 0..per_row {
                let (x, d) = numbers[j % numbers.len()];
                j += 1;
                let _ = write!(line, "{x:.d$}");
            }
            black_box(line.len())
        })
    });
    group.finish();
}

criterion_group!(
    benches,
    gedi,
    gedi_l2a,
    survey_line,
    survey_line_dem_edge,
    csv_row
);
criterion_main!(benches);
