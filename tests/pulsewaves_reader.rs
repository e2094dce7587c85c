//! The PulseWaves reader against the real files of `tests/data/waveform/` (LVIS,
//! a converted LAS 1.3 file, the PulseWaves library's own test file, a RIEGL LMS-Q680i line):
//! counts, segment layouts, values cross-checked with an independent decoding of the raw bytes,
//! geometry, damaged inputs (clear errors naming file and field, never a panic) and the CLI.
//!
//! The fixtures are required: without them every test fails naming the folder looked for.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use fwlidar::format::pulsewaves::{PulseWavesError, PulseWavesReader, TimeBase};
use fwlidar::pipeline::ports::SourceEvent;
use fwlidar::pulse::{Pulse, SegmentKind};
use fwlidar::source;

/// The fixtures folder (`tests/data`, or `$FWLIDAR_FIXTURES`).
fn fixtures() -> PathBuf {
    fwlidar::fixtures::dir()
}

fn fixture(stem: &str) -> PathBuf {
    let p = fixtures().join("waveform").join(format!("{stem}.pls"));
    assert!(p.is_file(), "fixture missing: {}", p.display());
    p
}

const LVIS: &str = "pulsewaves/lvis_example1";
const LAS13: &str = "pulsewaves/las13fwf_example1";
const TEST: &str = "pulsewaves/test";
const RIEGL: &str = "riegl_q680i/100429_152240_2535pt_UTM";

fn read_all(pls: &Path) -> (PulseWavesReader<std::fs::File, std::fs::File>, Vec<Pulse>) {
    let mut r = PulseWavesReader::open(pls).unwrap_or_else(|e| panic!("{e}"));
    let mut out = Vec::new();
    loop {
        let mut p = Pulse::default();
        match r.read_pulse(&mut p) {
            Ok(true) => out.push(p),
            Ok(false) => break,
            Err(e) => panic!("{e}"),
        }
    }
    (r, out)
}

/// Independent decoding of what the reader reports for pulse `i`, straight from the bytes with
/// the offsets of the specification: (gps time s, anchor, target, descriptor index,
/// first returning sample).
struct Raw {
    gps_time: f64,
    anchor: [f64; 3],
    target: [f64; 3],
    descriptor: u8,
    first_returning: i16,
}

fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}
fn i64_at(b: &[u8], at: usize) -> i64 {
    i64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}
