//! Navigation framer + decoders throughput (`docs/performance.md`): real receiver bytes from
//! `tests/data/nav/` repeated into ~4 MiB streams — the OxTS NMEA log (PASHR 25 Hz, GGA
//! 10 Hz; gpsd's `#` comment lines removed) and the NovAtel SPAN binary capture — fed to a
//! `NavDecoder` in 4 KiB reads, as a serial port would deliver them. Throughput in input bytes.
//! Also: trajectory lookup + interpolation at a pulse time, and one pulse's georeferencing
//! (geometry from the pose, then 256 bins stepped along it).

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::geo::OutputCrs;
use fwlidar::geo::direct_georeference::{Mounting, georeference};
use fwlidar::nav::dating::GpsTime;
use fwlidar::nav::decoder::NavDecoder;
use fwlidar::nav::trajectory::{Trajectory, TrajectoryConfig};
use fwlidar::nav::{NavKind, NavSample, NavTime};

const TARGET: usize = 4 << 20;

fn fixture(rel: &str) -> Vec<u8> {
    let p = fwlidar::fixtures::path(rel);
    std::fs::read(&p).unwrap_or_else(|e| panic!("fixture {}: {e}", p.display()))
}

fn repeat(unit: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(TARGET + unit.len());
    while v.len() < TARGET {
        v.extend_from_slice(unit);
    }
    v
}

fn bench(c: &mut Criterion) {
    let nmea: Vec<u8> = fixture("nav/gpsd/rst39.log")
        .split_inclusive(|&b| b == b'\n')
        .filter(|l| !l.starts_with(b"#"))
        .flatten()
        .copied()
        .collect();
    let streams = [
        ("nmea_oxts", repeat(&nmea)),
        (
            "novatel_span",
            repeat(&fixture("nav/novatel/corrimudata.pcap.payload.bin")),
        ),
    ];
    let mut g = c.benchmark_group("nav_decode");
    for (name, bytes) in &streams {
        g.throughput(Throughput::Bytes(bytes.len() as u64));
        g.bench_function(*name, |b| {
            b.iter(|| {
                let mut dec = NavDecoder::new(18.0, 512, None);
                let mut n = 0u64;
                for chunk in bytes.chunks(4096) {
                    dec.push(chunk, &mut |s, t| {
                        n += 1;
                        black_box((s, t));
                    });
                }
                dec.finish(&mut |_, _| {});
                black_box(n)
            })
        });
    }
    g.finish();

    // Trajectory lookup + interpolation at a pulse's time, 200 Hz INS with velocities.
    let mut tr = Trajectory::new(TrajectoryConfig::default());
    for k in 0..2000 {
        let t = GpsTime {
            week: 2000,
            sow: 1000.0 + k as f64 * 0.005,
        };
        let mut s = NavSample::new(NavKind::Inspva, NavTime::None);
        s.lat = Some(47.8 + k as f64 * 1e-6);
        s.lon = Some(13.4);
        s.height = Some(1000.0);
        s.vel_north = Some(60.0);
        s.vel_east = Some(0.0);
        s.vel_up = Some(0.0);
        s.roll = Some(1.0);
        s.pitch = Some(2.0);
        // A turn at 2 degrees per second through north (0.01 degrees per INS sample).
        s.heading = Some((359.0 + k as f64 * 0.01).rem_euclid(360.0));
        tr.push(t, &s);
    }
    let t0 = tr
        .time_of(GpsTime {
            week: 2000,
            sow: 1000.0,
        })
        .unwrap();
    let mut g = c.benchmark_group("georeference");
    let mut k = 0u64;
    g.bench_function("trajectory_lookup_and_interpolation", |b| {
        b.iter(|| {
            k = (k + 7919) % 1_990_000;
            let t = t0 + k as f64 * 5e-6;
            black_box((tr.position_at(black_box(t)), tr.attitude_at(black_box(t))))
        })
    });
    let crs = OutputCrs::from_epsg(32633).unwrap();
    let mount = Mounting {
        lever_arm_m: [0.1, 0.2, -0.3],
        boresight_deg: [0.01, -0.02, 0.03],
        refractive_index: 1.00027,
    };
    let pos = tr.position_at(t0 + 1.0).unwrap();
    let att = tr.attitude_at(t0 + 1.0).unwrap();
    // One pulse 12.5° off nadir, its return window 4000..4256 ns.
    let place = || {
        georeference(
            &crs,
            pos,
            &att,
            [black_box(12.5), f32::NAN],
            &mount,
            (4000.0, 4256.0),
        )
        .unwrap()
    };
    g.bench_function("pulse_geometry_only", |b| b.iter(|| black_box(place())));
    // Every bin's position in f64: `anchor + t · direction` for t = 4000, 4001, ... ns.
    let mut bins = vec![[0.0f64; 3]; 256];
    g.bench_function("pulse_geometry_and_256_bins", |b| {
        b.iter(|| {
            let geo = place().geometry;
            let d = geo.direction;
            // The first bin's position, then i bins on (an i32 index converts to f64 in SIMD).
            let a = [0, 1, 2].map(|k| geo.anchor[k] + 4000.0 * d[k]);
            for (i, p) in bins.iter_mut().enumerate() {
                let t = i as i32 as f64;
                *p = [a[0] + t * d[0], a[1] + t * d[1], a[2] + t * d[2]];
            }
            black_box(&bins);
        })
    });
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
