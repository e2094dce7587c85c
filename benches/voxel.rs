//! Voxel tiles: depositing the 256 return bins of one pulse (steady state, tile open), nadir and
//! 20° off nadir, with and without the footprint spread; writing one tile to the store
//! (uncompressed bytes per second, gzip level 1 and fsync included).
//!
//! `voxel_deposit_survey_line/all_pulses`: the deposit of [`MIX_PULSES`] survey-line pulses
//! (`config/scenes/survey_line.toml`, consecutive shots as the sink receives them — 1.75 scan
//! sweeps at the line's start and as many over the stand of trees; 256 return bins each, ±15°
//! scan from 1000 m) on the on-board grid (1 × 1 × 0.5 m,
//! `config/onboard.toml`), calibrated as the on-board chain leaves them, every tile open (steady
//! state). Criterion reports the time per pass over all pulses; the bench also prints the mean,
//! p50, p99 and p99.9 of single-pulse timings (`Instant` per pulse, each pulse's fastest of three
//! passes: a pass preempted on a loaded machine does not count).

#[path = "common/survey.rs"]
mod survey;

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::pulse::{Calibration, Pulse, PulseGeometry, SegmentKind};
use fwlidar::voxel::grid::{Grid, Placer, VoxelConfig};
use fwlidar::voxel::tile::TileData;
use fwlidar::voxel::tiles::TileSet;
use fwlidar::voxel::voxelise::{DepositParams, DepositStats, deposit_pulse};
use fwlidar::voxel::zarr::{StoreInfo, ZarrStore};

fn info() -> StoreInfo {
    StoreInfo {
        crs_wkt: None,
        epsg: Some(32736),
        intensity_units: "V".into(),
        run_key: "bench".into(),
        configuration: String::new(),
    }
}

fn cfg() -> VoxelConfig {
    // The defaults: 0.5 × 0.5 × 0.15 m, 32-column tiles, every height on Earth in sparse
    // height chunks of 64 levels.
    VoxelConfig {
        enabled: true,
        extent_m: Some([0.0, 0.0, 1024.0, 1024.0]),
        ..VoxelConfig::default()
    }
}

/// A pulse of 256 return bins from 40 m above the ground downwards, `zenith_deg` off nadir.
fn pulse(zenith_deg: f64) -> Pulse {
    let z = zenith_deg.to_radians();
    let m = 0.1499;
    let mut p = Pulse {
        seq: 1,
        gps_time: 1.0,
        sample_ns: 1.0,
        geometry: Some(PulseGeometry {
            anchor: [500.2, 500.3, 40.0],
            direction: [m * z.sin(), 0.0, -m * z.cos()],
        }),
        ..Default::default()
    };
    p.push_segment(SegmentKind::Return, 0, 0.0, 0..256u16);
    p.signal = (0..256).map(|i| ((i as f32) * 0.1).sin().abs()).collect();
    p
}

fn deposit(c: &mut Criterion) {
    let mut g = c.benchmark_group("voxel_deposit_256_bins");
    g.throughput(Throughput::Elements(1));
    for (name, zenith, footprint) in [
        ("nadir", 0.0, None),
        ("off_nadir_20deg", 20.0, None),
        ("nadir_footprint_0.5mrad", 0.0, Some(0.5e-3)),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let grid = Grid::new(&cfg(), [0.0, 0.0]);
        let store =
            ZarrStore::create_or_open(&dir.path().join("v.zarr"), grid.clone(), info()).unwrap();
        let mut tiles = TileSet::new(store, 64, 1e9);
        let params = DepositParams {
            placer: Placer::new(&grid),
            height: grid.height,
            dem: None,
            inv_quantum: 1e6,
            footprint_divergence_rad: footprint,
        };
        let mut stats = DepositStats::default();
        let mut p = pulse(zenith);
        // Range 1000 m for the footprint: the bins' t counts from emission.
        if footprint.is_some() {
            p.segments[0].start_ns = 6600.0;
            let g0 = p.geometry.as_mut().unwrap();
            g0.anchor[2] = 40.0 + 6600.0 * 0.1499;
        }
        deposit_pulse(&p, &mut tiles, &params, &mut stats).unwrap();
        g.bench_function(name, |b| {
            b.iter(|| {
                p.seq += 1;
                deposit_pulse(black_box(&p), &mut tiles, &params, &mut stats).unwrap()
            })
        });
        assert!(stats.bins_deposited > 0);
    }
    g.finish();
}

fn write(c: &mut Criterion) {
    let mut g = c.benchmark_group("voxel_tile_write");
    let grid = Grid::new(&cfg(), [0.0, 0.0]);
    // A realistic tile: every column holds samples in a 30 m band (ground at 0 m to the canopy
    // top), on the default grid (every height on Earth, sparse height chunks).
    let mut t = TileData::for_grid(&grid);
    let cols = (grid.tile_columns * grid.tile_columns) as usize;
    let levels = grid.levels as usize;
    let ground = (-grid.z_bottom_m / grid.voxel_size_m[2]) as usize;
    for k in ground..ground + 200 {
        for c in 0..cols {
            let o = c * levels + k;
            t.deposit(o, (o as i64 * 7919) % 100_000, (o % 977) as f32 * 1e-3);
            t.pass(o);
        }
    }
    // Throughput: the bytes of the height chunks the tile holds (what is compressed).
    g.throughput(Throughput::Bytes(
        (t.present_count() * grid.chunk_voxels() * 20) as u64,
    ));
    g.sample_size(20);
    g.measurement_time(Duration::from_secs(10));
    let dir = tempfile::tempdir().unwrap();
    let mut store =
        ZarrStore::create_or_open(&dir.path().join("v.zarr"), grid.clone(), info()).unwrap();
    g.bench_function("one_tile_32x32_band30m_zstd1_sparse", |b| {
        b.iter_custom(|iters| {
            let start = Instant::now();
            for i in 0..iters {
                store.write_tile([(i % 16) as i64, 0], &t, i).unwrap();
            }
            start.elapsed()
        })
    });
    g.finish();
}

