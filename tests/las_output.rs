//! `returns.las` + `returns.wdp` read by a real reader: laspy (`tests/python/read_las.py`)
//! checks the header, every point (position within 1 mm, time, return numbering, intensity,
//! extra bytes, wave packet fields, the parametric line) and that the waveform bytes at each
//! point's (offset, size) in the `.wdp` are the raw counts the pulse carried.
//!
//! The interpreter is `$FWLIDAR_PYTHON`, else `.venv/bin/python` (made by `tests/run.sh` with
//! numpy and laspy). A missing interpreter or package fails the test, naming what is missing.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use fwlidar::pipeline::ports::PulseSink;
use fwlidar::pulse::{FittedReturn, Pulse, PulseGeometry, SegmentKind};
use fwlidar::sink::las_wave::{LasWaveOptions, LasWaveSink};
use serde_json::json;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// WGS 84 / UTM zone 33N, written out here (no network, no CRS database).
const UTM33N_WKT: &str = concat!(
    r#"PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84","#,
    r#"6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],"#,
    r#"PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],"#,
    r#"PARAMETER["central_meridian",15],PARAMETER["scale_factor",0.9996],"#,
    r#"PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1],"#,
    r#"AUTHORITY["EPSG","32633"]]"#
);

fn python() -> PathBuf {
    common::python_with(&["numpy", "laspy"])
}

/// Pulse `i`: two return segments, one to four returns given out of time order, 8- or 16-bit
/// counts, one of two gains, a slightly off-nadir beam over UTM 33N; every 10th has no geometry.
fn make_pulse(i: u64) -> Pulse {
    let bits = if i.is_multiple_of(3) { 8 } else { 16 };
    let mut p = Pulse {
        pulse_id: 10_000 + i,
        gps_time: 345_600.0 + i as f64 * 1e-4,
        scan_angle_deg: [-10.0 + (i % 40) as f32 * 0.5, f32::NAN],
        sample_ns: 1.0,
        gain_v_per_dn: if bits == 8 { 0.01 } else { 0.000_5 },
        offset_v: if i.is_multiple_of(2) { -0.1 } else { 0.0 },
        bits,
        geometry: (i % 10 != 9).then_some(PulseGeometry {
            anchor: [
                500_321.123 + i as f64 * 0.37,
                6_650_010.5 - i as f64 * 0.11,
                1_800.0,
            ],
            direction: [0.004 * (i % 5) as f64, -0.003, -0.149_8],
        }),
        ..Default::default()
    };
    let max = if bits == 8 { 255 } else { 4095 };
    p.push_segment(SegmentKind::Outgoing, 0, -8.0, (0..16u16).map(|k| k * 9));
    p.push_segment(
        SegmentKind::Return,
        0,
        11_900.0,
        (0..64u16).map(|k| ((u64::from(k) * 37 + i * 11) % max) as u16),
    );
    p.push_segment(
        SegmentKind::Return,
        1,
        12_000.0 + (i % 7) as f64,
        (0..32u16).map(|k| ((u64::from(k) * 53 + i * 5) % max) as u16),
    );
    let n = 1 + (i % 4) as usize;
    // Out of time order on purpose: a late return of segment 2 first.
    let candidates = [(2u16, 20.5f32), (1, 10.25), (1, 40.0), (2, 3.0)];
    for &(segment, bins) in candidates.iter().take(n) {
        let start = p.segments[segment as usize].start_ns;
        p.returns.push(FittedReturn {
            segment,
            position_bins: bins,
            time_ns: start + f64::from(bins) * p.sample_ns,
            amplitude: 0.05 + (i % 13) as f32 * 0.1,
            sigma_bins: 1.5 + (i % 3) as f32 * 0.25,
            residual: 0.01 + (i % 5) as f32 * 0.002,
            // Calibrated on two pulses of three; NaN (no calibration) on the third.
            backscatter: if i.is_multiple_of(3) {
                f32::NAN
            } else {
                0.1 + (i % 17) as f32 * 0.01
            },
        });
    }
    p
}

