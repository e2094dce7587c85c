//! LAZ input (`format::las_read`, its `laz.rs`) on LAZ files made from the real RIEGL fixture by
//! the real LAZ writers (laspy and lazrs, `tests/python/write_laz.py`): they read as the same
//! pulses as the LAS, `fwlidar inspect` and `fwlidar replay` of them give the same output as of
//! the LAS, a `.wdz` beside them is an error that says how to decompress it, and damaged LAZ
//! bytes give errors naming the file, never a panic.
//!
//! The LAZ bytes are located here by walking the file's own structure (header, LASzip VLR,
//! chunk table offset, layer sizes), independently of the reader.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use fwlidar::format::las_read::{LasInfo, LasReadError, LasReadStats, LasReader};
use fwlidar::pulse::Pulse;
use proptest::prelude::*;

/// The folder of LAZ copies (made once per run) and what the script printed.
fn made() -> &'static (PathBuf, serde_json::Value) {
    static MADE: OnceLock<(PathBuf, serde_json::Value)> = OnceLock::new();
    MADE.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("laz_reader");
        let info = common::write_laz_copies(&dir);
        (dir, info)
    })
}

fn laz(name: &str) -> PathBuf {
    made().0.join(name)
}

fn real_las() -> PathBuf {
    common::fixture(common::RIEGL_LAS)
}

fn read_all<R: std::io::Read + std::io::Seek, W: std::io::Read + std::io::Seek>(
    r: &mut LasReader<R, W>,
) -> Result<Vec<Pulse>, LasReadError> {
    let mut out = Vec::new();
    loop {
        let mut p = Pulse::default();
        if !r.next_pulse(&mut p)? {
            return Ok(out);
        }
        out.push(p);
    }
}

/// The pulses of `path` and the reader's counts.
fn pulses_of(path: &Path) -> (Vec<Pulse>, LasReadStats, bool) {
    let mut r = LasReader::open(path).unwrap_or_else(|e| panic!("{e}"));
    let p = read_all(&mut r).unwrap_or_else(|e| panic!("{e}"));
    (p, r.stats().clone(), r.is_laz())
}

fn assert_same_pulses(a: &[Pulse], b: &[Pulse], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    assert_eq!(a.len(), 2376, "{what}");
    for (x, y) in a.iter().zip(b) {
        assert_eq!(x.pulse_id, y.pulse_id, "{what}");
        assert_eq!(x.raw, y.raw, "{what}: pulse {}", x.pulse_id);
        assert_eq!(x.segments.len(), y.segments.len(), "{what}");
        assert_eq!(
            (x.gps_time, x.sample_ns, x.bits, x.gain_v_per_dn, x.offset_v),
            (y.gps_time, y.sample_ns, y.bits, y.gain_v_per_dn, y.offset_v),
            "{what}: pulse {}",
            x.pulse_id
        );
        let (gx, gy) = (x.geometry.unwrap(), y.geometry.unwrap());
        assert_eq!(gx.anchor, gy.anchor, "{what}: pulse {}", x.pulse_id);
        assert_eq!(gx.direction, gy.direction, "{what}: pulse {}", x.pulse_id);
    }
}

#[test]
fn the_writers_make_laz_of_point_formats_9_and_4() {
    let info = &made().1;
    // Point data record format stored with bit 7 set: 9 -> 137, 4 -> 132.
    assert_eq!(info["r9.laz"], serde_json::json!([137, 50000, false]));
    assert_eq!(info["r9v.laz"], serde_json::json!([137, u32::MAX, true]));
    assert_eq!(info["r4.laz"], serde_json::json!([132, 50000, false]));
    for (name, format, minor) in [("r9.laz", 9, 4), ("r9v.laz", 9, 4), ("r4.laz", 4, 3)] {
        let bytes = std::fs::read(laz(name)).unwrap();
        let i = LasInfo::read(name, &mut std::io::Cursor::new(&bytes)).unwrap();
        assert_eq!(i.header.point_format, format, "{name}");
        assert_eq!(i.version, (1, minor), "{name}");
        assert!(i.laz.is_some(), "{name}");
        assert_eq!(i.descriptors_defined(), 100, "{name}");
    }
    let bytes = std::fs::read(real_las()).unwrap();
    let i = LasInfo::read("x.las", &mut std::io::Cursor::new(&bytes)).unwrap();
    assert!(i.laz.is_none());
}