fn i32_at(b: &[u8], at: usize) -> i32 {
    i32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

fn raw_pulse(pls: &[u8], i: usize) -> Raw {
    let start = i64_at(pls, 176) as usize;
    let size = u32::from_le_bytes(pls[200..204].try_into().unwrap()) as usize;
    let r = &pls[start + i * size..start + (i + 1) * size];
    let t = i64_at(r, 0) as f64 * f64_at(pls, 224) + f64_at(pls, 232);
    let axis = |k: usize, at: usize| {
        i32_at(r, at + 4 * k) as f64 * f64_at(pls, 256 + 8 * k) + f64_at(pls, 280 + 8 * k)
    };
    Raw {
        gps_time: t,
        anchor: [axis(0, 16), axis(1, 16), axis(2, 16)],
        target: [axis(0, 28), axis(1, 28), axis(2, 28)],
        descriptor: r[44],
        first_returning: i16::from_le_bytes([r[40], r[41]]),
    }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// (kind, channel, samples) → count over all pulses.
fn segment_census(pulses: &[Pulse]) -> BTreeMap<(String, u8, u32), usize> {
    let mut m = BTreeMap::new();
    for p in pulses {
        for s in &p.segments {
            *m.entry((format!("{:?}", s.kind), s.channel, s.len))
                .or_insert(0) += 1;
        }
    }
    m
}

/// First and last pulse: GPS time and anchor equal the independent decoding; the direction
/// spans target − anchor over 1000 sampling units.
fn check_first_and_last(stem: &str, pulses: &[Pulse], sample_units_ns: f64, time_shift_s: f64) {
    let bytes = std::fs::read(fixture(stem)).unwrap();
    for i in [0, pulses.len() - 1] {
        let raw = raw_pulse(&bytes, i);
        let p = &pulses[i];
        assert_eq!(p.pulse_id, i as u64);
        assert!(
            (p.gps_time - (raw.gps_time - time_shift_s)).abs() < 1e-6,
            "{stem} pulse {i}: gps_time {} vs raw {}",
            p.gps_time,
            raw.gps_time
        );
        let g = p.geometry.expect("PulseWaves pulses carry geometry");
        for k in 0..3 {
            assert!(
                (g.anchor[k] - raw.anchor[k]).abs() < 1e-9,
                "{stem} pulse {i} anchor {k}"
            );
            let d = (raw.target[k] - raw.anchor[k]) / (1000.0 * sample_units_ns);
            assert!(
                (g.direction[k] - d).abs() < 1e-12,
                "{stem} pulse {i} direction {k}"
            );
        }
    }
}

#[test]
fn lvis_outgoing_80_and_return_432_samples_in_geographic_coordinates() {
    let (r, pulses) = read_all(&fixture(LVIS));
    assert_eq!(pulses.len(), 1000);
    assert_eq!(r.crs(), Some("EPSG:4326"));
    assert_eq!(r.time_base(), TimeBase::GpsSecondsOfWeek);
    let census = segment_census(&pulses);
    assert_eq!(
        census,
        BTreeMap::from([
            (("Outgoing".into(), 0, 80), 1000),
            (("Return".into(), 0, 432), 1000)
        ])
    );
    for p in &pulses {
        assert_eq!(
            (p.sample_ns, p.bits, p.gain_v_per_dn, p.offset_v),
            (2.0, 8, 1.0, 0.0)
        );
        let g = p.geometry.unwrap();
        // Longitudes are stored in 0..360 (MANIFEST); this line is near 300.7 E, 83.2 N.
        assert!((0.0..360.0).contains(&g.anchor[0]) && (300.6..300.9).contains(&g.anchor[0]));
        assert!(
            (83.1..83.2).contains(&g.anchor[1]),
            "latitude {}",
            g.anchor[1]
        );
        // x, y in degrees, z in metres: in metres the direction is c/2 in air, ~0.1499 m per
        // ns, downwards.
        let lat = g.anchor[1].to_radians();
        let m = norm([
            g.direction[0] * 111_320.0 * lat.cos(),
            g.direction[1] * 110_700.0,
            g.direction[2],
        ]);
        assert!((m - 0.1499).abs() < 0.0005, "|direction| {m} m/ns");
        assert!(g.direction[2] < -0.14, "dz {}", g.direction[2]);
        assert!(p.raw.iter().all(|&s| s <= 255));
    }
    check_first_and_last(LVIS, &pulses, 2.0, 0.0);
    assert_eq!(r.wave_bytes_read(), r.waves_len() - 60);
}

#[test]
fn las13fwf_return_only_and_malformed_geokeys_are_tolerated_with_a_warning() {
    let (r, pulses) = read_all(&fixture(LAS13));
    assert_eq!(pulses.len(), 1000);
    assert_eq!(
        segment_census(&pulses),
        BTreeMap::from([(("Return".into(), 0, 256), 1000)])
    );
    assert!(
        pulses
            .iter()
            .all(|p| p.sample_ns == 1.0 && p.outgoing().is_none())
    );
    assert_eq!(
        r.crs(),
        None,
        "EPSG 32632 under the wrong key is not taken as the CRS"
    );
    let w = r.warnings().join("\n");
    assert!(w.contains("32632") && w.contains("3076"), "warnings: {w}");
    check_first_and_last(LAS13, &pulses, 1.0, 0.0);
}

#[test]
fn test_pls_every_segment_variant_decodes() {
    let pls = fixture(TEST);
    let bytes = std::fs::read(&pls).unwrap();
    let (r, pulses) = read_all(&pls);
    assert_eq!(pulses.len(), 15);
    assert_eq!(r.descriptors().count(), 9);
    assert_eq!(r.crs(), Some("EPSG:32613"));
    // Standard GPS time (offset 1e9) is reported as adjusted standard GPS time.
    assert_eq!(r.time_base(), TimeBase::GpsAdjustedStandard);
    check_first_and_last(TEST, &pulses, 1.0, 1e9);
    // What each fixed descriptor holds: the outgoing 24 samples, then (channel) per return
    // segment, as the descriptors' descriptions say.
    let expected: BTreeMap<u8, Vec<(SegmentKind, u8)>> = [
        (1, vec![]),
        (2, vec![0]),
        (3, vec![0, 0]),
        (4, vec![0, 0, 0]),
        (5, vec![1]),
        (6, vec![0, 1]),
        (7, vec![0, 0, 1]),
        (8, vec![0, 0, 0, 1]),
    ]
    .into_iter()
    .map(|(d, ch): (u8, Vec<u8>)| {
        let mut v = vec![(SegmentKind::Outgoing, 0)];
        v.extend(ch.into_iter().map(|c| (SegmentKind::Return, c)));
        (d, v)
    })
    .collect();
    let mut seen = std::collections::BTreeSet::new();
    for (i, p) in pulses.iter().enumerate() {
        let raw = raw_pulse(&bytes, i);
        seen.insert(raw.descriptor);
        let got: Vec<(SegmentKind, u8)> = p.segments.iter().map(|s| (s.kind, s.channel)).collect();
        match expected.get(&raw.descriptor) {
            Some(want) => assert_eq!(&got, want, "pulse {i} descriptor {}", raw.descriptor),
            None => assert_eq!(got.first(), Some(&(SegmentKind::Outgoing, 0)), "pulse {i}"),
        }
        assert_eq!(p.raw_of(0).len(), 24);
        // The first return segment starts at the record's first returning sample (rounded to
        // whole sampling units there).
        if let Some(s) = p.segments.iter().find(|s| s.kind == SegmentKind::Return) {
            assert!(
                (s.start_ns - raw.first_returning as f64).abs() <= 1.0,
                "pulse {i}: first return segment at {} ns, record says {}",
                s.start_ns,
                raw.first_returning
            );
        }
    }
    assert!(seen.len() >= 4, "descriptor variants used: {seen:?}");
    // The pulses' waves lie end to end: everything after the header was read once.
    assert_eq!(r.wave_bytes_read(), r.waves_len() - 60);
}

#[test]
fn riegl_q680i_channels_geometry_and_sensor() {
    let pls = fixture(RIEGL);
    let bytes = std::fs::read(&pls).unwrap();
    let (r, pulses) = read_all(&pls);
    assert_eq!(pulses.len(), 2368);
    assert_eq!(
        segment_census(&pulses),
        BTreeMap::from([
            (("Outgoing".into(), 3, 24), 2368),
            (("Return".into(), 0, 60), 14),
            (("Return".into(), 1, 60), 2314),
            (("Return".into(), 1, 120), 64),
        ])
    );
    assert_eq!(
        r.crs(),
        Some("EPSG:32633"),
        "from the user-defined citation"
    );
    assert!(r.warnings().iter().any(|w| w.contains("UTM_North zone 33")));
    assert_eq!(r.time_base(), TimeBase::GpsSecondsOfWeek);
    assert_eq!(r.lookup_tables(), 2);
    check_first_and_last(RIEGL, &pulses, 1.0, 0.0);
    for (i, p) in pulses.iter().enumerate() {
        let g = p.geometry.unwrap();
        // 1000 sampling units of 1 ns span 149.86 m: c/2 in air.
        let m = norm(g.direction);
        assert!(
            (m - 0.14986).abs() < 2e-5,
            "pulse {i}: |direction| {m} m/ns"
        );
        assert!(g.direction[2] < -0.14, "pulse {i} points down");
        // The anchor is the scanner at ~911 m (CRS height), not 911 m above the ground.
        assert!(
            (905.0..915.0).contains(&g.anchor[2]),
            "pulse {i}: anchor z {}",
            g.anchor[2]
        );
        let o = p.outgoing().unwrap();
        let t0 = p.segments[o].start_ns;
        assert!(
            (-14.0..-8.0).contains(&t0),
            "pulse {i}: outgoing at {t0} ns, 9-13 ns before the anchor"
        );
        let raw = raw_pulse(&bytes, i);
        let first = p
            .segments
            .iter()
            .find(|s| s.kind == SegmentKind::Return)
            .unwrap();
        assert!(
            (first.start_ns - raw.first_returning as f64).abs() <= 1.0,
            "pulse {i}"
        );
    }
    // Height of the anchor above the first sampled return: the ground and canopy the LAS file
    // holds lie at 234.6..509.7 m, so the anchor is 400..680 m above them.
    let heights: Vec<f64> = pulses
        .iter()
        .map(|p| {
            let g = p.geometry.unwrap();
            let s = p
                .segments
                .iter()
                .find(|s| s.kind == SegmentKind::Return)
                .unwrap();
            -(s.start_ns * g.direction[2])
        })
        .collect();
    let max = heights.iter().cloned().fold(f64::MIN, f64::max);
    let min = heights.iter().cloned().fold(f64::MAX, f64::min);
    assert!(
        min > 350.0 && max < 700.0,
        "anchor heights above first samples {min}..{max} m"
    );

    let src = source::open_file(&pls).unwrap();
    let facts = src.facts();
    let sensor = facts.sensor.expect("the scanner record is complete");
    assert!(sensor.name.starts_with("Q680i"), "{}", sensor.name);
    assert_eq!(
        (
            sensor.wavelength_nm,
            sensor.pulse_fwhm_ns,
            sensor.pulse_rate_hz,
            sensor.beam_divergence_mrad
        ),
        (1550.0, 4.0, 400_000.0, 0.5)
    );
    assert_eq!(
        (sensor.sample_interval_ns, sensor.bits_per_sample),
        (1.0, 8)
    );
    assert_eq!(facts.time_base.as_deref(), Some("gps_seconds_of_week"));
    assert_eq!(facts.crs.as_deref(), Some("EPSG:32633"));
}

/// The same RIEGL line as LAS 1.4 point format 9 with its `.wdp`, decoded here from the bytes:
/// every LAS point whose GPS time matches a pulse (|dt| <= 0.5 us) has its waveform packet
/// equal, sample for sample, to one low-power (channel 1) segment of that pulse, and lies at
/// `anchor + (start_ns + return_point_wave_location) x direction` within a few millimetres.
#[test]
fn riegl_las_points_lie_on_their_pulses_and_their_packets_equal_the_segments() {
    let pls = fixture(RIEGL);
    let (_, pulses) = read_all(&pls);
    let las = std::fs::read(pls.with_extension("las")).unwrap();
    let wdp = std::fs::read(pls.with_extension("wdp")).unwrap();
    let u16_at = |b: &[u8], at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
    let u32_at = |b: &[u8], at: usize| u32::from_le_bytes(b[at..at + 4].try_into().unwrap());
    let f32_at = |b: &[u8], at: usize| f32::from_le_bytes(b[at..at + 4].try_into().unwrap());
    let point_start = u32_at(&las, 96) as usize;
    assert_eq!(las[104], 9, "point format 9");
    let rec_len = u16_at(&las, 105) as usize;
    let points = i64_at(&las, 247) as usize;
    // Waveform packet descriptors (LASF_Spec 100..354): samples per packet by index.
    let mut samples_of = BTreeMap::new();
    let mut at = u16_at(&las, 94) as usize;
    for _ in 0..u32_at(&las, 100) {
        let (id, len) = (u16_at(&las, at + 18), u16_at(&las, at + 20) as usize);
        if (100..355).contains(&id) {
            assert_eq!(las[at + 54], 16, "16-bit packets");
            samples_of.insert((id - 99) as u8, u32_at(&las, at + 56) as usize);
        }
        at += 54 + len;
    }
    let mut by_time: Vec<(f64, usize)> = pulses
        .iter()
        .enumerate()
        .map(|(i, p)| (p.gps_time, i))
        .collect();
    by_time.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut matched, mut worst) = (0, 0.0f64);
    for k in 0..points {
        let r = &las[point_start + k * rec_len..point_start + (k + 1) * rec_len];
        let t = f64_at(r, 22);
        let j = by_time.partition_point(|e| e.0 < t - 0.5e-6);
        let Some(&(pt, pi)) = by_time.get(j) else {
            continue;
        };
        if (pt - t).abs() > 0.5e-6 {
            continue;
        }
        let p = &pulses[pi];
        let n = samples_of[&r[30]];
        let offset = i64_at(r, 31) as usize;
        let packet: Vec<u16> = (0..n).map(|s| u16_at(&wdp, offset + 2 * s)).collect();
        let seg = (0..p.segments.len())
            .find(|&s| p.segments[s].channel == 1 && p.raw_of(s) == packet.as_slice())
            .unwrap_or_else(|| {
                panic!("LAS point {k}: no low-power segment of pulse {pi} equals its packet")
            });
        let loc_ns = f32_at(r, 43) as f64 / 1000.0;
        let g = p.geometry.unwrap();
        let at_ns = p.segments[seg].start_ns + loc_ns;
        for a in 0..3 {
            let xyz =
                i32_at(r, 4 * a) as f64 * f64_at(&las, 131 + 8 * a) + f64_at(&las, 155 + 8 * a);
            worst = worst.max((g.anchor[a] + at_ns * g.direction[a] - xyz).abs());
        }
        matched += 1;
    }
    assert!(
        matched >= 2500,
        "{matched} of {points} LAS points matched a pulse"
    );
    assert!(
        worst < 0.005,
        "a LAS point lies {worst} m off its pulse's ray"
    );
}

#[test]
fn source_streams_every_pulse_and_reports() {
    let pool = fwlidar::pulse::PulsePool::new(4);
    let mut src = source::open_file(&fixture(LVIS)).unwrap();
    assert_eq!(src.name(), "pulsewaves");
    let mut n = 0;
    loop {
        match src.next(&pool).unwrap() {
            SourceEvent::Pulse(p) => {
                n += 1;
                pool.give(p);
            }
            SourceEvent::End => break,
            SourceEvent::Nav(_) => panic!("no navigation in PulseWaves"),
            SourceEvent::Idle => panic!("a file source is never idle"),
        }
    }
    assert_eq!(n, 1000);
    assert_eq!(pool.allocated(), 1, "the pooled pulse is reused");
    assert_eq!(src.progress(), Some((1000, 1000)));
    let fwlidar::source::report::InputReport::PulseWaves(rep) = src.report().input else {
        panic!("a PulseWaves source reports as one")
    };
    assert_eq!(rep.pulses, 1000);
    assert_eq!(rep.descriptors.len(), 1);
    // LVIS's scanner record has no pulse frequency: no complete sensor.
    assert!(src.facts().sensor.is_none());
    assert_eq!(src.facts().crs.as_deref(), Some("EPSG:4326"));
}

// ---- damaged inputs: clear errors naming the file and field ----

fn copy_pair(stem: &str, dir: &Path, name: &str) -> (PathBuf, PathBuf) {
    let pls = fixture(stem);
    let (p, w) = (
        dir.join(format!("{name}.pls")),
        dir.join(format!("{name}.wvs")),
    );
    std::fs::copy(&pls, &p).unwrap();
    std::fs::copy(pls.with_extension("wvs"), &w).unwrap();
    (p, w)
}

fn read_err(pls: &Path) -> String {
    let mut r = match PulseWavesReader::open(pls) {
        Ok(r) => r,
        Err(e) => return e.to_string(),
    };
    let mut p = Pulse::default();
    loop {
        match r.read_pulse(&mut p) {
            Ok(true) => {}
            Ok(false) => panic!("{} read without error", pls.display()),
            Err(e) => return e.to_string(),
        }
    }
}

#[test]
fn missing_waves_file_names_both_paths() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("alone.pls");
    std::fs::copy(fixture(LVIS), &p).unwrap();
    let e = read_err(&p);
    assert!(
        e.contains("alone.pls") && e.contains("alone.wvs") && e.contains("alone.WVS"),
        "{e}"
    );
    let e = source::open_file(&p).err().unwrap();
    assert!(e.contains("alone.wvs"), "{e}");
}