/// What the sink should have written for `pulses`, one JSON object per point in file order.
fn expected_points(pulses: &[Pulse]) -> Vec<serde_json::Value> {
    let mut points = Vec::new();
    for p in pulses {
        let Some(g) = p.geometry else { continue };
        let mut order: Vec<usize> = (0..p.returns.len()).collect();
        order.sort_by(|&a, &b| p.returns[a].time_ns.total_cmp(&p.returns[b].time_ns));
        for (rank, &k) in order.iter().enumerate() {
            let r = p.returns[k];
            let seg = p.segments[r.segment as usize];
            let pos: Vec<f64> = (0..3)
                .map(|a| g.anchor[a] + r.time_ns * g.direction[a])
                .collect();
            // Counts at most the digitizer's full scale, spread over 16 bits.
            let full_scale = f64::from((1u32 << p.bits) - 1);
            let intensity = ((f64::from(r.amplitude) / f64::from(p.gain_v_per_dn)).min(full_scale)
                * f64::from(1u32 << (16 - p.bits)))
            .round();
            points.push(json!({
                "x": pos[0], "y": pos[1], "z": pos[2],
                "gps_time": p.gps_time,
                "return_number": rank + 1,
                "number_of_returns": order.len(),
                "intensity": intensity,
                "amplitude": r.amplitude,
                // FWHM in ns.
                "width": f64::from(r.sigma_bins) * p.sample_ns * 2.354_820_045_030_949,
                "backscatter": (!r.backscatter.is_nan()).then_some(r.backscatter),
                "residual": r.residual,
                "location_ps": (r.time_ns - seg.start_ns) * 1000.0,
                "xyz_t": g.direction.map(|d| -d / 1000.0),
                "first_sample": g.direction.map(|d| d * seg.start_ns)
                    .iter().zip(g.anchor).map(|(a, b)| a + b).collect::<Vec<f64>>(),
                "bits": p.bits,
                "spacing_ps": 1000,
                "gain": f64::from(p.gain_v_per_dn),
                "offset": f64::from(p.offset_v),
                "counts": p.raw_of(r.segment as usize),
            }));
        }
    }
    points
}

/// Writes 500 pulses with `options` into a temporary folder; the folder and the expected points.
fn write_pulses(options: LasWaveOptions) -> (tempfile::TempDir, Vec<serde_json::Value>) {
    let dir = tempfile::tempdir().unwrap();
    let mut sink = LasWaveSink::create(dir.path(), options).unwrap();
    let pulses: Vec<Pulse> = (0..500).map(make_pulse).collect();
    for p in &pulses {
        sink.write(p).unwrap();
    }
    sink.finish().unwrap();
    let points = expected_points(&pulses);
    let stats = sink.stats();
    assert_eq!(stats.points, points.len() as u64);
    assert_eq!(stats.pulses_without_geometry, 50);
    (dir, points)
}

#[test]
fn laspy_reads_returns_las_and_wdp() {
    let (dir, points) = write_pulses(LasWaveOptions {
        crs_wkt: Some(UTM33N_WKT.to_string()),
        point_format: 9,
        ..Default::default()
    });
    let report = check_with_laspy(dir.path(), Some(UTM33N_WKT), &points, 9, "returns.las");
    eprintln!("{report}");
}

/// Point format 6 (the default): 30-byte records + the four extra bytes, every value by name,
/// no-data where the backscatter is NaN, the WKT CRS, no `.wdp`.
#[test]
fn laspy_reads_format_6_with_every_extra_byte_by_name() {
    let (dir, points) = write_pulses(LasWaveOptions {
        crs_wkt: Some(UTM33N_WKT.to_string()),
        ..Default::default()
    });
    let report = check_with_laspy(dir.path(), Some(UTM33N_WKT), &points, 6, "returns.las");
    assert!(report.contains("format 6"), "{report}");
    assert!(!dir.path().join("returns.wdp").exists());
}

/// Runs the checker on `out` with the expected points; returns its report line.
fn check_with_laspy(
    out: &Path,
    wkt: Option<&str>,
    points: &[serde_json::Value],
    point_format: u8,
    las: &str,
) -> String {
    let expected = out.join("expected.json");
    std::fs::write(
        &expected,
        serde_json::to_vec(&json!({
            "wkt": wkt, "points": points, "point_format": point_format, "las": las,
        }))
        .unwrap(),
    )
    .unwrap();
    let py = python();
    let o = Command::new(&py)
        .arg(Path::new(ROOT).join("tests/python/read_las.py"))
        .arg(out)
        .arg(&expected)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", py.display()));
    let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        !stdout.contains("MISSING PYTHON PACKAGE"),
        "{} lacks a package the LAS check needs: {stdout}(run tests/run.sh or `{} -m pip install \
         numpy laspy`)",
        py.display(),
        py.display()
    );
    assert!(
        o.status.success(),
        "laspy check failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(stdout.contains("all as written"), "{stdout}");
    stdout
}

/// Replays the bundled sample with the run configuration `config` (written into `dir`); the
/// output folder and stdout. Fails the test if the replay fails.
fn replay_sample_with(dir: &Path, config: &str) -> (PathBuf, String) {
    let cfg = dir.join("run.toml");
    std::fs::write(&cfg, config).unwrap();
    let out = dir.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .args([
            "replay",
            "replay/two_layer.fwcap",
            "--no-progress",
            "--config",
        ])
        .arg(&cfg)
        .arg("--out")
        .arg(&out)
        .args([
            "--set",
            "output.waveform_format=csv",
            "--set",
            "output.returns=true",
        ])
        .current_dir(ROOT)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (out, String::from_utf8_lossy(&o.stdout).into_owned())
}