/// Pulses of the survey-line mix (half at the line's start, half over the trees).
const MIX_PULSES: usize = 10_000;
/// Consecutive shots, as the sink receives them (the cache sees the scan's own reuse).
const MIX_STRIDE: usize = 1;
/// Metres of range per nanosecond of two-way travel (c / 2n, n = 1.00027).
const METRES_PER_NS: f64 = 0.149_855;

/// Survey-line pulses as the on-board chain hands them to the voxel sink: geometry from the
/// simulator's truth (scene frame moved to UTM-sized coordinates, t0 at emission), the signal
/// in volts above the first sample, a range-normalised calibration.
fn survey_line_deposits() -> Vec<Pulse> {
    let mut raw = survey::survey_line_pulses(MIX_PULSES / 2, MIX_STRIDE, None);
    raw.extend(survey::survey_line_pulses(
        MIX_PULSES / 2,
        MIX_STRIDE,
        Some(-100.0),
    ));
    raw.into_iter()
        .map(|(mut p, t)| {
            let o = [357_000.0, 7_235_000.0, 0.0];
            p.geometry = Some(PulseGeometry {
                anchor: [o[0] + t.origin[0], o[1] + t.origin[1], t.origin[2]],
                direction: t.beam.map(|b| b * METRES_PER_NS),
            });
            let base = p.raw[0] as f32;
            p.signal = p
                .raw
                .iter()
                .map(|&r| (r as f32 - base) * p.gain_v_per_dn)
                .collect();
            p.calibration = Some(Calibration {
                scale: 1.0,
                emission_ns: 0.0,
                metres_per_ns: METRES_PER_NS,
                reference_range_m: 1000.0,
                range_normalised: true,
            });
            p
        })
        .collect()
}

/// The deposit of the survey line's pulses (per-pulse figures printed).
fn deposit_survey_line(c: &mut Criterion) {
    let mut pulses = survey_line_deposits();
    let onboard = VoxelConfig {
        enabled: true,
        voxel_size_m: [1.0, 1.0, 0.5],
        ..VoxelConfig::default()
    };
    let first = fwlidar::sink::voxel_tiles::extent_centre(&pulses[0]).unwrap();
    let grid = Grid::new(&onboard, first);
    let dir = tempfile::tempdir().unwrap();
    let store =
        ZarrStore::create_or_open(&dir.path().join("v.zarr"), grid.clone(), info()).unwrap();
    let mut tiles = TileSet::new(store, 100_000, 1e12);
    let params = DepositParams {
        placer: Placer::new(&grid),
        height: grid.height,
        dem: None,
        inv_quantum: 1.0 / grid.intensity_quantum,
        footprint_divergence_rad: None,
    };
    let mut stats = DepositStats::default();
    let n = pulses.len() as u64;
    // One pass over every pulse; with `times`, each pulse's time is kept when it is its
    // fastest so far (a pass preempted on a loaded machine does not count).
    let mut pass = |pulses: &mut [Pulse], times: Option<&mut Vec<u64>>| {
        let mut times = times;
        for (i, p) in pulses.iter_mut().enumerate() {
            p.seq += n;
            let t0 = Instant::now();
            deposit_pulse(black_box(p), &mut tiles, &params, &mut stats).unwrap();
            if let Some(t) = times.as_deref_mut() {
                t[i] = t[i].min(t0.elapsed().as_nanos() as u64);
            }
        }
    };
    pass(&mut pulses, None);
    let mut times = vec![u64::MAX; pulses.len()];
    for _ in 0..3 {
        pass(&mut pulses, Some(&mut times));
    }
    times.sort_unstable();
    let q = |f: f64| times[((times.len() - 1) as f64 * f).round() as usize] as f64 / 1e3;
    let mean = times.iter().sum::<u64>() as f64 / times.len() as f64 / 1e3;
    println!(
        "voxel_deposit_survey_line: {} pulses, {} bins, each pulse's fastest of three passes: \
         mean {mean:.3} µs, p50 {:.3} µs, p99 {:.3} µs, p99.9 {:.3} µs",
        pulses.len(),
        pulses
            .iter()
            .flat_map(|p| p.segments.iter().filter(|s| s.kind == SegmentKind::Return))
            .map(|s| s.len as usize)
            .sum::<usize>(),
        q(0.5),
        q(0.99),
        q(0.999)
    );
    let mut g = c.benchmark_group("voxel_deposit_survey_line");
    g.throughput(Throughput::Elements(n));
    g.bench_function("all_pulses", |b| {
        b.iter_custom(|iters| {
            let t0 = Instant::now();
            for _ in 0..iters {
                pass(&mut pulses, None);
            }
            t0.elapsed()
        })
    });
    g.finish();
}

criterion_group!(benches, deposit, deposit_survey_line, write);
criterion_main!(benches);