#[test]
fn upper_case_wvs_is_found() {
    let dir = tempfile::tempdir().unwrap();
    let (p, w) = copy_pair(TEST, dir.path(), "UP");
    std::fs::rename(&w, dir.path().join("UP.WVS")).unwrap();
    let (_, pulses) = read_all(&p);
    assert_eq!(pulses.len(), 15);
}

#[test]
fn truncated_pls_is_an_error_naming_the_pulse_table() {
    let dir = tempfile::tempdir().unwrap();
    let (p, _) = copy_pair(LVIS, dir.path(), "short");
    let b = std::fs::read(&p).unwrap();
    std::fs::write(&p, &b[..b.len() - 100]).unwrap();
    let e = read_err(&p);
    assert!(
        e.contains("short.pls") && e.contains("truncated") && e.contains("number_of_pulses 1000"),
        "{e}"
    );
    // Cut inside the VLRs.
    std::fs::write(&p, &b[..600]).unwrap();
    let e = read_err(&p);
    assert!(
        e.contains("short.pls") && e.contains("offset_to_pulse_data"),
        "{e}"
    );
    // Cut inside the header.
    std::fs::write(&p, &b[..100]).unwrap();
    let e = read_err(&p);
    assert!(e.contains("short.pls") && e.contains("header"), "{e}");
}

