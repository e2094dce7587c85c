//! Navigation parsers on real receiver logs (`tests/data/nav/`, see tests/data/MANIFEST.md):
//! gpsd's regression logs (OxTS PASHR attitude, a Hemisphere heading receiver, a cold boot full
//! of garbled sentences, bad checksums, odd number formats), a NovAtel SPAN binary stream and
//! Applanix SBET files. Counts are exact; fails naming any missing fixture.

use std::collections::BTreeMap;
use std::process::Command;

use fwlidar::nav::NavSample;
use fwlidar::nav::dating::GpsTime;
use fwlidar::nav::decoder::{DecodeSummary, NavDecoder};
use fwlidar::nav::sbet::SbetReader;

mod common;
use common::{BIN, fixture};

/// Decodes `bytes` fed in pieces of `chunk` bytes.
fn decode(bytes: &[u8], chunk: usize) -> (Vec<(NavSample, Option<GpsTime>)>, DecodeSummary) {
    let mut dec = NavDecoder::new(18.0, 512, None);
    let mut out = Vec::new();
    for piece in bytes.chunks(chunk.max(1)) {
        dec.push(piece, &mut |s, t| out.push((s, t)));
    }
    dec.finish(&mut |s, t| out.push((s, t)));
    (out, dec.summary())
}

fn map(pairs: &[(&str, u64)]) -> BTreeMap<String, u64> {
    pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
}

struct Expect {
    file: &'static str,
    by_kind: &'static [(&'static str, u64)],
    rejected: &'static [(&'static str, u64)],
    ignored: &'static [(&'static str, u64)],
}

/// Exact counts per log. How they were checked and how they compare with gpsd's `.chk`
/// outputs: `docs/navigation.md`.
const LOGS: &[Expect] = &[
    Expect {
        file: "rst39.log",
        by_kind: &[
            ("GGA", 40),
            ("HDT", 4),
            ("PASHR", 100),
            ("RMC", 4),
            ("ZDA", 4),
        ],
        rejected: &[],
        ignored: &[],
    },
    Expect {
        file: "hemi.log",
        by_kind: &[("GGA", 21), ("HDT", 4), ("VTG", 21), ("ZDA", 108)],
        rejected: &[("no_fix", 194), ("no_value", 405)],
        ignored: &[],
    },
    Expect {
        file: "firefly-II.log",
        by_kind: &[("RMC", 23), ("ZDA", 23)],
        rejected: &[("bad_checksum", 23)],
        ignored: &[],
    },
    Expect {
        file: "gp-320fw-2019-04-07-coldboot.log",
        by_kind: &[("GGA", 2), ("RMC", 1), ("VTG", 2), ("ZDA", 7)],
        rejected: &[
            ("bad_checksum", 36),
            ("no_checksum", 5),
            ("no_fix", 23),
            ("no_value", 8),
            ("truncated", 4),
        ],
        ignored: &[("GLL", 8), ("GSA", 15), ("GSV", 28)],
    },
    Expect {
        file: "nmea-fuzzy-cases.log",
        by_kind: &[("GGA", 14), ("RMC", 14)],
        rejected: &[],
        ignored: &[],
    },
];

#[test]
fn gpsd_logs_decode_with_exact_counts_whatever_the_read_sizes() {
    for e in LOGS {
        let bytes = std::fs::read(fixture(&format!("nav/gpsd/{}", e.file))).unwrap();
        let (samples, s) = decode(&bytes, 1 << 16);
        assert_eq!(s.by_kind, map(e.by_kind), "{}: decoded", e.file);
        assert_eq!(
            s.rejected_by_reason,
            map(e.rejected),
            "{}: rejected",
            e.file
        );
        assert_eq!(s.ignored, map(e.ignored), "{}: ignored", e.file);
        assert_eq!(s.records, samples.len() as u64);
        assert_eq!(s.rejected, e.rejected.iter().map(|r| r.1).sum::<u64>());
        // Every sample dated (each log has a ZDA or RMC date early enough).
        assert!(samples.iter().all(|(_, t)| t.is_some()), "{}", e.file);
        // Serial reads split records anywhere: the same result at every read size.
        for chunk in [1, 7, 64] {
            let (again, s2) = decode(&bytes, chunk);
            assert_eq!(s2, s, "{}: summary at {chunk}-byte reads", e.file);
            assert_eq!(again, samples, "{}: samples at {chunk}-byte reads", e.file);
        }
    }
}