/// Every pulse of the LAZ equals the LAS's: samples, time, digitizer, geometry to the bit; the
/// counts too, but for the chunks decompressed.
#[test]
fn laz_reads_as_the_same_pulses_as_the_las() {
    let (las, las_stats, las_is_laz) = pulses_of(&real_las());
    assert!(!las_is_laz);
    assert_eq!(las_stats.laz_chunks, 0);
    for (name, chunks) in [("r9.laz", 1), ("r9v.laz", 6)] {
        let (z, mut stats, is_laz) = pulses_of(&laz(name));
        assert!(is_laz, "{name}");
        assert_same_pulses(&las, &z, name);
        assert_eq!(stats.laz_chunks, chunks, "{name}");
        stats.laz_chunks = 0;
        assert_eq!(stats, las_stats, "{name}");
    }
    // Format 4 (point-wise chunked, LASzip items v2) against laspy's LAS 1.3 of the same points.
    let (l4, s4, _) = pulses_of(&laz("r4.las"));
    let (z4, mut sz4, _) = pulses_of(&laz("r4.laz"));
    assert_same_pulses(&l4, &z4, "r4.laz");
    assert_eq!(sz4.laz_chunks, 1);
    sz4.laz_chunks = 0;
    assert_eq!(sz4, s4);
    // And the format 4 file holds the same waveforms and lines as the original format 9.
    for (a, b) in l4.iter().zip(&las) {
        assert_eq!(a.raw, b.raw);
        assert_eq!(a.geometry.unwrap().anchor, b.geometry.unwrap().anchor);
    }
}

/// A LAZ whose packets are internal (LAS 1.4: the waveform data packet record as an EVLR after
/// the chunk table, global encoding bit 1) reads as the same pulses: the packets are read from
/// the LAZ file itself, uncompressed, as for LAS.
#[test]
fn laz_with_internal_packets_reads_as_the_las() {
    let mut b = std::fs::read(laz("r9v.laz")).unwrap();
    let mut wdp = std::fs::read(laz("r9.wdp")).unwrap();
    // The .wdp starts with the record's 60-byte EVLR header; its length after the header:
    let after = (wdp.len() - 60) as u64;
    wdp[20..28].copy_from_slice(&after.to_le_bytes());
    let at = b.len() as u64;
    b[6..8].copy_from_slice(&(1u16 << 1).to_le_bytes());
    b[227..235].copy_from_slice(&at.to_le_bytes());
    b[235..243].copy_from_slice(&at.to_le_bytes());
    b[243..247].copy_from_slice(&1u32.to_le_bytes());
    b.extend_from_slice(&wdp);
    let mut r = LasReader::from_bytes(&b, None).unwrap();
    assert_eq!(
        r.info().waveform,
        fwlidar::format::las_read::WaveformLocation::Internal { record_start: at }
    );
    let got = read_all(&mut r).unwrap();
    let (want, _, _) = pulses_of(&real_las());
    assert_same_pulses(&want, &got, "internal packets");
    assert_eq!(r.stats().laz_chunks, 6);
}

/// The reader's progress through a LAZ (compressed bytes) never goes back, stays within the
/// file and ends at the end of the compressed points.
#[test]
fn laz_progress_stays_within_the_file() {
    let path = laz("r9v.laz");
    let len = std::fs::metadata(&path).unwrap().len();
    let mut r = LasReader::open(&path).unwrap();
    let mut p = Pulse::default();
    let mut last = 0;
    while r.next_pulse(&mut p).unwrap() {
        let (done, all) = r.progress();
        assert!(
            done >= last && done <= all && all <= len,
            "{done} {all} {len}"
        );
        last = done;
    }
    let (done, all) = r.progress();
    assert!(all - done < all / 100, "{done} of {all} at the end");
}