/// `fwlidar replay` with `[output] las = true` and georeferencing off on the capture sample:
/// capture pulses then carry no geometry, so the LAS is empty (and valid), and the summary
/// counts every skipped pulse.
#[test]
fn replay_with_las_enabled_writes_a_valid_file_and_counts_pulses_without_geometry() {
    let dir = tempfile::tempdir().unwrap();
    let config = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml"))
        .unwrap()
        .replace("enabled = true", "enabled = false");
    assert!(config.contains("las = true") && config.contains("enabled = false"));
    let (out, stdout) = replay_sample_with(dir.path(), &config);
    assert!(
        common::summary_output(&stdout, "returns.las")
            .is_some_and(|l| l.starts_with("0 points (format 6)")),
        "{stdout}"
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let las = &summary["sinks"]["las"];
    assert_eq!(las["points"], 0);
    let skipped = las["pulses_without_geometry"].as_u64().unwrap();
    let without_returns = las["pulses_without_returns"].as_u64().unwrap();
    assert_eq!(skipped + without_returns, 2000, "{las}");
    assert!(skipped > 1000, "most sample pulses have returns: {las}");
    assert!(!out.join("returns.las.partial").exists());
    check_with_laspy(&out, None, &[], 6, "returns.las");
}

/// The capture sample georeferenced from its own NMEA into UTM 36S (`output_epsg` named, so the
/// CRS is known before the file is written): laspy reads every return as a point at the x, y, z
/// `returns.csv` gives, with the zone's WKT.
#[test]
fn georeferenced_capture_returns_read_back_with_laspy_where_returns_csv_puts_them() {
    let dir = tempfile::tempdir().unwrap();
    let config = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml"))
        .unwrap()
        .replace("# output_epsg = 32736", "output_epsg = 32736");
    assert!(config.contains("\noutput_epsg = 32736"));
    let (out, _) = replay_sample_with(dir.path(), &config);
    let csv = std::fs::read_to_string(out.join("returns.csv")).unwrap();
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').skip(8).map(|v| v.parse().unwrap()).collect())
        .collect();
    assert!(rows.len() > 3000, "{} returns", rows.len());
    let script = "import laspy, sys\n\
                  las = laspy.read(sys.argv[1])\n\
                  w = [v.string for v in las.header.vlrs if hasattr(v, 'string')]\n\
                  print(len(las.points), w[0] if w else 'NONE')\n\
                  for x, y, z in zip(las.x, las.y, las.z):\n\
                  \x20   print(f'{x:.3f} {y:.3f} {z:.3f}')\n";
    let o = Command::new(python())
        .args(["-c", script])
        .arg(out.join("returns.las"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8(o.stdout).unwrap();
    let mut lines = text.lines();
    let head = lines.next().unwrap();
    assert!(head.starts_with(&format!("{} ", rows.len())), "{head}");
    assert!(
        head.contains("UTM zone 36S") && head.contains("32736"),
        "{head}"
    );
    for (i, (l, r)) in lines.zip(&rows).enumerate() {
        let p: Vec<f64> = l.split(' ').map(|v| v.parse().unwrap()).collect();
        for k in 0..3 {
            assert!(
                (p[k] - r[k]).abs() <= 0.0011,
                "point {i}: laspy {p:?}, returns.csv {r:?}"
            );
        }
    }
}

/// The georeferenced sample with `las_rotate_s = 0.01` (the sample spans 0.04 s of pulse time)
/// and point format 9: several `returns_NNNN.las` + `.wdp` pairs, each complete and read by
/// laspy, with as many points in all as `returns.csv` has returns; no temporary file is left.
#[test]
fn rotation_writes_several_complete_files_holding_every_return() {
    let dir = tempfile::tempdir().unwrap();
    let config = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml"))
        .unwrap()
        .replace("las_point_format = 6", "las_point_format = 9")
        .replace("las_rotate_s = 0.0", "las_rotate_s = 0.01")
        .replace("# output_epsg = 32736", "output_epsg = 32736");
    assert!(config.contains("las_rotate_s = 0.01") && config.contains("las_point_format = 9"));
    let (out, stdout) = replay_sample_with(dir.path(), &config);
    let returns = std::fs::read_to_string(out.join("returns.csv"))
        .unwrap()
        .lines()
        .count()
        - 1;
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    let files: Vec<String> = summary["sinks"]["las"]["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap().to_string())
        .collect();
    assert!(files.len() >= 3, "{files:?}\n{stdout}");
    for (k, f) in files.iter().enumerate() {
        assert_eq!(f, &format!("returns_{k:04}.las"));
    }
    assert!(!out.join("returns.las").exists());
    let script = "import laspy, sys, struct\n\
                  from pathlib import Path\n\
                  total = 0\n\
                  for f in sys.argv[1:]:\n\
                  \x20   las = laspy.read(f)\n\
                  \x20   assert las.header.point_format.id == 9\n\
                  \x20   assert len(las.points) == las.header.point_count > 0, f\n\
                  \x20   wdp = Path(f[:-4] + '.wdp').read_bytes()\n\
                  \x20   assert struct.unpack('<Q', wdp[20:28])[0] == len(wdp) - 60, f\n\
                  \x20   end = las.wavepacket_offset.astype('u8') + las.wavepacket_size\n\
                  \x20   assert int(end.max()) == len(wdp), f\n\
                  \x20   assert list(las.point_format.extra_dimension_names) == \
                  ['amplitude', 'width', 'backscatter', 'residual']\n\
                  \x20   total += len(las.points)\n\
                  print(total)\n";
    let o = Command::new(python())
        .args(["-c", script])
        .args(files.iter().map(|f| out.join(f)))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let total: usize = String::from_utf8_lossy(&o.stdout).trim().parse().unwrap();
    assert_eq!(total, returns, "every return in one of the files");
    assert_eq!(summary["sinks"]["las"]["points"], returns);
    let leftovers: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".partial"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

/// The hyper point cloud of the georeferenced sample: one point per return-segment sample above
/// 10 V, exactly the values of `waveforms.csv` above it (laspy reads the `signal` extra byte), all
/// in the CRS of `returns.las`.
#[test]
fn hyper_points_hold_every_return_sample_above_the_threshold() {
    let dir = tempfile::tempdir().unwrap();
    let config = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml"))
        .unwrap()
        .replace("hyper_points = false", "hyper_points = true")
        .replace("# hyper_threshold_v = 10.0", "hyper_threshold_v = 10.0")
        .replace("# output_epsg = 32736", "output_epsg = 32736");
    assert!(config.contains("\nhyper_threshold_v = 10.0"));
    let (out, stdout) = replay_sample_with(dir.path(), &config);
    assert!(
        common::summary_output(&stdout, "hyper_points.las")
            .is_some_and(|l| l.contains("above 10.0 V")),
        "{stdout}"
    );
    // Expected: every value above 10 of the return segments in waveforms.csv.
    let pulses = std::fs::read_to_string(out.join("pulses.csv")).unwrap();
    let waves = std::fs::read_to_string(out.join("waveforms.csv")).unwrap();
    let mut want: Vec<f32> = Vec::new();
    for (row, line) in pulses.lines().skip(1).zip(waves.lines()) {
        if row.split(',').nth(4) != Some("return") {
            continue;
        }
        want.extend(
            line.split(',')
                .map(|v| v.parse::<f32>().unwrap())
                .filter(|&v| v > 10.0),
        );
    }
    want.sort_by(f32::total_cmp);
    assert!(want.len() > 1000, "{} samples", want.len());
    let script = "import laspy, sys, numpy as np\n\
                  las = laspy.read(sys.argv[1])\n\
                  assert las.header.point_format.id == 6\n\
                  assert list(las.point_format.extra_dimension_names) == ['signal', 'backscatter']\n\
                  w = [v.string for v in las.header.vlrs if hasattr(v, 'string')]\n\
                  assert '32736' in w[0], w\n\
                  assert len(las.points) == las.header.point_count\n\
                  b = np.asarray(las.backscatter, dtype=np.float64)\n\
                  s = np.asarray(las.signal, dtype=np.float64)\n\
                  assert np.all(np.isfinite(b)) and np.all(b > 0), b.min()\n\
                  r = b / s\n\
                  assert r.max() / r.min() < 1.2, (r.min(), r.max())\n\
                  for v in np.sort(np.asarray(las.signal, dtype=np.float32)):\n\
                  \x20   print(repr(float(v)))\n";
    let o = Command::new(python())
        .args(["-c", script])
        .arg(out.join("hyper_points.las"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let got: Vec<f32> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| l.parse::<f64>().unwrap() as f32)
        .collect();
    assert_eq!(got.len(), want.len());
    assert!(got == want, "signal values differ from waveforms.csv");
}

/// Bad LAS output keys are reported by `fwlidar validate`, each with its field and reason.
#[test]
fn las_output_keys_are_validated() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("bad.toml");
    std::fs::write(
        &cfg,
        "[output]\nhyper_points = true\nlas_point_format = 7\nlas_rotate_s = -1\nlas_flush_s = nan\n",
    )
    .unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .arg("validate")
        .arg(&cfg)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    for needle in [
        "output.hyper_threshold_v: must be given",
        "output.las_point_format: must be 6 or 9, got 7",
        "output.las_rotate_s: must be 0 (one file) or a positive number of seconds, got -1",
        "output.las_flush_s:",
    ] {
        assert!(err.contains(needle), "{needle:?} not in {err}");
    }
}