#[test]
fn truncated_wvs_is_an_error_naming_pulse_sampling_and_segment() {
    let dir = tempfile::tempdir().unwrap();
    let (p, w) = copy_pair(RIEGL, dir.path(), "cut");
    let b = std::fs::read(&w).unwrap();
    std::fs::write(&w, &b[..b.len() / 2]).unwrap();
    let e = read_err(&p);
    assert!(
        e.contains("cut.wvs") && e.contains("pulse ") && e.contains("sampling"),
        "{e}"
    );
    assert!(
        e.contains("truncated") || e.contains("offset_to_waves"),
        "{e}"
    );
    std::fs::write(&w, &b[..30]).unwrap();
    let e = read_err(&p);
    assert!(e.contains("cut.wvs") && e.contains("header"), "{e}");
}

#[test]
fn descriptor_index_pointing_nowhere_names_the_pulse() {
    let dir = tempfile::tempdir().unwrap();
    let (p, _) = copy_pair(LVIS, dir.path(), "patched");
    let mut b = std::fs::read(&p).unwrap();
    let start = i64_at(&b, 176) as usize;
    b[start + 17 * 48 + 44] = 9;
    std::fs::write(&p, &b).unwrap();
    let e = read_err(&p);
    assert!(
        e.contains(
            "patched.pls: pulse 17: descriptor index 9 points nowhere (file has 1 descriptor: 1)"
        ),
        "{e}"
    );
}