fn fwlidar(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(common::BIN)
        .args(args)
        .current_dir(common::ROOT)
        .output()
        .expect("run fwlidar")
}

fn json_of(o: &Output) -> serde_json::Value {
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// Drops what differs between a LAS and its LAZ from a source report.
fn without_laz_keys(mut v: serde_json::Value) -> serde_json::Value {
    if let Some(o) = v.as_object_mut() {
        o.remove("compression");
        o.remove("laz_chunks");
    }
    v
}

#[test]
fn inspect_of_the_laz_matches_the_las() {
    let las = real_las();
    let z = laz("r9v.laz");
    let a = json_of(&fwlidar(&[
        "inspect".as_ref(),
        "--json".as_ref(),
        las.as_os_str(),
    ]));
    let b = json_of(&fwlidar(&[
        "inspect".as_ref(),
        "--json".as_ref(),
        z.as_os_str(),
    ]));
    assert_eq!(a["report"]["compression"], "none", "{a}");
    assert_eq!(b["report"]["compression"], "laz", "{b}");
    assert_eq!(b["report"]["laz_chunks"], 6, "{b}");
    assert!(a["report"].get("laz_chunks").is_none(), "{a}");
    let strip = |mut v: serde_json::Value| {
        let report = without_laz_keys(v["report"].take());
        v["report"] = report;
        v.as_object_mut().unwrap().remove("file");
        v
    };
    assert_eq!(strip(a), strip(b));
    // Every pulse listed identically.
    let args = |f: &Path| {
        fwlidar(&[
            "inspect".as_ref(),
            "--pulses".as_ref(),
            "--json".as_ref(),
            f.as_os_str(),
        ])
    };
    let (pa, pb) = (args(&las), args(&z));
    assert!(pa.status.success() && pb.status.success());
    assert_eq!(pa.stdout.iter().filter(|&&c| c == b'\n').count(), 2376);
    assert!(pa.stdout == pb.stdout, "inspect --pulses differs");
}

/// `fwlidar replay` of the LAZ writes the same tables (returns.csv and every other CSV, byte
/// for byte) and the same summary as of the LAS.
#[test]
fn replay_of_the_laz_matches_the_las() {
    let dir = tempfile::tempdir().unwrap();
    let run = |input: &Path, out: &Path| {
        let o = fwlidar(&[
            "replay".as_ref(),
            input.as_os_str(),
            "--no-progress".as_ref(),
            "--workers".as_ref(),
            "2".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
            "--set".as_ref(),
            "output.waveform_format=csv".as_ref(),
            "--set".as_ref(),
            "output.returns=true".as_ref(),
        ]);
        assert!(o.status.success(), "{}", common::text(&o.stderr));
        let s: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
        s
    };
    let (oa, ob) = (dir.path().join("las"), dir.path().join("laz"));
    let sa = run(&real_las(), &oa);
    let sb = run(&laz("r9.laz"), &ob);
    assert_eq!(sa["source"]["pulses"], 2376);
    assert_eq!(sb["source"]["compression"], "laz");
    assert_eq!(
        without_laz_keys(sa["source"].clone()),
        without_laz_keys(sb["source"].clone())
    );
    for key in ["pulses_in", "pulses_out", "dropped", "errors"] {
        assert_eq!(sa[key], sb[key], "summary {key}");
    }
    // The sinks' counts (their paths name the two output folders).
    // (Without the time spent writing, `io_s`.)
    let sinks_b = without_timing(sb["sinks"].clone())
        .to_string()
        .replace(&*ob.to_string_lossy(), &oa.to_string_lossy());
    assert_eq!(without_timing(sa["sinks"].clone()).to_string(), sinks_b);
    let mut tables = Vec::new();
    for e in std::fs::read_dir(&oa).unwrap() {
        let name = e.unwrap().file_name();
        if name.to_string_lossy().ends_with(".csv") {
            let a = std::fs::read(oa.join(&name)).unwrap();
            let b = std::fs::read(ob.join(&name))
                .unwrap_or_else(|e| panic!("{name:?} not written for the LAZ: {e}"));
            assert!(a == b, "{name:?} differs between the LAS and the LAZ");
            tables.push(name.to_string_lossy().into_owned());
        }
    }
    assert!(tables.iter().any(|t| t == "returns.csv"), "{tables:?}");
    let returns = std::fs::read_to_string(oa.join("returns.csv")).unwrap();
    assert!(
        returns.lines().count() > 2376,
        "returns.csv is nearly empty"
    );
}

/// A copy of `name` as `x.laz` in a new folder, `edit`ed, with the `.wdp` beside it.
fn edited(name: &str, edit: impl FnOnce(&mut Vec<u8>)) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let mut b = std::fs::read(laz(name)).unwrap();
    edit(&mut b);
    let path = dir.path().join("x.laz");
    std::fs::write(&path, b).unwrap();
    let wdp = std::fs::read(laz("r9.wdp")).unwrap();
    std::fs::write(dir.path().join("x.wdp"), wdp).unwrap();
    (dir, path)
}

