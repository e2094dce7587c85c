//! PulseWaves read throughput: open a `.pls` + `.wvs` pair and read and decode every pulse
//! into one reused `Pulse`, files in the page cache. Throughput is in bytes of the `.wvs` file
//! (the waveform data). Reads `tests/data` (or `$FWLIDAR_FIXTURES`); results are
//! recorded in `docs/performance.md`.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::format::pulsewaves::PulseWavesReader;
use fwlidar::pulse::Pulse;

fn fixtures() -> PathBuf {
    fwlidar::fixtures::dir()
}

fn read_file(c: &mut Criterion) {
    let dir = fixtures().join("waveform");
    let mut g = c.benchmark_group("pulsewaves_read");
    for (name, stem) in [
        ("riegl_q680i", "riegl_q680i/100429_152240_2535pt_UTM"),
        ("lvis", "pulsewaves/lvis_example1"),
    ] {
        let pls = dir.join(format!("{stem}.pls"));
        let wvs_len = std::fs::metadata(pls.with_extension("wvs"))
            .expect("the .wvs fixture")
            .len();
        g.throughput(Throughput::Bytes(wvs_len));
        let mut pulse = Pulse::default();
        g.bench_function(name, |b| {
            b.iter(|| {
                let mut r = PulseWavesReader::open(&pls).expect("fixture opens");
                let mut samples = 0usize;
                while r.read_pulse(&mut pulse).expect("fixture reads") {
                    samples += pulse.raw.len();
                }
                black_box(samples)
            })
        });
    }
    g.finish();
}

criterion_group!(benches, read_file);
criterion_main!(benches);
