//! `fwlidar repair`: a `replay` killed (SIGKILL) while writing rotated LAS files leaves a
//! `returns_NNNN.las.partial` whose header is stale; repair rebuilds it and laspy then reads every
//! point, equal to the prefix of the same file from an uninterrupted run. Bad input is refused
//! with the file and field named, a non-zero exit and the original untouched; no mutation of a
//! file makes the analysis panic.

mod common;

use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{BIN, ROOT, python, text};
use fwlidar::format::las_points::{PointSix, write_point_cloud};
use fwlidar::format::las_repair::analyse;
use fwlidar::format::las_write::ExtraDim;
use fwlidar::pipeline::ports::PulseSink;
use fwlidar::pulse::{FittedReturn, Pulse, PulseGeometry, SegmentKind};
use fwlidar::sink::las_wave::{LasWaveOptions, LasWaveSink};
use proptest::prelude::*;

/// The sample's run configuration made slow enough to be killed mid-run (one worker, 1500
/// Richardson-Lucy iterations), writing format 9 rotated every 10 ms of pulse time and handed to
/// the OS every 0.5 ms of pulse time, georeferenced into UTM 36S.
fn slow_config() -> String {
    let c = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml"))
        .unwrap()
        .replace("workers = 0", "workers = 1")
        .replace("iterations = 20 }", "iterations = 1500 }")
        .replace("las = false", "las = true")
        .replace("las_point_format = 6", "las_point_format = 9")
        .replace("las_rotate_s = 0.0", "las_rotate_s = 0.01")
        .replace("las_flush_s = 1.0", "las_flush_s = 0.0005")
        .replace("# output_epsg = 32736", "output_epsg = 32736");
    for k in [
        "workers = 1",
        "iterations = 1500 }",
        "las_rotate_s = 0.01",
        "las_flush_s = 0.0005",
        "\noutput_epsg = 32736",
    ] {
        assert!(c.contains(k), "config/replay.toml changed: {k} not set");
    }
    c
}

fn replay_cmd(cfg: &Path, out: &Path) -> Command {
    let mut c = Command::new(BIN);
    c.args([
        "replay",
        "replay/two_layer.fwcap",
        "--no-progress",
        "--config",
    ])
    .arg(cfg)
    .arg("--out")
    .arg(out)
    .current_dir(ROOT);
    c
}

fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes(b[o..o + 4].try_into().unwrap())
}

/// The open `returns_NNNN.las.partial` in `out` that holds at least `min_points` whole records
/// beyond its preamble, with at least one completed file before it.
fn killable_partial(out: &Path, min_points: u64) -> Option<PathBuf> {
    let mut partial = None;
    let mut complete = false;
    for e in std::fs::read_dir(out).ok()? {
        let e = e.ok()?;
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with("returns_") && name.ends_with(".las.partial") {
            partial = Some(e.path());
        } else if name.starts_with("returns_") && name.ends_with(".las") {
            complete = true;
        }
    }
    let p = partial?;
    let b = std::fs::read(&p).ok()?;
    if !complete || b.len() < 107 {
        return None;
    }
    let offset = u64::from(u32_at(&b, 96));
    let rl = u64::from(u16::from_le_bytes([b[105], b[106]]));
    (b.len() as u64 >= offset + min_points * rl).then_some(p)
}

/// Prints the listed fields of every point of each LAS file, one line per point, with laspy.
fn laspy_points(files: &[&Path]) -> Vec<Vec<String>> {
    let script = "import laspy, sys\n\
                  for f in sys.argv[1:]:\n\
                  \x20   las = laspy.read(f)\n\
                  \x20   assert las.header.point_count == len(las.points)\n\
                  \x20   cols = [las.X, las.Y, las.Z, las.gps_time, las.return_number,\n\
                  \x20           las.number_of_returns, las.intensity, las.amplitude, las.width,\n\
                  \x20           las.backscatter, las.residual, las.wavepacket_index,\n\
                  \x20           las.wavepacket_offset, las.wavepacket_size]\n\
                  \x20   print('FILE', len(las.points), las.header.mins.tolist(), las.header.maxs.tolist())\n\
                  \x20   for row in zip(*cols):\n\
                  \x20       print(' '.join(repr(float(v)) for v in row))\n";
    let o = Command::new(python())
        .args(["-c", script])
        .args(files)
        .output()
        .unwrap();
    assert!(o.status.success(), "laspy: {}", text(&o.stderr));
    let mut out: Vec<Vec<String>> = Vec::new();
    for l in text(&o.stdout).lines() {
        if l.starts_with("FILE") {
            out.push(vec![l.to_string()]);
        } else {
            out.last_mut().unwrap().push(l.to_string());
        }
    }
    out
}

