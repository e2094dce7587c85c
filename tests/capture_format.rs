//! Properties of the native capture format v1.0: round trips, recovery from truncation and
//! damage, resync after garbage, no panics on arbitrary input, and the errors for files that are
//! not (readable) captures.

mod common;

use std::io::Cursor;
use std::path::Path;

use fwlidar::format::capture::{
    FlushPolicy, PREAMBLE_LEN, RECORD_OVERHEAD, SYNC, SkipReport, preamble,
};
use fwlidar::format::{CaptureError, CaptureReader, CaptureWriter, Record};
use fwlidar::pulse::{Pulse, SegmentKind};
use proptest::prelude::*;

/// A record as plain data, comparable bit for bit (floats by their bits, so NaN compares).
#[derive(Clone, Debug, PartialEq)]
enum Rec {
    Header(String),
    Frame(FrameData),
    Nav {
        port: u8,
        receive_time_ns: u64,
        bytes: Vec<u8>,
    },
}

#[derive(Clone, Debug, PartialEq)]
struct FrameData {
    pulse_id: u64,
    gps_time: u64,
    scan_angle_deg: [u32; 2],
    sample_ns: u64,
    gain_v_per_dn: u32,
    offset_v: u32,
    bits: u8,
    /// (outgoing?, channel, start_ns bits, samples)
    segments: Vec<(bool, u8, u64, Vec<u16>)>,
}

impl FrameData {
    fn to_pulse(&self) -> Pulse {
        let mut p = Pulse {
            pulse_id: self.pulse_id,
            gps_time: f64::from_bits(self.gps_time),
            scan_angle_deg: self.scan_angle_deg.map(f32::from_bits),
            sample_ns: f64::from_bits(self.sample_ns),
            gain_v_per_dn: f32::from_bits(self.gain_v_per_dn),
            offset_v: f32::from_bits(self.offset_v),
            bits: self.bits,
            ..Pulse::default()
        };
        for (outgoing, channel, start, samples) in &self.segments {
            let kind = if *outgoing {
                SegmentKind::Outgoing
            } else {
                SegmentKind::Return
            };
            p.push_segment(
                kind,
                *channel,
                f64::from_bits(*start),
                samples.iter().copied(),
            );
        }
        p
    }

    fn from_pulse(p: &Pulse) -> FrameData {
        FrameData {
            pulse_id: p.pulse_id,
            gps_time: p.gps_time.to_bits(),
            scan_angle_deg: p.scan_angle_deg.map(f32::to_bits),
            sample_ns: p.sample_ns.to_bits(),
            gain_v_per_dn: p.gain_v_per_dn.to_bits(),
            offset_v: p.offset_v.to_bits(),
            bits: p.bits,
            segments: p
                .segments
                .iter()
                .enumerate()
                .map(|(i, s)| {
                    (
                        s.kind == SegmentKind::Outgoing,
                        s.channel,
                        s.start_ns.to_bits(),
                        p.raw_of(i).to_vec(),
                    )
                })
                .collect(),
        }
    }
}

/// Bytes a record occupies in the file.
fn record_len(r: &Rec) -> u64 {
    let payload = match r {
        Rec::Header(s) => s.len(),
        Rec::Frame(f) => {
            44 + f
                .segments
                .iter()
                .map(|s| 16 + s.3.len() * f.bits as usize / 8)
                .sum::<usize>()
        }
        Rec::Nav { bytes, .. } => 12 + bytes.len(),
    };
    (RECORD_OVERHEAD + payload) as u64
}

/// Writes `first_header` then `recs`; returns the bytes and the end offset of every record
/// (the first header's included).
fn write_capture(first_header: &str, recs: &[Rec]) -> (Vec<u8>, Vec<u64>) {
    let mut w = CaptureWriter::from_writer(Vec::new(), "mem", first_header, FlushPolicy::default())
        .unwrap();
    let mut ends = vec![w.bytes_written()];
    for r in recs {
        match r {
            Rec::Header(s) => w.write_header(s).unwrap(),
            Rec::Frame(f) => w.write_pulse(&f.to_pulse()).unwrap(),
            Rec::Nav {
                port,
                receive_time_ns,
                bytes,
            } => w.write_nav(*port, *receive_time_ns, bytes).unwrap(),
        }
        ends.push(w.bytes_written());
    }
    (w.finish().unwrap(), ends)
}

