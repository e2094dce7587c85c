//! Capture read (and write) throughput: a ~64 MiB capture of frames with 2 segments x 200 16-bit
//! samples, read from memory (`Cursor`) and from a file in the page cache. Throughput is in bytes
//! of capture. Results are recorded in `docs/performance.md`.

use std::hint::black_box;
use std::io::{Cursor, Read};

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::format::capture::{FlushPolicy, FsyncPolicy};
use fwlidar::format::{CaptureReader, CaptureWriter, Record};
use fwlidar::pulse::{Pulse, SegmentKind};

const TARGET_BYTES: u64 = 64 * 1024 * 1024;

fn no_flush() -> FlushPolicy {
    FlushPolicy {
        every_records: 0,
        every_ms: 0,
        fsync: FsyncPolicy::Never,
    }
}

fn pulse(i: u64) -> Pulse {
    let mut p = Pulse {
        pulse_id: i,
        gps_time: 300_000.0 + i as f64 * 2.5e-6,
        scan_angle_deg: [((i % 1000) as f32 - 500.0) * 0.06, f32::NAN],
        sample_ns: 1.0,
        gain_v_per_dn: 0.002,
        offset_v: -0.05,
        bits: 16,
        ..Pulse::default()
    };
    p.push_segment(
        SegmentKind::Outgoing,
        0,
        -10.0,
        (0..200u64).map(|k| ((k * 37 + i) % 4096) as u16),
    );
    p.push_segment(
        SegmentKind::Return,
        1,
        6000.0 + (i % 50) as f64,
        (0..200u64).map(|k| ((k * 91 + i * 7) % 4096) as u16),
    );
    p
}

/// Frames plus one nav record per 100 frames, until the capture reaches ~64 MiB.
fn build_capture() -> (Vec<u8>, u64) {
    let mut w = CaptureWriter::from_writer(
        Vec::with_capacity(TARGET_BYTES as usize + 4096),
        "bench",
        "sensor = \"bench\"",
        no_flush(),
    )
    .expect("writer");
    let mut i = 0;
    while w.bytes_written() < TARGET_BYTES {
        w.write_pulse(&pulse(i)).expect("frame");
        if i % 100 == 0 {
            w.write_nav(
                1,
                i,
                b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n",
            )
            .expect("nav");
        }
        i += 1;
    }
    (w.finish().expect("finish"), i)
}

fn walk<R: Read>(r: R) -> u64 {
    let mut reader = CaptureReader::new(r, "bench").expect("preamble");
    let mut n = 0u64;
    while let Some(rec) = reader.next_record() {
        if let Ok(Record::Frame(f)) = rec {
            n += black_box(f.payload().len()) as u64;
        }
    }
    assert!(reader.skipped().is_clean());
    n
}

fn walk_decode<R: Read>(r: R, pulse: &mut Pulse) -> u64 {
    let mut reader = CaptureReader::new(r, "bench").expect("preamble");
    let mut n = 0u64;
    while let Some(rec) = reader.next_record() {
        if let Ok(Record::Frame(f)) = rec {
            f.decode_into(pulse).expect("decode");
            n += black_box(pulse.raw.len()) as u64;
        }
    }
    n
}

fn capture_read(c: &mut Criterion) {
    let (bytes, frames) = build_capture();
    let mut group = c.benchmark_group("capture_read");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.sample_size(20);
    eprintln!(
        "capture: {} bytes, {} frames ({} bytes per frame record)",
        bytes.len(),
        frames,
        44 + 16 + 2 * (16 + 400)
    );

    group.bench_function("walk_verify_crc/cursor", |b| {
        b.iter(|| walk(Cursor::new(&bytes)))
    });
    let mut p = Pulse::default();
    group.bench_function("walk_and_decode/cursor", |b| {
        b.iter(|| walk_decode(Cursor::new(&bytes), &mut p))
    });

    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("bench.fwc");
    std::fs::write(&path, &bytes).expect("write capture");
    // warm the page cache
    let _ = std::fs::read(&path).expect("read capture");
    group.bench_function("walk_verify_crc/file", |b| {
        b.iter(|| walk(std::fs::File::open(&path).expect("open")))
    });
    group.bench_function("walk_and_decode/file", |b| {
        b.iter(|| walk_decode(std::fs::File::open(&path).expect("open"), &mut p))
    });
    group.finish();

    let mut group = c.benchmark_group("capture_write");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.sample_size(10);
    let pulses: Vec<Pulse> = (0..1000).map(pulse).collect();
    let mut sink = Vec::with_capacity(bytes.len() + 4096);
    group.bench_function("write_frames/vec", |b| {
        b.iter(|| {
            sink.clear();
            let mut w =
                CaptureWriter::from_writer(&mut sink, "bench", "", no_flush()).expect("writer");
            for i in 0..frames {
                w.write_pulse(&pulses[(i % 1000) as usize]).expect("frame");
                if i % 100 == 0 {
                    w.write_nav(
                        1,
                        i,
                        b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n",
                    )
                    .expect("nav");
                }
            }
            w.finish().expect("finish");
        })
    });
    group.finish();
}

criterion_group!(benches, capture_read);
criterion_main!(benches);