/// `fwlidar inspect` of `path`: must fail with exit code 1, without a panic; its stderr.
fn refused(path: &Path) -> String {
    let o = fwlidar(&["inspect".as_ref(), path.as_os_str()]);
    let err = common::text(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    err
}

#[test]
fn wdz_beside_the_laz_is_an_error_saying_how_to_decompress_it() {
    let (dir, path) = edited("r9.laz", |_| {});
    std::fs::rename(dir.path().join("x.wdp"), dir.path().join("x.wdz")).unwrap();
    let d = dir.path().display();
    let want = format!("laszip -i {d}/x.laz -o {d}/x.las -waveform");
    let err = refused(&path);
    assert!(
        err.contains(&format!(
            "{d}/x.laz: the waveform data packets are in {d}/x.wdz"
        )) && err.contains(&want)
            && err.contains(".wdp"),
        "{err}"
    );
    // replay stops the same way.
    let out = dir.path().join("out");
    let o = fwlidar(&[
        "replay".as_ref(),
        path.as_os_str(),
        "--no-progress".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(common::text(&o.stderr).contains(&want));
    match LasReader::open(&path) {
        Err(LasReadError::CompressedWdp { wdz, command, .. }) => {
            assert!(wdz.ends_with("x.wdz"));
            assert_eq!(command, want);
        }
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("a .wdz is not read"),
    }
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

/// Where the LAZ structures are: (start of point data, LASzip VLR payload, chunk table).
fn layout(b: &[u8]) -> (usize, usize, usize) {
    let off = u32_at(b, 96) as usize;
    let mut at = u16::from_le_bytes([b[94], b[95]]) as usize;
    let mut vlr = None;
    for _ in 0..u32_at(b, 100) {
        let len = u16::from_le_bytes([b[at + 20], b[at + 21]]) as usize;
        if &b[at + 2..at + 16] == b"laszip encoded" {
            vlr = Some(at + 54);
        }
        at += 54 + len;
    }
    let table = i64::from_le_bytes(b[off..off + 8].try_into().unwrap()) as usize;
    (off, vlr.expect("LASzip VLR"), table)
}

/// Damage placed by the file's structure: each is refused with an error naming the file and
/// what is wrong, exit code 1, no panic.
#[test]
fn damaged_laz_is_an_error_naming_the_file() {
    type Edit = Box<dyn Fn(&mut Vec<u8>)>;
    // Format 9 layered chunk: the uncompressed first point (63 bytes), the point count, 14 layer
    // sizes (Point14: 9, WavePacket14: 1, 4 extra bytes: 4), then the layers.
    let first_layer = |b: &[u8]| layout(b).0 + 8 + 63 + 4;
    let cases: Vec<(&str, Edit, &str)> = vec![
        (
            "r9.laz",
            Box::new(|b| {
                let (off, _, _) = layout(b);
                b.truncate(off + 20_000);
            }),
            "x.laz: truncated: the LAZ chunk table header",
        ),
        (
            // Unfinished writer: no chunk table offset, nothing valid at the end either.
            "r9.laz",
            Box::new(|b| {
                let (off, _, table) = layout(b);
                b[off..off + 8].copy_from_slice(&(-1i64).to_le_bytes());
                b.truncate(table);
                let n = b.len();
                b[n - 8..].copy_from_slice(&0i64.to_le_bytes());
            }),
            "LAZ chunk table offset",
        ),
        (
            "r9v.laz",
            Box::new(|b| {
                let (_, _, table) = layout(b);
                b[table + 4..table + 8].copy_from_slice(&0x00ff_ffffu32.to_le_bytes());
            }),
            "16777215 chunks, but the",
        ),
        (
            // The arithmetic decoder's first four bytes of the first layer all ones: the `laz`
            // crate indexes out of bounds (a panic inside it, turned into this error).
            "r9.laz",
            Box::new(move |b| {
                let at = first_layer(b) + 4 * 14;
                b[at..at + 4].copy_from_slice(&[0xff; 4]);
            }),
            "(LAZ chunk 0 of 1: points 0..2535, bytes 10186..47411): damaged: the LAZ decoder \
             failed on it (",
        ),
        (
            "r9.laz",
            Box::new(move |b| {
                let at = first_layer(b);
                b[at..at + 4].copy_from_slice(&0x7fff_ffffu32.to_le_bytes());
            }),
            "damaged: its 14 layers add up to",
        ),
        (
            // 100 bytes cut from the middle of the compressed points, the chunk table offset
            // moved to match: the chunks the table lists no longer fit before it.
            "r9v.laz",
            Box::new(|b| {
                let (off, _, table) = layout(b);
                let mid = off + 8 + (table - off - 8) / 2;
                b.drain(mid..mid + 100);
                b[off..off + 8].copy_from_slice(&(table as i64 - 100).to_le_bytes());
            }),
            "bytes from byte",
        ),
        (
            // The VLR's second item (WavePacket14, type 13) said to be RGB14 (type 11).
            "r9.laz",
            Box::new(|b| {
                let (_, vlr, _) = layout(b);
                b[vlr + 34 + 6] = 11;
            }),
            "LASzip VLR (\"laszip encoded\" 22204): items: Point14 v3 (30 bytes), RGB14",
        ),
        (
            "r4.laz",
            Box::new(|b| {
                let (_, vlr, _) = layout(b);
                b[vlr] = 1;
            }),
            "compressor: 1 (point-wise without chunks",
        ),
        (
            "r9.laz",
            Box::new(|b| {
                let (_, vlr, _) = layout(b);
                b[vlr - 52] = b'X';
            }),
            "x.laz: header: point data record format: 137 says the point records are \
             LAZ-compressed (format 9 with bit 7 set), but no LASzip VLR",
        ),
    ];
    for (name, edit, want) in cases {
        let (_dir, path) = edited(name, edit);
        let err = refused(&path);
        assert!(err.contains(want), "{name}: want {want:?}, got {err}");
        assert!(err.contains("x.laz"), "{err}");
    }
}

/// The decoder panic above, through the library: an error, the decoder not used again.
#[test]
fn a_panic_in_the_laz_crate_is_an_error_and_reading_stops() {
    let mut b = std::fs::read(laz("r9.laz")).unwrap();
    let at = layout(&b).0 + 8 + 63 + 4 + 4 * 14;
    b[at..at + 4].copy_from_slice(&[0xff; 4]);
    let wdp = std::fs::read(laz("r9.wdp")).unwrap();
    let mut r = LasReader::from_bytes(&b, Some(&wdp)).unwrap();
    // Every pulse before the damaged point is delivered, and counted as delivered (the fuzz
    // target found the packet of a pulse whose next point failed counted but not delivered).
    let mut p = Pulse::default();
    let (mut delivered, mut samples) = (0u64, 0u64);
    let e = loop {
        match r.next_pulse(&mut p) {
            Ok(true) => {
                delivered += 1;
                samples += p.raw.len() as u64;
            }
            Ok(false) => panic!("the damage goes unnoticed"),
            Err(e) => break e.to_string(),
        }
    };
    assert!(delivered >= 1);
    assert_eq!(r.stats().pulses, delivered);
    assert_eq!(r.stats().waveform_bytes, 2 * samples);
    assert!(
        e.starts_with("las.las: point ") && e.contains("damaged: the LAZ decoder failed on it ("),
        "{e}"
    );
    let again = r.next_pulse(&mut p).unwrap_err().to_string();
    assert!(
        again.contains("decompression stopped at an earlier error"),
        "{again}"
    );
}

fn bytes_of(name: &str) -> &'static [u8] {
    static ALL: OnceLock<Vec<(String, Vec<u8>)>> = OnceLock::new();
    let all = ALL.get_or_init(|| {
        ["r9.laz", "r9v.laz", "r4.laz", "r9.wdp"]
            .iter()
            .map(|n| (n.to_string(), std::fs::read(laz(n)).unwrap()))
            .collect()
    });
    &all.iter().find(|(n, _)| n == name).unwrap().1
}

proptest! {
    #![proptest_config(common::proptest_cases(300, "proptest-regressions/tests/laz_reader.txt"))]

    /// Truncated and bit-flipped LAZ bytes (flips mostly in the compressed points and the
    /// chunk table): every pulse is read or an error naming the file is returned; never a
    /// panic, never an endless loop.
    #[test]
    fn damaged_laz_is_read_or_refused(
        which in 0usize..3,
        flips in prop::collection::vec((0.0f64..1.0, 0u8..8, any::<bool>()), 0..6),
        cut in prop::option::weighted(0.25, 0.0f64..1.0),
    ) {
        let name = ["r9.laz", "r9v.laz", "r4.laz"][which];
        let mut b = bytes_of(name).to_vec();
        let (off, _, _) = layout(&b);
        let len = b.len();
        for (f, bit, anywhere) in flips {
            let from = if anywhere { 0 } else { off };
            let at = from + ((f * (len - from) as f64) as usize).min(len - from - 1);
            b[at] ^= 1 << bit;
        }
        if let Some(c) = cut {
            b.truncate((c * len as f64) as usize);
        }
        let wdp = bytes_of("r9.wdp");
        match LasReader::from_bytes(&b, Some(wdp)) {
            Err(e) => {
                let m = e.to_string();
                prop_assert!(m.starts_with("las.las") || m.starts_with("las.wdp"), "{}", m);
            }
            Ok(mut r) => {
                let mut p = Pulse::default();
                let mut n = 0u64;
                loop {
                    match r.next_pulse(&mut p) {
                        Ok(true) => {
                            n += 1;
                            prop_assert!(n <= r.info().header.number_of_points);
                        }
                        Ok(false) => break,
                        Err(e) => {
                            let m = e.to_string();
                            prop_assert!(
                                m.starts_with("las.las") || m.starts_with("las.wdp"),
                                "{}",
                                m
                            );
                            break;
                        }
                    }
                }
            }
        }
    }
}

/// `v` without the keys that hold wall time (`io_s`), at any depth.
fn without_timing(mut v: serde_json::Value) -> serde_json::Value {
    match &mut v {
        serde_json::Value::Object(m) => {
            m.remove("io_s");
            for x in m.values_mut() {
                *x = without_timing(x.take());
            }
        }
        serde_json::Value::Array(a) => {
            for x in a.iter_mut() {
                *x = without_timing(x.take());
            }
        }
        _ => {}
    }
    v
}