/// Reads every record; checks the accounting invariant and returns records and report.
fn read_all(bytes: &[u8]) -> Result<(Vec<Rec>, SkipReport), CaptureError> {
    let mut r = CaptureReader::new(Cursor::new(bytes), "mem")?;
    let mut out = Vec::new();
    let mut pulse = Pulse::default();
    while let Some(rec) = r.next_record() {
        let rec = match rec? {
            Record::Header(s) => Rec::Header(s.to_string()),
            Record::Frame(f) => {
                f.decode_into(&mut pulse)
                    .expect("a frame the reader returns decodes");
                assert_eq!(f.pulse_id(), pulse.pulse_id);
                Rec::Frame(FrameData::from_pulse(&pulse))
            }
            Record::Nav {
                port,
                receive_time_ns,
                bytes,
            } => Rec::Nav {
                port,
                receive_time_ns,
                bytes: bytes.to_vec(),
            },
        };
        out.push(rec);
    }
    let rep = *r.skipped();
    let delivered: u64 = out.iter().map(record_len).sum();
    assert_eq!(
        r.position(),
        bytes.len() as u64,
        "reader consumed everything"
    );
    assert_eq!(
        PREAMBLE_LEN as u64 + delivered + rep.bytes_skipped + rep.truncated_tail_bytes,
        bytes.len() as u64,
        "skip report accounts for every byte: {rep:?}"
    );
    Ok((out, rep))
}

fn frame_strategy() -> impl Strategy<Value = FrameData> {
    (
        any::<u64>(),
        any::<u64>(),
        any::<[u32; 2]>(),
        any::<u64>(),
        any::<u32>(),
        any::<u32>(),
        prop_oneof![Just(8u8), Just(16u8)],
        prop::collection::vec(
            (
                any::<bool>(),
                any::<u8>(),
                any::<u64>(),
                prop::collection::vec(any::<u16>(), 0..300),
            ),
            0..4,
        ),
    )
        .prop_map(
            |(pulse_id, gps_time, scan, sample_ns, gain, offset, bits, mut segments)| {
                if bits == 8 {
                    for s in &mut segments {
                        for v in &mut s.3 {
                            *v &= 0xFF;
                        }
                    }
                }
                FrameData {
                    pulse_id,
                    gps_time,
                    scan_angle_deg: scan,
                    sample_ns,
                    gain_v_per_dn: gain,
                    offset_v: offset,
                    bits,
                    segments,
                }
            },
        )
}

fn rec_strategy() -> impl Strategy<Value = Rec> {
    prop_oneof![
        1 => ".{0,80}".prop_map(Rec::Header),
        4 => frame_strategy().prop_map(Rec::Frame),
        3 => (any::<u8>(), any::<u64>(), prop::collection::vec(any::<u8>(), 0..200)).prop_map(
            |(port, receive_time_ns, bytes)| Rec::Nav {
                port,
                receive_time_ns,
                bytes
            }
        ),
    ]
}

/// A small deterministic capture of ~20 records with no accidental sync markers in payloads.
fn small_capture() -> (Vec<Rec>, Vec<u8>, Vec<u64>) {
    let mut recs = Vec::new();
    for i in 0..20u64 {
        let r = match i % 5 {
            0 | 2 => {
                let bits = if i % 2 == 0 { 16 } else { 8 };
                Rec::Frame(FrameData {
                    pulse_id: 1000 + i,
                    gps_time: (3600.0 + i as f64 * 1e-5).to_bits(),
                    scan_angle_deg: [(i as f32 - 10.0).to_bits(), f32::NAN.to_bits()],
                    sample_ns: 1.0f64.to_bits(),
                    gain_v_per_dn: 0.01f32.to_bits(),
                    offset_v: 0.0f32.to_bits(),
                    bits,
                    segments: (0..(i % 3) as u8)
                        .map(|s| {
                            (
                                s == 0,
                                s,
                                (s as f64 * 100.0).to_bits(),
                                (0..(5 + i as u16)).map(|k| k * 3 + s as u16).collect(),
                            )
                        })
                        .collect(),
                })
            }
            1 | 3 => Rec::Nav {
                port: (i % 3) as u8,
                receive_time_ns: 1_700_000_000_000_000_000 + i,
                bytes: format!("$GPGGA,{i},4807.038,N*47\r\n").into_bytes(),
            },
            _ => Rec::Header(format!("segment = {i}\nsensor = \"sim\"")),
        };
        recs.push(r);
    }
    let (bytes, ends) = write_capture("sensor = \"sim\"", &recs);
    let mut all = vec![Rec::Header("sensor = \"sim\"".into())];
    all.extend(recs);
    (all, bytes, ends)
}

