//! The command line end to end, through the real binary: simulate → capture → replay → outputs,
//! bad input (clear errors naming the file and field, non-zero exit, nothing written over),
//! SIGTERM (clean stop, every output flushed) and kill -9 of the capture writer.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use fwlidar::format::{CaptureReader, Record};

const BIN: &str = env!("CARGO_BIN_EXE_fwlidar");
const ROOT: &str = env!("CARGO_MANIFEST_DIR");
/// The flags that ask `replay` for its text outputs beside the binary ones.
const CSV_OUTPUTS: [&str; 4] = [
    "--set",
    "output.waveform_format=csv",
    "--set",
    "output.returns=true",
];

fn fwlidar(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .current_dir(ROOT)
        .output()
        .expect("run fwlidar")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn read_summary(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap()
}

fn sample() -> PathBuf {
    Path::new(ROOT).join("replay/two_layer.fwcap")
}

fn scene() -> PathBuf {
    Path::new(ROOT).join("config/scenes/two_layer.toml")
}

#[test]
fn sample_capture_is_reproducible() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("again.fwcap");
    let o = fwlidar(&[
        "simulate",
        "--scene",
        scene().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let fresh = std::fs::read(&out).unwrap();
    let committed = std::fs::read(sample()).unwrap();
    assert!(
        fresh == committed,
        "replay/two_layer.fwcap differs from a fresh simulation: regenerate it (replay/README.md)"
    );
}

/// Reads `waveforms.csv` into rows of f64.
fn read_waveforms(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| l.split(',').map(|v| v.parse::<f64>().unwrap()).collect())
        .collect()
}

#[test]
fn replay_of_the_sample_writes_consistent_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let o = fwlidar(&[
        "replay",
        sample().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
        "--set",
        "output.waveform_format=csv",
        "--set",
        "output.returns=true",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let stdout = text(&o.stdout);
    assert!(stdout.contains("2000 in, 2000 out"), "{stdout}");

    let summary = read_summary(&out);
    assert_eq!(summary["pulses_in"], 2000);
    assert_eq!(summary["pulses_out"], 2000);
    assert_eq!(summary["dropped_total"], 0);
    assert_eq!(summary["source"]["records"]["frames"], 2000);
    assert_eq!(summary["source"]["skipped"]["bytes_skipped"], 0);
    assert_eq!(summary["stages"][0]["name"], "denoise");
    assert_eq!(summary["stages"][0]["received"], 2000);
    let svc = &summary["stages"][0]["service"];
    assert!(svc["p50_ns"].as_u64().unwrap() > 0);
    assert!(svc["p99_ns"].as_u64().unwrap() >= svc["p50_ns"].as_u64().unwrap());
    assert!(svc["max_ns"].as_u64().unwrap() >= svc["p999_ns"].as_u64().unwrap());
    assert!(summary["pulses_per_s"].as_f64().unwrap() > 0.0);
    let nav = &summary["nav"]["ports"]["0"];
    assert!(nav["bytes"].as_u64().unwrap() > 0);
    // The simulated NMEA decodes completely and is dated by its ZDA: GGA, PASHR, ZDA.
    assert_eq!(nav["rejected"], 0, "{nav}");
    assert!(nav["by_kind"]["GGA"].as_u64().unwrap() >= 2, "{nav}");
    assert!(nav["by_kind"]["ZDA"].as_u64().unwrap() >= 1, "{nav}");
    assert_eq!(nav["first_gps_time"]["week"], 1690, "{nav}");

    // pulses.csv and waveforms.csv line up row for row, with the declared lengths.
    let pulses = std::fs::read_to_string(out.join("pulses.csv")).unwrap();
    let rows: Vec<Vec<&str>> = pulses
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    let waves = read_waveforms(&out.join("waveforms.csv"));
    assert_eq!(rows.len(), 4000);
    assert_eq!(waves.len(), 4000);
    for (r, w) in rows.iter().zip(&waves) {
        assert_eq!(r[8].parse::<usize>().unwrap(), w.len());
    }

    // The physics survived: the mean denoised return has its two peaks where the scene put the
    // plane (15 m above ground) and the ground: 15 m apart = 100 bins at 1 ns.
    let returns: Vec<&Vec<f64>> = rows
        .iter()
        .zip(&waves)
        .filter(|(r, _)| r[4] == "return")
        .map(|(_, w)| w)
        .collect();
    let n = returns[0].len();
    let mean: Vec<f64> = (0..n)
        .map(|i| returns.iter().map(|w| w[i]).sum::<f64>() / returns.len() as f64)
        .collect();
    let mut peaks: Vec<(usize, f64)> = (1..n - 1)
        .filter(|&i| mean[i] > mean[i - 1] && mean[i] >= mean[i + 1] && mean[i] > 5.0)
        .map(|i| (i, mean[i]))
        .collect();
    peaks.sort_by(|a, b| b.1.total_cmp(&a.1));
    assert!(peaks.len() >= 2, "{peaks:?}");
    let (a, b) = (peaks[0].0.min(peaks[1].0), peaks[0].0.max(peaks[1].0));
    assert!((b - a).abs_diff(100) <= 1, "peaks at {a} and {b}");
    // The baseline (12 DN, volts = counts for this sensor) was removed: the tail is near zero.
    assert!(mean[n - 5].abs() < 1.0, "tail {}", mean[n - 5]);
    // ... and so are the pre-trigger samples of the outgoing pulse, whose peak is ~200 DN.
    let outgoing: Vec<&Vec<f64>> = rows
        .iter()
        .zip(&waves)
        .filter(|(r, _)| r[4] == "outgoing")
        .map(|(_, w)| w)
        .collect();
    let head: f64 = outgoing
        .iter()
        .map(|w| w[..4].iter().sum::<f64>() / 4.0)
        .sum::<f64>()
        / outgoing.len() as f64;
    let peak = outgoing
        .iter()
        .map(|w| w.iter().cloned().fold(f64::MIN, f64::max))
        .sum::<f64>()
        / outgoing.len() as f64;
    assert!(
        head.abs() < 1.0 && peak > 150.0,
        "outgoing head {head}, peak {peak}"
    );

    // The embedded default runs the whole signal chain ...
    let names: Vec<&str> = summary["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        ["denoise", "deconvolve", "decompose", "calibrate", "metrics"]
    );
    // ... and its discrete returns (returns.csv) sit where the physics puts the two surfaces:
    // two-way travel time 2R/c to the ground at 1000 m and to the plane 15 m above it.
    let c_m_per_ns = fwlidar::core::units::C_M_PER_NS;
    let truth_ns = [2.0 * 985.0 / c_m_per_ns, 2.0 * 1000.0 / c_m_per_ns];
    let text_returns = std::fs::read_to_string(out.join("returns.csv")).unwrap();
    let mut lines = text_returns.lines();
    assert_eq!(
        lines.next(),
        Some(
            "pulse_id,gps_time,segment,position_bins,time_ns,amplitude_v,sigma_bins,residual_v,x,y,z,\
             backscatter"
        )
    );
    let mut per_pulse: std::collections::BTreeMap<u64, Vec<f64>> = Default::default();
    // The embedded configuration georeferences the pulses from the capture's NMEA: every
    // return has x, y, z in UTM 36S (the first fix at 24.99 S, 31.59 E). The simulator's
    // scene is in vacuum and the default air refractive index n = 1.00027 shortens each range
    // to R / n, so a surface at height h lies at h + (H − h)(1 − 1/n) (H = 1000 m up).
    let n = 1.00027;
    let truth_z = [15.0 + 985.0 * (1.0 - 1.0 / n), 1000.0 * (1.0 - 1.0 / n)];
    let mut z_offsets = [Vec::new(), Vec::new()];
    for l in lines {
        let f: Vec<&str> = l.split(',').collect();
        assert_eq!(f.len(), 12, "{l}");
        let xyz: Vec<f64> = f[8..11]
            .iter()
            .map(|v| v.parse().unwrap_or_else(|_| panic!("georeferenced: {l}")))
            .collect();
        // Easting and northing of the flight line's start (UTM 36S), 60 m/s east for 0.03 s.
        assert!(
            (xyz[0] - 357_696.0).abs() < 5.0 && (xyz[1] - 7_235_420.0).abs() < 5.0,
            "{l}"
        );
        let t: f64 = f[4].parse().unwrap();
        if let Some(k) = truth_ns.iter().position(|&s| (t - s).abs() < 1.0) {
            z_offsets[k].push(xyz[2] - truth_z[k]);
        }
        let amplitude: f64 = f[5].parse().unwrap();
        let sigma: f64 = f[6].parse().unwrap();
        assert!(amplitude > 0.0 && sigma > 0.0, "{l}");
        per_pulse.entry(f[0].parse().unwrap()).or_default().push(t);
    }
    let mut both = 0;
    let mut offsets = [Vec::new(), Vec::new()];
    let mut extras = 0;
    for times in per_pulse.values() {
        let mut found = [false; 2];
        for &t in times {
            match truth_ns.iter().position(|&s| (t - s).abs() < 1.0) {
                Some(k) => {
                    found[k] = true;
                    offsets[k].push(t - truth_ns[k]);
                }
                None => extras += 1,
            }
        }
        both += usize::from(found == [true, true]);
    }
    for (k, o) in z_offsets.iter_mut().enumerate() {
        o.sort_by(f64::total_cmp);
        let median = o[o.len() / 2];
        assert!(
            median.abs() < 0.05,
            "surface {k}: median height offset {median} m"
        );
    }
    let georef = &summary["source"]["georeference"];
    assert_eq!(georef["georeferenced"], 2000, "{georef}");
    assert_eq!(georef["output_crs"], "EPSG:32736", "{georef}");
    // Measured: 1985 of 2000 pulses with both surfaces, median offsets under 0.01 ns, 500 extras.
    assert!(both >= 1960, "{both} of 2000 pulses have both surfaces");
    for o in &mut offsets {
        o.sort_by(f64::total_cmp);
        let median = o[o.len() / 2];
        assert!(median.abs() < 0.2, "median offset {median} ns");
    }
    assert!(extras < 1000, "{extras} returns away from both surfaces");
}

#[test]
fn replay_defaults_to_the_bundled_sample_and_embedded_config() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o");
    let o = fwlidar(&["replay", "--out", out.to_str().unwrap(), "--no-progress"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(out.join("summary.json").exists());
    assert!(text(&o.stdout).contains("two_layer.fwcap"));
}

#[test]
fn json_logs_are_json() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o");
    let o = fwlidar(&[
        "--log-format",
        "json",
        "replay",
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success());
    let err = text(&o.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert!(!lines.is_empty());
    for l in lines {
        let v: serde_json::Value = serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}"));
        assert!(v.get("level").is_some());
    }
}

#[test]
fn inspect_lists_every_pulse_as_json() {
    let o = fwlidar(&["inspect", sample().to_str().unwrap(), "--pulses", "--json"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = text(&o.stdout);
    let lines: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2000);
    let first = &lines[0];
    assert!(first["gps_time"].as_f64().unwrap() > 0.0);
    let segs = first["segments"].as_array().unwrap();
    assert_eq!(segs[0]["kind"], "outgoing");
    assert_eq!(segs[1]["kind"], "return");
    assert_eq!(segs[1]["samples"].as_array().unwrap().len(), 225);
    assert_eq!(segs[1]["sample_ns"], 1.0);
    // Times increase pulse by pulse.
    assert!(
        lines
            .windows(2)
            .all(|w| w[1]["gps_time"].as_f64() > w[0]["gps_time"].as_f64())
    );
    let o = fwlidar(&["inspect", sample().to_str().unwrap()]);
    assert!(text(&o.stdout).contains("2000 frames"));
}

// ---- bad input -------------------------------------------------------------------------------

fn assert_fails(o: &Output, code: i32, needles: &[&str]) {
    let err = text(&o.stderr);
    assert_eq!(o.status.code(), Some(code), "stderr: {err}");
    for n in needles {
        assert!(err.contains(n), "expected `{n}` in: {err}");
    }
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn replay_of_a_missing_file_or_a_directory_fails_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o");
    let o = fwlidar(&[
        "replay",
        "/nonexistent/x.fwcap",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_fails(&o, 1, &["/nonexistent/x.fwcap"]);
    assert!(!out.exists(), "nothing written for a missing input");
    let o = fwlidar(&[
        "replay",
        dir.path().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_fails(&o, 1, &[dir.path().to_str().unwrap()]);
}

#[test]
fn replay_of_an_empty_or_newer_capture_fails_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty.fwcap");
    std::fs::write(&empty, b"").unwrap();
    let o = fwlidar(&["replay", empty.to_str().unwrap(), "--out", "/tmp/never"]);
    assert_fails(&o, 1, &["empty.fwcap", "empty"]);

    let mut newer = std::fs::read(sample()).unwrap();
    newer[8] = 2; // major version 2 (minor stays 1)
    let p = dir.path().join("newer.fwcap");
    std::fs::write(&p, &newer).unwrap();
    let o = fwlidar(&["replay", p.to_str().unwrap(), "--out", "/tmp/never"]);
    assert_fails(&o, 1, &["newer.fwcap", "2.1", "newer than"]);

    let junk = dir.path().join("notes.txt");
    std::fs::write(&junk, b"flight notes, not a capture\n").unwrap();
    let o = fwlidar(&["inspect", junk.to_str().unwrap()]);
    assert_fails(&o, 1, &["notes.txt", "not an fwlidar capture"]);
}

#[test]
fn bad_configuration_is_reported_with_file_line_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("bad.toml");
    std::fs::write(
        &cfg,
        "[pipeline]\nworkers = \"two\"\nqueue_capacity = 64\n[[pipeline.stages]]\ntype = \"denoise\"\ncutof_ghz = 0.2\n",
    )
    .unwrap();
    let out = dir.path().join("o");
    let o = fwlidar(&[
        "replay",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_fails(
        &o,
        2,
        &[
            "bad.toml:2:",
            "pipeline.workers",
            "bad.toml:6:",
            "pipeline.stages[0].cutof_ghz",
        ],
    );
    assert!(!out.exists());
    let o = fwlidar(&["validate", cfg.to_str().unwrap()]);
    assert_fails(
        &o,
        2,
        &["pipeline.workers", "cutof_ghz", "1 of 1 file(s) failed"],
    );
    let o = fwlidar(&["replay", "--config", dir.path().to_str().unwrap()]);
    assert_fails(&o, 2, &["directory"]);
}

#[test]
fn every_shipped_config_validates_through_the_cli() {
    let mut files = Vec::new();
    for sub in ["config", "config/sensors", "config/scenes"] {
        for e in std::fs::read_dir(Path::new(ROOT).join(sub)).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                files.push(p.to_str().unwrap().to_string());
            }
        }
    }
    assert!(files.len() >= 5, "{files:?}");
    let mut args = vec!["validate"];
    args.extend(files.iter().map(String::as_str));
    let o = fwlidar(&args);
    assert!(o.status.success(), "{}", text(&o.stderr));
}

#[test]
fn existing_files_are_never_written_over() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("keep.fwcap");
    std::fs::write(&cap, b"precious").unwrap();
    let o = fwlidar(&[
        "simulate",
        "--scene",
        scene().to_str().unwrap(),
        "--out",
        cap.to_str().unwrap(),
        "--no-progress",
    ]);
    assert_fails(&o, 1, &["keep.fwcap", "exists"]);
    assert_eq!(std::fs::read(&cap).unwrap(), b"precious");

    // An output folder that is a file is refused and left alone.
    let file = dir.path().join("out");
    std::fs::write(&file, b"not a folder").unwrap();
    let o = fwlidar(&["replay", "--out", file.to_str().unwrap(), "--no-progress"]);
    assert_fails(&o, 1, &["not a folder"]);
    assert_eq!(std::fs::read(&file).unwrap(), b"not a folder");
}

// ---- signals and crashes -------------------------------------------------------------------------

fn simulate_big(dir: &Path, pulses: u64) -> PathBuf {
    let cap = dir.join("big.fwcap");
    let o = fwlidar(&[
        "simulate",
        "--scene",
        scene().to_str().unwrap(),
        "--out",
        cap.to_str().unwrap(),
        "--pulses",
        &pulses.to_string(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    cap
}

#[test]
fn sigterm_and_sigint_stop_replay_cleanly_with_every_output_flushed() {
    let dir = tempfile::tempdir().unwrap();
    let cap = simulate_big(dir.path(), 200_000);
    for signal in ["-TERM", "-INT"] {
        stop_replay_with(&cap, &dir.path().join(signal), signal);
    }
}

fn stop_replay_with(cap: &Path, out: &Path, signal: &str) {
    let child = Command::new(BIN)
        .args([
            "replay",
            cap.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
        ])
        .args(CSV_OUTPUTS)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until processing is under way, then ask it to stop.
    let start = Instant::now();
    while !out.join("waveforms.csv.partial").exists() && start.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(200));
    let st = Command::new("kill")
        .args([signal, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success());
    let o = child.wait_with_output().unwrap();
    assert!(
        o.status.success(),
        "exit {:?}: {}",
        o.status,
        text(&o.stderr)
    );
    let summary = read_summary(out);
    assert_eq!(
        summary["stopped_early"], true,
        "replay finished before the signal"
    );
    let n_out = summary["pulses_out"].as_u64().unwrap();
    assert!(n_out > 0 && n_out < 200_000, "{n_out}");
    assert_eq!(
        summary["pulses_in"].as_u64().unwrap(),
        n_out,
        "in-flight pulses were processed"
    );
    // Every pulse that was counted is in the outputs, complete.
    let pulses = std::fs::read_to_string(out.join("pulses.csv")).unwrap();
    assert_eq!(pulses.lines().count() as u64, 1 + 2 * n_out);
    let waves = std::fs::read_to_string(out.join("waveforms.csv")).unwrap();
    assert_eq!(waves.lines().count() as u64, 2 * n_out);
    assert!(waves.ends_with('\n'));
    assert!(!out.join("waveforms.csv.partial").exists());
}

#[test]
fn kill_9_of_the_capture_writer_loses_at_most_the_unflushed_tail() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("killed.fwcap");
    let mut child = Command::new(BIN)
        .args([
            "simulate",
            "--scene",
            scene().to_str().unwrap(),
            "--out",
            cap.to_str().unwrap(),
            "--pulses",
            "50000000",
            "--no-progress",
        ])
        .current_dir(ROOT)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while std::fs::metadata(&cap).map_or(0, |m| m.len()) < 2_000_000
        && start.elapsed() < Duration::from_secs(30)
    {
        std::thread::sleep(Duration::from_millis(10));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();

    let mut r = CaptureReader::open(&cap).unwrap();
    let mut ids = Vec::new();
    let mut headers = 0;
    while let Some(rec) = r.next_record() {
        match rec.unwrap() {
            Record::Header(_) => headers += 1,
            Record::Frame(f) => ids.push(f.pulse_id()),
            Record::Nav { .. } => {}
        }
    }
    let s = *r.skipped();
    assert_eq!(headers, 1);
    assert!(ids.len() > 1000, "{} frames recovered", ids.len());
    // The recovered frames are exactly the first N written, with no hole.
    assert!(ids.iter().enumerate().all(|(i, id)| *id == i as u64));
    // The only damage is a partial record at the end, smaller than one record.
    assert_eq!(s.bytes_skipped, 0, "{s:?}");
    assert_eq!(s.bad_checksums, 0, "{s:?}");
    assert!(s.truncated_tail_bytes < 400, "{s:?}");
}

#[test]
fn replay_of_a_damaged_capture_recovers_every_intact_record_and_says_what_it_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = std::fs::read(sample()).unwrap();
    let len = bytes.len();
    bytes[len / 2] ^= 0x55; // one flipped byte in the middle: one record lost
    bytes.truncate(len - 100); // a cut-off tail: the last record lost
    bytes.splice(
        len / 4..len / 4,
        b"garbage from a bad disk block".iter().copied(),
    );
    let cap = dir.path().join("damaged.fwcap");
    std::fs::write(&cap, &bytes).unwrap();
    let out = dir.path().join("o");
    let o = fwlidar(&[
        "replay",
        cap.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let summary = read_summary(&out);
    let skipped = &summary["source"]["skipped"];
    let records = &summary["source"]["records"];
    // 2000 frames + 2 navigation records; three are damaged: the one the garbage landed in, the
    // one with the flipped byte, the cut-off last one. Every other record is recovered.
    let frames = records["frames"].as_u64().unwrap();
    let nav = records["nav_records"].as_u64().unwrap();
    assert_eq!(frames + nav, 2002 - 3, "{summary}");
    // Every recovered frame is either processed or counted by the georeference step (one of the
    // two navigation epochs is among the damaged records, so most pulses cannot be placed).
    let missed: u64 = summary["source"]["georeference"]["missed"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(
        summary["pulses_in"].as_u64().unwrap() + missed,
        frames,
        "{summary}"
    );
    assert_eq!(summary["pulses_out"], summary["pulses_in"]);
    assert_eq!(skipped["bad_checksums"], 2, "{skipped}");
    assert!(
        skipped["bytes_skipped"].as_u64().unwrap() >= 29,
        "{skipped}"
    );
    assert!(
        skipped["truncated_tail_bytes"].as_u64().unwrap() > 0,
        "{skipped}"
    );
    assert!(text(&o.stdout).contains("capture damage:"));
}

#[test]
fn validate_states_each_stage_worst_case_cost() {
    // Four deconvolve stages, one per method, and a decompose stage; the printed flops must be
    // the documented formulas (docs/configuration.md) for n = max_samples and m = the kernel.
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("cost.toml");
    std::fs::write(
        &cfg,
        r#"
[[pipeline.stages]]
type = "deconvolve"
method = { method = "richardson_lucy", iterations = 50 }
max_samples = 300
max_taps = 40

[[pipeline.stages]]
type = "deconvolve"
method = { method = "gold", iterations = 30, repetitions = 2, boost = 1.8 }
kernel = { taps = { taps = [1.0, 2.0, 1.0], center = 1 } }
max_samples = 300

[[pipeline.stages]]
type = "deconvolve"
method = { method = "nnls", max_iterations = 60 }
max_samples = 300
max_taps = 40

[[pipeline.stages]]
type = "deconvolve"
method = { method = "wiener" }
max_samples = 300
max_taps = 40

[[pipeline.stages]]
type = "decompose"
max_iterations = 25
"#,
    )
    .unwrap();
    let o = fwlidar(&["validate", cfg.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let out = text(&o.stdout);
    let (n, m) = (300u64, 40u64);
    let rl = 50 * (4 * n * m + 8 * n);
    let m3 = 3u64;
    let gold = 2 * n * m3 + 2 * (30 * (4 * n * m3 + 6 * n) + 2 * n * m3 + 6 * n);
    let k = 60u64;
    let plain = m * m + m + 2 * n * m + n + 60 * (2 * k * (2 * m - 1) + n + 11 * k * k + 18 * k);
    // A row with clipped samples takes the weighted path (Gram rows from the taps, dual from
    // the residual), so the stated worst case is the larger of the two.
    let outer_w = 2 * k * m + 2 * n * m + 5 * n + 3 * m * (k + 1) + 3 * k * k + 5 * k;
    let weighted = m * m + 2 * m + 2 * n * m + 4 * n + 60 * (outer_w + 8 * k * k + 13 * k);
    let nnls = plain.max(weighted);
    // Wiener: L = 360 = 2³·3²·5, the first even 2·3·5-smooth length >= n + m = 340.
    let l = 360f64;
    let wiener = (7.5 * l * l.log2() + 20.0 * (l / 2.0 + 1.0)) as u64;
    let grouped = |v: u64| {
        let d = v.to_string();
        d.chars()
            .enumerate()
            .flat_map(|(i, c)| {
                let sep = i > 0 && (d.len() - i).is_multiple_of(3);
                sep.then_some(' ').into_iter().chain([c])
            })
            .collect::<String>()
    };
    for (stage, method, flops) in [
        (0, "richardson_lucy, 50 iterations", rl),
        (1, "gold, 60 iterations", gold),
        (2, "nnls, 60 iterations", nnls),
        (3, "wiener, direct", wiener),
    ] {
        let line = out
            .lines()
            .find(|l| l.contains(&format!("stage {stage} deconvolve")))
            .unwrap_or_else(|| panic!("no line for stage {stage}:\n{out}"));
        assert!(line.contains(method), "{line}");
        assert!(
            line.contains(&format!("worst case {} flop", grouped(flops))),
            "stage {stage}: expected {flops} flop: {line}"
        );
        assert!(line.contains("<= 300 samples"), "{line}");
    }
    assert!(out.contains("kernel: calibrated, 3 taps"), "{out}");
    assert!(out.contains("outgoing pulse of <= 40 taps"), "{out}");
    assert!(
        out.contains("stage 4 decompose: at most 25 Levenberg-Marquardt steps"),
        "{out}"
    );
}

#[test]
fn import_of_a_capture_keeps_every_pulse_and_never_overwrites() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("copy.fwcap");
    let o = fwlidar(&[
        "import",
        sample().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(
        text(&o.stdout).contains("2000 pulses"),
        "{}",
        text(&o.stdout)
    );
    let a = fwlidar(&["inspect", sample().to_str().unwrap(), "--pulses", "--json"]);
    let b = fwlidar(&["inspect", out.to_str().unwrap(), "--pulses", "--json"]);
    assert!(a.status.success() && b.status.success());
    assert_eq!(text(&a.stdout).lines().count(), 2000);
    assert_eq!(a.stdout, b.stdout, "every pulse and sample carried over");
    let o = fwlidar(&["inspect", out.to_str().unwrap()]);
    assert!(text(&o.stdout).contains("origin: imported"));

    // A second import to the same name fails and leaves the first intact.
    let before = std::fs::read(&out).unwrap();
    let o = fwlidar(&[
        "import",
        sample().to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ]);
    assert_fails(&o, 1, &["copy.fwcap", "never overwritten"]);
    assert_eq!(std::fs::read(&out).unwrap(), before);

    // An input that is not a waveform file: a clear error, nothing written.
    let junk = dir.path().join("notes.txt");
    std::fs::write(&junk, b"not a waveform file at all\n").unwrap();
    let out2 = dir.path().join("x.fwcap");
    let o = fwlidar(&[
        "import",
        junk.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
    ]);
    assert_fails(&o, 1, &["notes.txt", "not an fwlidar capture"]);
    assert!(!out2.exists());
    assert!(!dir.path().join("x.fwcap.partial").exists());
}

/// The decompose stage's `pulses = "auto"`: replay with LAS on decomposes every pulse (the
/// same returns as `pulses = "all"`); replay of the on-board configuration, whose outputs
/// write no returns, passes every pulse on undecomposed (no QC viewer in replay).
#[test]
fn replay_with_las_on_decomposes_every_pulse() {
    let dir = tempfile::tempdir().unwrap();
    let onboard = Path::new(ROOT).join("config/onboard.toml");
    let input = sample();
    let run = |name: &str, sets: &[&str]| -> serde_json::Value {
        let out = dir.path().join(name);
        let mut args = vec![
            "replay",
            input.to_str().unwrap(),
            "--config",
            onboard.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
            "--workers",
            "2",
            "--set",
            "pipeline.input_edge=\"block\"",
        ];
        for s in sets {
            args.extend(["--set", s]);
        }
        let o = fwlidar(&args);
        assert!(o.status.success(), "{name}: {}", text(&o.stderr));
        read_summary(&out)
    };
    let auto = run("auto", &["output.las=true"]);
    let all = run(
        "all",
        &["output.las=true", "pipeline.stages[2].pulses=\"all\""],
    );
    let (a, b) = (&auto["sinks"]["las"], &all["sinks"]["las"]);
    assert!(a["points"].as_u64().unwrap() > 0, "{a:#}");
    assert_eq!(a["points"], b["points"]);
    assert_eq!(a["pulses_without_returns"], b["pulses_without_returns"]);
    assert_eq!(auto["pulses_out"], all["pulses_out"]);
    // On board's outputs (no LAS): no returns written, nothing decomposed.
    let board = run("board", &[]);
    assert!(board["sinks"]["las"].is_null(), "{:#}", board["sinks"]);
    assert_eq!(board["pulses_out"], all["pulses_out"]);
    let p50 = |s: &serde_json::Value, name: &str| {
        s["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["name"] == name)
            .and_then(|t| t["service"]["p50_ns"].as_f64())
            .unwrap()
    };
    assert!(
        p50(&board, "decompose") < 0.25 * p50(&all, "decompose"),
        "decompose p50 {} ns on board's outputs, {} ns for every pulse",
        p50(&board, "decompose"),
        p50(&all, "decompose")
    );
}