fn repair_json(file: &Path) -> serde_json::Value {
    let o = Command::new(BIN)
        .args(["repair", "--json"])
        .arg(file)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "repair {}: {}",
        file.display(),
        text(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn killed_replay_is_repaired_and_reads_back_as_the_uninterrupted_runs_prefix() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("run.toml");
    std::fs::write(&cfg, slow_config()).unwrap();

    // The run that is killed: SIGKILL as soon as a rotated file is complete and the open one
    // holds points.
    let killed = dir.path().join("killed");
    let mut child = replay_cmd(&cfg, &killed)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let mut partial = None;
    while t0.elapsed() < Duration::from_secs(120) {
        if let Some(p) = killable_partial(&killed, 20) {
            partial = Some(p);
            break;
        }
        if child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let really_killed = child.try_wait().unwrap().is_none();
    child.kill().unwrap();
    child.wait().unwrap();

    // The uninterrupted run.
    let full = dir.path().join("full");
    let o = replay_cmd(&cfg, &full).output().unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));

    // The open file may have been completed between the look and the kill: take the one open
    // at the kill then.
    let partial = partial.and_then(|p| {
        if p.exists() {
            Some(p)
        } else {
            killable_partial(&killed, 1)
        }
    });
    let partial = match (really_killed, partial) {
        (true, Some(p)) => p,
        _ => {
            // The run ended before it could be killed (a very fast machine): make the cut file
            // from a finished one by resetting what a finished header adds.
            eprintln!("replay finished before the kill; cutting a finished file instead");
            std::fs::create_dir_all(&killed).unwrap();
            let p = killed.join("returns_0001.las.partial");
            let mut b = std::fs::read(full.join("returns_0001.las")).unwrap();
            b[179..227].fill(0);
            b[247..375].fill(0);
            std::fs::write(&p, &b).unwrap();
            let mut w = std::fs::read(full.join("returns_0001.wdp")).unwrap();
            w[20..28].fill(0);
            std::fs::write(killed.join("returns_0001.wdp.partial"), &w).unwrap();
            p
        }
    };
    let name = partial.file_name().unwrap().to_string_lossy().into_owned();
    let index = &name["returns_".len().."returns_".len() + 4];
    let original = std::fs::read(&partial).unwrap();
    let stale_count = u64::from_le_bytes(original[247..255].try_into().unwrap());

    let report = repair_json(&partial);
    let points = report["points"].as_u64().unwrap();
    assert!(points >= 20, "{report}");
    assert!(
        stale_count < points,
        "the killed file's header was not finalised: {stale_count} of {points} points counted"
    );
    assert_eq!(report["repaired"], true);
    assert!(
        report["changed"]
            .as_array()
            .unwrap()
            .iter()
            .any(|c| c["field"] == "number of point records"),
        "{report}"
    );
    let bak = PathBuf::from(report["backup"].as_str().unwrap());
    assert_eq!(
        std::fs::read(&bak).unwrap(),
        original,
        "backup is the original"
    );
    assert_eq!(
        report["wdp"]["record_length_after"].as_u64().unwrap() + 60,
        report["wdp"]["bytes"].as_u64().unwrap()
    );

    // laspy reads every point of the repaired file; they equal the uninterrupted run's first
    // points of the same file, field for field.
    let full_file = full.join(format!("returns_{index}.las"));
    let got = laspy_points(&[&partial, &full_file]);
    let (rep, whole) = (&got[0], &got[1]);
    assert_eq!(rep.len() - 1, points as usize, "{}", rep[0]);
    assert!(whole.len() >= rep.len(), "{} vs {}", rep[0], whole[0]);
    for (i, (a, b)) in rep[1..].iter().zip(&whole[1..]).enumerate() {
        assert_eq!(a, b, "point {i} differs from the uninterrupted run");
    }
    // The repaired .wdp holds the same packets as the uninterrupted run's, up to its end.
    let w = std::fs::read(killed.join(format!("returns_{index}.wdp.partial"))).unwrap();
    let wf = std::fs::read(full.join(format!("returns_{index}.wdp"))).unwrap();
    assert!(wf.len() >= w.len() && wf[60..w.len()] == w[60..]);
    // A second repair finds nothing to do.
    let again = repair_json(&partial);
    assert_eq!(again["repaired"], false, "{again}");

    // The same crash cut mid-record: the partial record is dropped and said.
    let cut = dir.path().join("cut.las");
    let mut b = original.clone();
    b.truncate(b.len() - 7);
    std::fs::write(&cut, &b).unwrap();
    std::fs::copy(
        bak.with_file_name(format!("returns_{index}.wdp.partial.bak")),
        dir.path().join("cut.wdp"),
    )
    .unwrap();
    let r2 = repair_json(&cut);
    let rl = r2["point_record_length"].as_u64().unwrap();
    assert_eq!(
        r2["trailing_bytes_dropped"].as_u64().unwrap(),
        rl - 7,
        "{r2}"
    );
    assert!(r2["points"].as_u64().unwrap() < points + 1);
    if report["points_dropped_without_waveform"] == 0 {
        assert_eq!(r2["points"].as_u64().unwrap(), points - 1, "{r2}");
    }
    let got = laspy_points(&[&cut]);
    assert_eq!(got[0].len() - 1, r2["points"].as_u64().unwrap() as usize);
    for (a, b) in got[0][1..].iter().zip(&rep[1..]) {
        assert_eq!(a, b);
    }
}

