//! Navigation framer + decoders throughput (`docs/performance.md`): real receiver bytes from
//! `../shared/fixtures/nav/` repeated into ~4 MiB streams — the OxTS NMEA log (PASHR 25 Hz, GGA
//! 10 Hz; gpsd's `#` comment lines removed) and the NovAtel SPAN binary capture — fed to a
//! `NavDecoder` in 4 KiB reads, as a serial port would deliver them. Throughput in input bytes.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::nav::decoder::NavDecoder;

const TARGET: usize = 4 << 20;

fn fixture(rel: &str) -> Vec<u8> {
    let base = std::env::var_os("FWLIDAR_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/fixtures"));
    let p = base.join(rel);
    std::fs::read(&p).unwrap_or_else(|e| panic!("missing fixture {}: {e}", p.display()))
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
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = bench
}
criterion_main!(benches);