#[test]
fn wrong_signature_and_compression_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let (p, w) = copy_pair(TEST, dir.path(), "sig");
    let mut b = std::fs::read(&p).unwrap();
    b[0] = b'X';
    std::fs::write(&p, &b).unwrap();
    let e = read_err(&p);
    assert!(e.contains("sig.pls") && e.contains("signature"), "{e}");
    b[0] = b'P';
    std::fs::write(&p, &b).unwrap();
    let mut wb = std::fs::read(&w).unwrap();
    wb[16] = 1;
    std::fs::write(&w, &wb).unwrap();
    let e = read_err(&p);
    assert!(
        e.contains("sig.wvs") && e.contains("compression") && e.contains("not supported"),
        "{e}"
    );
}

// ---- random damage: Ok or Err, never a panic ----

fn pairs() -> &'static Vec<(Vec<u8>, Vec<u8>)> {
    static PAIRS: OnceLock<Vec<(Vec<u8>, Vec<u8>)>> = OnceLock::new();
    PAIRS.get_or_init(|| {
        [LVIS, LAS13, TEST, RIEGL]
            .iter()
            .map(|s| {
                let p = fixture(s);
                (
                    std::fs::read(&p).unwrap(),
                    std::fs::read(p.with_extension("wvs")).unwrap(),
                )
            })
            .collect()
    })
}