/// Sentences whose checksum holds, counted line by line here without the framer: the framer's
/// good frames must be exactly these on the clean logs.
#[test]
fn framed_sentences_equal_an_independent_line_count_on_clean_logs() {
    for file in [
        "rst39.log",
        "hemi.log",
        "firefly-II.log",
        "nmea-fuzzy-cases.log",
    ] {
        let bytes = std::fs::read(fixture(&format!("nav/gpsd/{file}"))).unwrap();
        let mut good = 0u64;
        let mut bad = 0u64;
        for line in bytes.split(|&b| b == b'\n') {
            let line = line.strip_suffix(b"\r").unwrap_or(line);
            let Some(body) = line.strip_prefix(b"$") else {
                continue;
            };
            let star = body.iter().rposition(|&b| b == b'*').unwrap();
            let x = body[..star].iter().fold(0u8, |a, b| a ^ b);
            let given = u8::from_str_radix(std::str::from_utf8(&body[star + 1..]).unwrap(), 16);
            if given == Ok(x) {
                good += 1;
            } else {
                bad += 1;
            }
        }
        let (_, s) = decode(&bytes, 4096);
        let framed = s.records + s.rejected + s.ignored.values().sum::<u64>()
            - s.rejected_by_reason
                .get("bad_checksum")
                .copied()
                .unwrap_or(0);
        assert_eq!(framed, good, "{file}");
        assert_eq!(
            s.rejected_by_reason
                .get("bad_checksum")
                .copied()
                .unwrap_or(0),
            bad,
            "{file}"
        );
    }
}

#[test]
fn oxts_attitude_forms_a_dated_25_hz_trajectory() {
    let bytes = std::fs::read(fixture("nav/gpsd/rst39.log")).unwrap();
    let (samples, _) = decode(&bytes, 4096);
    let att: Vec<_> = samples
        .iter()
        .filter(|(s, _)| s.kind == fwlidar::nav::NavKind::Pashr)
        .collect();
    assert_eq!(att.len(), 100);
    // RMC date 19 Feb 2014: GPS week 1780; 20:41:32 UTC on a Wednesday + 16 leap seconds in
    // 2014 (we apply the configured 18, so the sow is 2 s later than the truth of the day).
    let first = att[0].1.unwrap();
    assert_eq!(first.week, 1780);
    assert!(
        (first.sow - (3.0 * 86_400.0 + 20.0 * 3600.0 + 41.0 * 60.0 + 32.0 + 18.0)).abs() < 1e-6
    );
    for w in att.windows(2) {
        let dt = w[1].1.unwrap().seconds() - w[0].1.unwrap().seconds();
        assert!((dt - 0.04).abs() < 1e-6, "25 Hz: {dt}");
    }
    assert_eq!(att[0].0.heading, Some(10.51));
    assert_eq!(att[0].0.roll, Some(0.39));
    assert_eq!(att[0].0.pitch, Some(-0.79));
}

#[test]
fn novatel_span_stream_matches_the_known_fix() {
    let bytes = std::fs::read(fixture("nav/novatel/corrimudata.pcap.payload.bin")).unwrap();
    let (samples, s) = decode(&bytes, 4096);
    assert_eq!(
        s.by_kind,
        map(&[
            ("BESTPOS", 28),
            ("CORRIMUDATA", 29),
            ("INSPVAX", 28),
            ("TIME", 2)
        ])
    );
    assert_eq!(
        s.ignored,
        map(&[("novatel_264", 2)]),
        "INSCOV is not decoded"
    );
    assert_eq!(s.rejected, 0);
    let ins: Vec<_> = samples
        .iter()
        .filter(|(x, _)| x.kind == fwlidar::nav::NavKind::Inspvax)
        .collect();
    for (x, t) in &ins {
        assert_eq!(t.unwrap().week, 1820);
        assert!((x.lat.unwrap() - 43.4041).abs() < 5e-5);
        assert!((x.lon.unwrap() + 80.4702).abs() < 5e-5);
        assert!((x.height_msl.unwrap() - 326.2).abs() < 0.05);
        assert!((x.roll.unwrap() - 1.04).abs() < 0.02);
        assert!((x.pitch.unwrap() - 0.31).abs() < 0.02);
        assert!((x.heading.unwrap() - 94.2).abs() < 0.05);
    }
    for w in ins.windows(2) {
        let dt = w[1].1.unwrap().seconds() - w[0].1.unwrap().seconds();
        assert!((dt - 0.05).abs() < 1e-6, "20 Hz: {dt}");
    }
    // TIME says GPS − UTC was 16 s (week 1820 is November 2014).
    let time = samples
        .iter()
        .find(|(x, _)| x.kind == fwlidar::nav::NavKind::Time)
        .unwrap();
    assert_eq!(time.0.gps_minus_utc, Some(16.0));
}