#[test]
fn small_capture_reads_back_clean() {
    let (recs, bytes, ends) = small_capture();
    assert_eq!(*ends.last().unwrap(), bytes.len() as u64);
    let (got, rep) = read_all(&bytes).unwrap();
    assert_eq!(got, recs);
    assert!(rep.is_clean(), "{rep:?}");
}

#[test]
fn truncation_at_every_offset_recovers_every_complete_record() {
    let (recs, bytes, ends) = small_capture();
    for cut in 0..=bytes.len() {
        let part = &bytes[..cut];
        if cut < PREAMBLE_LEN {
            let err = read_all(part).unwrap_err();
            if cut == 0 {
                assert!(matches!(err, CaptureError::Empty { .. }), "{err}");
            } else {
                assert!(
                    matches!(err, CaptureError::TruncatedPreamble { len, .. } if len == cut),
                    "{err}"
                );
            }
            continue;
        }
        let complete = ends.iter().filter(|&&e| e <= cut as u64).count();
        let last_end = if complete == 0 {
            PREAMBLE_LEN as u64
        } else {
            ends[complete - 1]
        };
        let (got, rep) = read_all(part).unwrap();
        assert_eq!(got, recs[..complete], "cut at {cut}");
        assert_eq!(rep.bytes_skipped, 0, "cut at {cut}: {rep:?}");
        assert_eq!(rep.resyncs, 0, "cut at {cut}: {rep:?}");
        assert_eq!(
            rep.truncated_tail_bytes,
            cut as u64 - last_end,
            "cut at {cut}: {rep:?}"
        );
    }
}

#[test]
fn flipping_any_record_byte_loses_only_that_record() {
    let (recs, bytes, ends) = small_capture();
    let mut starts = vec![PREAMBLE_LEN as u64];
    starts.extend_from_slice(&ends[..ends.len() - 1]);
    for at in PREAMBLE_LEN..bytes.len() {
        let mut damaged = bytes.clone();
        damaged[at] ^= 0xFF;
        let k = ends.iter().position(|&e| e > at as u64).unwrap();
        let mut want = recs.clone();
        want.remove(k);
        let (got, rep) = read_all(&damaged).unwrap();
        assert_eq!(got, want, "byte {at} flipped (record {k})");
        let len = ends[k] - starts[k];
        if k + 1 < recs.len() {
            assert_eq!(rep.bytes_skipped, len, "byte {at}: {rep:?}");
            assert_eq!(rep.resyncs, 1, "byte {at}: {rep:?}");
            assert_eq!(rep.truncated_tail_bytes, 0, "byte {at}: {rep:?}");
        } else {
            assert_eq!(rep.bytes_skipped, 0, "byte {at}: {rep:?}");
            assert_eq!(rep.truncated_tail_bytes, len, "byte {at}: {rep:?}");
        }
        assert!(rep.bad_checksums <= 1 + len, "byte {at}: {rep:?}");
    }
}

#[test]
fn damaged_length_field_pointing_past_the_end_does_not_hide_later_records() {
    let (recs, bytes, ends) = small_capture();
    // record 3's payload_len says "huge but under the maximum": runs past EOF
    let at = ends[2] as usize + 8;
    let mut damaged = bytes.clone();
    damaged[at..at + 4].copy_from_slice(&(1024 * 1024u32).to_le_bytes());
    let (got, rep) = read_all(&damaged).unwrap();
    let mut want = recs.clone();
    want.remove(3);
    assert_eq!(got, want);
    assert_eq!(rep.resyncs, 1);
    assert_eq!(rep.truncated_tail_bytes, 0);
    assert_eq!(rep.bytes_skipped, ends[3] - ends[2]);
}