/// A small complete PF6 file with a WKT and two extra dimensions.
fn small_las(path: &Path) -> Vec<u8> {
    let extra = [ExtraDim::f32("a", "a (V)"), ExtraDim::f32("b", "b (ns)")];
    let pts = (0..5).map(|i| {
        (
            PointSix {
                xyz: [500_000.0 + f64::from(i), 6_000_000.0, 10.0 * f64::from(i)],
                return_number: 1 + (i % 2) as u8,
                number_of_returns: 2,
                gps_time: f64::from(i),
                ..Default::default()
            },
            [f64::from(i), 1.0],
        )
    });
    write_point_cloud(path, Some("PROJCS[\"x\"]"), &extra, pts).unwrap();
    std::fs::read(path).unwrap()
}

/// Runs `fwlidar repair FILE`; asserts it fails with exit 1, the message naming the file and
/// containing every `needles`, and the file untouched with no backup.
fn refused(file: &Path, needles: &[&str]) {
    let before = std::fs::read(file).ok();
    let o = Command::new(BIN).arg("repair").arg(file).output().unwrap();
    let err = text(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(&file.display().to_string()), "{err}");
    for n in needles {
        assert!(err.contains(n), "{n:?} not in {err}");
    }
    assert_eq!(std::fs::read(file).ok(), before, "file untouched");
}

#[test]
fn repair_refuses_bad_input_naming_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();

    let not_las = d.join("notes.las");
    std::fs::write(&not_las, "this is not a point cloud at all").unwrap();
    refused(&not_las, &["not a LAS file", "file signature"]);
    assert!(!d.join("notes.las.bak").exists());

    let v12 = d.join("v12.las");
    let mut b = small_las(&v12);
    b[25] = 2;
    std::fs::write(&v12, &b).unwrap();
    refused(&v12, &["version", "LAS 1.2"]);

    let cut_vlrs = d.join("cut_vlrs.las");
    let b = small_las(&cut_vlrs);
    std::fs::write(&cut_vlrs, &b[..400]).unwrap();
    refused(&cut_vlrs, &["offset to point data", "VLR area is cut"]);

    let many_vlrs = d.join("many_vlrs.las");
    let mut b = small_las(&many_vlrs);
    b[100..104].copy_from_slice(&3u32.to_le_bytes());
    std::fs::write(&many_vlrs, &b).unwrap();
    refused(&many_vlrs, &["VLR 2"]);

    let laz = d.join("laz.las");
    let mut b = small_las(&laz);
    b[104] |= 0x80;
    std::fs::write(&laz, &b).unwrap();
    refused(&laz, &["point data record format", "LAZ"]);

    // A cut file whose backup exists already: refused, nothing changed.
    let crashed = d.join("crashed.las");
    let mut b = small_las(&crashed);
    b[247..255].fill(0);
    std::fs::write(&crashed, &b).unwrap();
    std::fs::write(d.join("crashed.las.bak"), b"older backup").unwrap();
    refused(&crashed, &["crashed.las.bak", "already exists"]);
    assert_eq!(
        std::fs::read(d.join("crashed.las.bak")).unwrap(),
        b"older backup"
    );

    // A path that does not exist.
    refused(&d.join("missing.las"), &["cannot open"]);

    // A file that cannot be written: root may write through any mode, so the file lies on a
    // read-only file system for root.
    let ro = d.join("ro");
    std::fs::create_dir(&ro).unwrap();
    let ro_file = ro.join("crashed.las");
    // SAFETY: geteuid has no preconditions.
    let as_root = unsafe { libc::geteuid() } == 0;
    let disk = as_root.then(|| common::Tmpfs::mount(&ro, "4m"));
    std::fs::write(&ro_file, &b).unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&ro_file, std::fs::Permissions::from_mode(0o444)).unwrap();
    std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
    if let Some(disk) = &disk {
        disk.read_only();
    }
    refused(&ro_file, &["cannot open for writing"]);
    assert!(!ro.join("crashed.las.bak").exists());
    drop(disk);
    std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();

    // A complete file: nothing to repair, no backup, exit 0.
    let good = d.join("good.las");
    let b = small_las(&good);
    let o = Command::new(BIN).arg("repair").arg(&good).output().unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(text(&o.stdout).contains("nothing to repair"));
    assert_eq!(std::fs::read(&good).unwrap(), b);
    assert!(!d.join("good.las.bak").exists());

    // The crashed one without the stale backup: repaired to the original header.
    std::fs::remove_file(d.join("crashed.las.bak")).unwrap();
    let r = repair_json(&crashed);
    assert_eq!(r["points"], 5);
    let repaired = std::fs::read(&crashed).unwrap();
    let orig = std::fs::read(&good).unwrap();
    assert_eq!(
        repaired[179..375],
        orig[179..375],
        "bounds and counts rebuilt"
    );
}