/// Reads a pair from memory to the end or the first error; returns the pulses read.
fn read_memory(pls: Vec<u8>, wvs: Vec<u8>) -> Result<u64, PulseWavesError> {
    let mut r = PulseWavesReader::new(Cursor::new(pls), "fuzz.pls", Cursor::new(wvs), "fuzz.wvs")?;
    let mut p = Pulse::default();
    while r.read_pulse(&mut p)? {
        assert!(p.segments.iter().all(|s| s.range().end <= p.raw.len()));
    }
    Ok(r.pulses_read())
}

#[test]
fn reading_from_memory_equals_reading_the_files() {
    let (pls, wvs) = pairs()[3].clone();
    assert_eq!(read_memory(pls, wvs).unwrap(), 2368);
}

mod damage {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig { cases: 1000, failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn mutated_or_truncated_files_give_ok_or_err_never_a_panic(
            which in 0usize..4,
            // Mostly in the header, VLRs and first records, where the structure is.
            pls_edits in proptest::collection::vec((0usize..12_000, any::<u8>()), 0..12),
            wvs_edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..12),
            pls_cut in proptest::option::of(any::<prop::sample::Index>()),
            wvs_cut in proptest::option::of(any::<prop::sample::Index>()),
        ) {
            let (mut pls, mut wvs) = pairs()[which].clone();
            for (at, v) in pls_edits {
                let n = pls.len();
                pls[at % n] = v;
            }
            for (at, v) in wvs_edits {
                let i = at.index(wvs.len());
                wvs[i] = v;
            }
            if let Some(c) = pls_cut {
                pls.truncate(c.index(pls.len()));
            }
            if let Some(c) = wvs_cut {
                wvs.truncate(c.index(wvs.len()));
            }
            match read_memory(pls, wvs) {
                Ok(_) => {}
                Err(e) => prop_assert!(e.to_string().starts_with("fuzz."), "{e}"),
            }
        }
    }
}

// ---- the command line ----

#[test]
fn inspect_lists_every_riegl_pulse_as_json() {
    let out = Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .args([
            "inspect",
            fixture(RIEGL).to_str().unwrap(),
            "--pulses",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 2368);
    for (i, l) in lines.iter().enumerate() {
        let v: serde_json::Value = serde_json::from_str(l).unwrap();
        assert_eq!(v["pulse_id"], i as u64);
        assert_eq!(v["anchor"].as_array().unwrap().len(), 3);
        assert_eq!(v["direction"].as_array().unwrap().len(), 3);
        let segs = v["segments"].as_array().unwrap();
        assert!(segs.len() >= 2, "line {i}");
        assert_eq!(segs[0]["kind"], "outgoing");
        assert_eq!(segs[0]["samples"].as_array().unwrap().len(), 24);
    }
}