#[test]
fn error_files_name_their_path() {
    let dir = tempfile::tempdir().unwrap();
    let check = |name: &str, content: &[u8], want: fn(&CaptureError) -> bool| {
        let path = dir.path().join(name);
        std::fs::write(&path, content).unwrap();
        let err = match CaptureReader::open(&path) {
            Err(e) => e,
            Ok(_) => panic!("{name} opened"),
        };
        assert!(want(&err), "{name}: {err:?}");
        assert!(
            err.to_string().contains(&path.display().to_string()),
            "{name}: {err}"
        );
    };
    check("empty.fwc", b"", |e| {
        matches!(e, CaptureError::Empty { .. })
    });
    check(
        "magic.fwc",
        b"\x89FWLCAQ\n\x01\x00\x00\x00\x00\x00\x00\x00",
        |e| matches!(e, CaptureError::NotACapture { .. }),
    );
    check("text.fwc", b"sensor = \"not a capture\"\n", |e| {
        matches!(e, CaptureError::NotACapture { .. })
    });
    let mut newer = preamble();
    newer[8..10].copy_from_slice(&2u16.to_le_bytes());
    newer[10..12].copy_from_slice(&1u16.to_le_bytes());
    check("newer.fwc", &newer, |e| {
        matches!(
            e,
            CaptureError::NewerVersion {
                major: 2,
                minor: 1,
                ..
            }
        )
    });
    let missing = dir.path().join("missing.fwc");
    let err = match CaptureReader::open(&missing) {
        Err(e) => e,
        Ok(_) => panic!("opened a missing file"),
    };
    assert!(matches!(err, CaptureError::Io { .. }));
    assert!(err.to_string().contains("missing.fwc"));
}

#[test]
fn newer_minor_is_read_and_unknown_kinds_are_counted() {
    let (recs, mut bytes, ends) = small_capture();
    bytes[10..12].copy_from_slice(&4u16.to_le_bytes());
    let mut future = SYNC.to_vec();
    future.extend_from_slice(&[200, 0, 0, 0]);
    future.extend_from_slice(&5u32.to_le_bytes());
    future.extend_from_slice(b"hello");
    let crc = crc32c::crc32c(&future[4..]);
    future.extend_from_slice(&crc.to_le_bytes());
    let at = ends[4] as usize;
    bytes.splice(at..at, future.iter().copied());
    let r = CaptureReader::new(Cursor::new(&bytes), "mem").unwrap();
    assert_eq!(r.version(), (1, 4));
    let (got, rep) = read_all(&bytes).unwrap();
    assert_eq!(got, recs);
    assert_eq!(rep.unknown_kinds, 1);
    assert_eq!(rep.bytes_skipped, future.len() as u64);
    assert_eq!(rep.resyncs, 0);
}

#[test]
fn create_refuses_to_overwrite() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("precious.fwc");
    std::fs::write(&path, b"precious bytes").unwrap();
    let err = match CaptureWriter::create(&path, "x = 1", FlushPolicy::default()) {
        Err(e) => e,
        Ok(_) => panic!("create overwrote an existing file"),
    };
    assert!(matches!(err, CaptureError::AlreadyExists { .. }), "{err:?}");
    assert!(err.to_string().contains("precious.fwc"));
    assert_eq!(std::fs::read(&path).unwrap(), b"precious bytes");
}

#[test]
fn file_round_trip_and_append_after_a_crash() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("flight.fwc");
    let (recs, _, _) = small_capture();
    let mut w = CaptureWriter::create(&path, "sensor = \"sim\"", FlushPolicy::default()).unwrap();
    for r in &recs[1..] {
        match r {
            Rec::Header(s) => w.write_header(s).unwrap(),
            Rec::Frame(f) => w.write_pulse(&f.to_pulse()).unwrap(),
            Rec::Nav {
                port,
                receive_time_ns,
                bytes,
            } => w.write_nav(*port, *receive_time_ns, bytes).unwrap(),
        }
    }
    w.finish().unwrap();
    let full = std::fs::read(&path).unwrap();
    assert_eq!(read_all(&full).unwrap().0, recs);

    // a crash left half a record at the end; a restarted recorder appends a new segment
    let cut = full.len() - 7;
    std::fs::write(&path, &full[..cut]).unwrap();
    let mut w = CaptureWriter::append(&path, "restarted = true", FlushPolicy::default()).unwrap();
    w.write_nav(1, 5, b"after restart").unwrap();
    w.finish().unwrap();

    let mut r = CaptureReader::open(&path).unwrap();
    let mut count = 0;
    while let Some(rec) = r.next_record() {
        rec.unwrap();
        count += 1;
    }
    let (got, rep) = read_all(&std::fs::read(&path).unwrap()).unwrap();
    assert_eq!(*r.skipped(), rep);
    assert_eq!(count, got.len());
    let n = recs.len();
    assert_eq!(got[..n - 1], recs[..n - 1]);
    assert_eq!(
        got[n - 1..],
        [
            Rec::Header("restarted = true".into()),
            Rec::Nav {
                port: 1,
                receive_time_ns: 5,
                bytes: b"after restart".to_vec()
            }
        ]
    );
    assert_eq!(rep.resyncs, 1);
    assert_eq!(rep.bytes_skipped, record_len(&recs[n - 1]) - 7);
    assert_eq!(rep.truncated_tail_bytes, 0);
}