/// A crashed-looking format 9 file from the sink (header counts zeroed) and its `.wdp` header.
fn crashed_pf9() -> (Vec<u8>, Vec<u8>) {
    let dir = tempfile::tempdir().unwrap();
    let mut sink = LasWaveSink::create(
        dir.path(),
        LasWaveOptions {
            point_format: 9,
            crs_wkt: Some("PROJCS[\"x\"]".into()),
            ..Default::default()
        },
    )
    .unwrap();
    for i in 0..6u64 {
        let mut p = Pulse {
            pulse_id: i,
            gps_time: i as f64,
            gain_v_per_dn: 0.01,
            bits: 8,
            sample_ns: 1.0,
            geometry: Some(PulseGeometry {
                anchor: [500_000.0 + i as f64, 6_000_000.0, 1000.0],
                direction: [0.0, 0.0, -0.15],
            }),
            ..Default::default()
        };
        p.push_segment(SegmentKind::Return, 0, 100.0, (0..8u16).map(|k| k * 3));
        for t in [101.0, 104.0] {
            p.returns.push(FittedReturn {
                segment: 0,
                time_ns: t,
                amplitude: 0.5,
                sigma_bins: 1.0,
                ..Default::default()
            });
        }
        sink.write(&p).unwrap();
    }
    sink.finish().unwrap();
    let mut b = std::fs::read(dir.path().join("returns.las")).unwrap();
    b[179..227].fill(0);
    b[247..375].fill(0);
    let w = std::fs::read(dir.path().join("returns.wdp")).unwrap();
    (b, w)
}

proptest! {
    #![proptest_config(common::proptest_cases(400, "proptest-regressions/tests/las_repair.txt"))]

    /// Any damage to a crashed file (bytes changed, the file cut anywhere) is repaired or
    /// refused, never a panic; a plan never grows the file and counts only whole records.
    #[test]
    fn repair_analysis_never_panics_on_damaged_files(
        edits in proptest::collection::vec((0usize..25_000, any::<u8>()), 0..12),
        cut in 0usize..25_000,
        wdp_edits in proptest::collection::vec((0usize..60, any::<u8>()), 0..3),
        wdp_cut in 0usize..200,
    ) {
        use std::sync::OnceLock;
        static BASE: OnceLock<(Vec<u8>, Vec<u8>)> = OnceLock::new();
        let (base, wdp) = BASE.get_or_init(crashed_pf9);
        let mut b = base.clone();
        for (at, v) in &edits {
            if let Some(x) = b.get_mut(at % base.len()) {
                *x = *v;
            }
        }
        b.truncate(cut.min(b.len()).max(if cut % 2 == 0 { b.len() } else { 0 }));
        let mut w = wdp.clone();
        for (at, v) in &wdp_edits {
            w[*at] = *v;
        }
        w.truncate(w.len().saturating_sub(wdp_cut));
        let head = &w[..w.len().min(60)];
        let len = b.len() as u64;
        if let Ok(plan) = analyse(&mut Cursor::new(&b), "m.las", len, Some(("m.wdp", w.len() as u64, head))) {
            prop_assert!(plan.new_len <= len);
            let r = &plan.report;
            if plan.new_len < len {
                prop_assert_eq!(plan.new_len, r.offset_to_point_data + r.points * u64::from(r.point_record_length));
            }
        }
        // And without a .wdp.
        let _ = analyse(&mut Cursor::new(&b), "m.las", len, None);
    }
}
