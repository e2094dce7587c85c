//! Voxel tiles: depositing the 256 return bins of one pulse (steady state, tile open), nadir and
//! 20° off nadir, with and without the footprint spread; writing one tile to the store
//! (uncompressed bytes per second, gzip level 1 and fsync included).

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::pulse::{Pulse, PulseGeometry, SegmentKind};
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

criterion_group!(benches, deposit, write);
criterion_main!(benches);