proptest! {
    #![proptest_config(common::proptest_cases(64, "proptest-regressions/tests/capture_format.txt"))]

    #[test]
    fn round_trip(first in ".{0,40}", recs in prop::collection::vec(rec_strategy(), 0..40)) {
        let (bytes, ends) = write_capture(&first, &recs);
        prop_assert_eq!(*ends.last().unwrap(), bytes.len() as u64);
        let (got, rep) = read_all(&bytes).unwrap();
        let mut want = vec![Rec::Header(first)];
        want.extend(recs);
        prop_assert_eq!(got, want);
        prop_assert!(rep.is_clean(), "{:?}", rep);
    }

    #[test]
    fn garbage_between_records_is_skipped_and_counted(
        recs in prop::collection::vec(rec_strategy(), 1..20),
        junk in prop::collection::vec((any::<prop::sample::Index>(), prop::collection::vec(any::<u8>(), 1..100)), 1..6),
    ) {
        let (bytes, ends) = write_capture("h = 1", &recs);
        // insertion points: record boundaries (after the preamble .. end of file)
        let mut bounds = vec![PREAMBLE_LEN as u64];
        bounds.extend_from_slice(&ends);
        let mut inserts: Vec<(usize, Vec<u8>)> = junk
            .into_iter()
            .map(|(i, g)| (bounds[i.index(bounds.len())] as usize, g))
            .collect();
        inserts.sort_by_key(|(at, _)| *at);
        let mut damaged = Vec::new();
        let mut from = 0;
        let (mut mid, mut tail, mut episodes) = (0u64, 0u64, std::collections::BTreeSet::new());
        for (at, g) in &inserts {
            damaged.extend_from_slice(&bytes[from..*at]);
            damaged.extend_from_slice(g);
            from = *at;
            if *at == bytes.len() {
                tail += g.len() as u64;
            } else {
                mid += g.len() as u64;
                episodes.insert(*at);
            }
        }
        damaged.extend_from_slice(&bytes[from..]);
        let (got, rep) = read_all(&damaged).unwrap();
        let mut want = vec![Rec::Header("h = 1".into())];
        want.extend(recs);
        prop_assert_eq!(got, want);
        prop_assert_eq!(rep.bytes_skipped, mid);
        prop_assert_eq!(rep.truncated_tail_bytes, tail);
        prop_assert_eq!(rep.resyncs, episodes.len() as u64);
    }

    #[test]
    fn arbitrary_bytes_never_panic(body in prop::collection::vec(any::<u8>(), 0..4096), with_preamble in any::<bool>()) {
        let mut bytes = Vec::new();
        if with_preamble {
            bytes.extend_from_slice(&preamble());
        }
        bytes.extend_from_slice(&body);
        let _ = read_all(&bytes);
    }

    #[test]
    fn sync_rich_noise_never_panics(parts in prop::collection::vec(
        prop_oneof![
            Just(SYNC.to_vec()),
            prop::collection::vec(any::<u8>(), 0..24),
            (any::<u8>(), 0u32..64).prop_map(|(k, n)| { let mut v = vec![k, 0, 0, 0]; v.extend_from_slice(&n.to_le_bytes()); v }),
        ],
        0..200,
    )) {
        let mut bytes = preamble().to_vec();
        for p in parts {
            bytes.extend_from_slice(&p);
        }
        let _ = read_all(&bytes);
    }

    #[test]
    fn damage_never_yields_altered_records(
        recs in prop::collection::vec(rec_strategy(), 1..15),
        hits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
    ) {
        let (bytes, _) = write_capture("h = 2", &recs);
        let mut damaged = bytes.clone();
        let body = damaged.len() - PREAMBLE_LEN;
        for (i, v) in hits {
            damaged[PREAMBLE_LEN + i.index(body)] = v;
        }
        let (got, _) = read_all(&damaged).unwrap();
        let mut originals = vec![Rec::Header("h = 2".into())];
        originals.extend(recs);
        // every record read back is one of the originals, in order
        let mut it = originals.iter();
        for g in &got {
            prop_assert!(it.any(|o| o == g), "altered or reordered record {:?}", g);
        }
    }
}

#[test]
fn tempdir_path_is_absolute() {
    // guard for the error-message checks above: they look for the full path
    let dir = tempfile::tempdir().unwrap();
    assert!(Path::new(dir.path()).is_absolute());
}
