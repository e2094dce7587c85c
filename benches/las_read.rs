//! LAS waveform read throughput: every pulse of the real RIEGL file
//! (`waveform/riegl_q680i/100429_152240_2535pt_UTM.las` + `.wdp`, 2535 points, 2376 pulses, from
//! the repository's `tests/data`, or `$FWLIDAR_FIXTURES`), opened and
//! decoded into one reused pulse, from the page cache (`LasReader::open`) and from memory
//! (`LasReader::from_bytes`). Throughput is in bytes of the `.wdp` (the waveform data).
//! Results are recorded in `docs/performance.md`.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::format::las_read::LasReader;
use fwlidar::pulse::Pulse;

fn fixture() -> PathBuf {
    fwlidar::fixtures::path("waveform/riegl_q680i/100429_152240_2535pt_UTM.las")
}

fn las_read(c: &mut Criterion) {
    let las = fixture();
    let wdp = las.with_extension("wdp");
    let las_bytes = std::fs::read(&las).expect("las");
    let wdp_bytes = std::fs::read(&wdp).expect("wdp");
    let mut g = c.benchmark_group("las_read");
    g.throughput(Throughput::Bytes(wdp_bytes.len() as u64));
    let mut pulse = Pulse::default();
    g.bench_function("riegl_q680i_file", |b| {
        b.iter(|| {
            let mut r = LasReader::open(&las).expect("open");
            let mut n = 0u64;
            while r.next_pulse(&mut pulse).expect("pulse") {
                n += u64::from(pulse.raw[0]);
            }
            black_box(n)
        })
    });
    g.bench_function("riegl_q680i_memory", |b| {
        b.iter(|| {
            let mut r = LasReader::from_bytes(&las_bytes, Some(&wdp_bytes)).expect("open");
            let mut n = 0u64;
            while r.next_pulse(&mut pulse).expect("pulse") {
                n += u64::from(pulse.raw[0]);
            }
            black_box(n)
        })
    });
    g.finish();
}

criterion_group!(benches, las_read);
criterion_main!(benches);