#[test]
fn sbet_records_and_the_one_byte_short_file() {
    let f = fixture("nav/sbet/2-points.sbet");
    let recs: Vec<_> = SbetReader::new(std::fs::File::open(&f).unwrap(), "2-points.sbet")
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(recs.len(), 2);
    assert!((recs[0].lat.unwrap() - 32.5452).abs() < 1e-4);
    assert!((recs[0].lon.unwrap() + 116.9782).abs() < 1e-4);
    assert!((recs[0].height.unwrap() - 107.7).abs() < 0.05);
    assert!((recs[0].heading.unwrap() - 174.6).abs() < 0.05);

    let bad = fixture("nav/sbet/badfile.sbet");
    let o = Command::new(BIN)
        .args(["inspect", "--nav", "sbet", bad.to_str().unwrap(), "--json"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("badfile.sbet") && err.contains("record 1 is truncated"),
        "{err}"
    );
    let out = String::from_utf8_lossy(&o.stdout);
    let lines: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2, "the good record, then the summary");
    assert_eq!(lines[1]["records"], 1);
    assert_eq!(lines[1]["rejected_by_reason"]["truncated"], 1);
}

#[test]
fn inspect_nav_prints_one_json_object_per_sample_and_a_summary() {
    let f = fixture("nav/gpsd/rst39.log");
    let o = Command::new(BIN)
        .args(["inspect", "--nav", "nmea", f.to_str().unwrap(), "--json"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    let lines: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 153);
    let pashr = &lines[0];
    assert_eq!(pashr["kind"], "PASHR");
    assert!(pashr["gps_time"].as_f64().is_some());
    for k in ["roll", "pitch", "heading"] {
        assert!(pashr[k].as_f64().is_some(), "{k} in {pashr}");
    }
    let gga = lines.iter().find(|l| l["kind"] == "GGA").unwrap();
    assert!((gga["lat"].as_f64().unwrap() - 42.0955).abs() < 1e-3);
    assert!((gga["lon"].as_f64().unwrap() + 88.034).abs() < 1e-3);
    let last = lines.last().unwrap();
    assert_eq!(last["summary"], true);
    assert_eq!(last["records"], 152);
    assert_eq!(last["rejected"], 0);
}

/// Every position gpsd reports for a log (its `.chk` TPVs with `lat`/`lon`, printed to 9
/// decimals) is one of ours, to 1e-9 degrees: where gpsd reports fewer fixes, it reports a
/// subset, not different numbers. How many distinct fixes each side has is printed.
#[test]
fn every_position_gpsd_reports_is_one_of_ours() {
    for e in LOGS {
        let bytes = std::fs::read(fixture(&format!("nav/gpsd/{}", e.file))).unwrap();
        let (samples, _) = decode(&bytes, 4096);
        let ours: Vec<(f64, f64)> = samples
            .iter()
            .filter_map(|(s, _)| s.lat.zip(s.lon))
            .collect();
        let chk = std::fs::read(fixture(&format!("nav/gpsd/{}.chk", e.file))).unwrap();
        let mut theirs: Vec<(f64, f64)> = String::from_utf8_lossy(&chk)
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter_map(|j| Some((j["lat"].as_f64()?, j["lon"].as_f64()?)))
            .collect();
        theirs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
        theirs.dedup();
        assert!(!theirs.is_empty(), "{}: gpsd reports positions", e.file);
        for (lat, lon) in &theirs {
            let near = ours
                .iter()
                .any(|(a, b)| (a - lat).abs() < 1e-9 && (b - lon).abs() < 1e-9);
            assert!(near, "{}: gpsd's ({lat}, {lon}) is none of ours", e.file);
        }
        eprintln!(
            "{}: gpsd {} distinct positions, all among our {} position records",
            e.file,
            theirs.len(),
            ours.len()
        );
    }
}
