//! Real readers of our outputs: numpy, laspy and pyproj read what the README's `replay` wrote
//! (`tests/python/read_outputs.py`): `waveforms.npy` equal to the CSV form of the same run,
//! `returns.las` with its CRS where `returns.csv` puts the returns.
//!
//! The interpreter is `$FWLIDAR_PYTHON`, else `.venv/bin/python` (made by `.ci/run` with numpy, laspy, pyproj).
//! Outside CI without either, the test says what is missing and passes; under CI (`CI` set) a
//! missing interpreter fails the test.

use std::path::{Path, PathBuf};
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_fwlidar");
const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn python() -> Option<PathBuf> {
    if let Ok(p) = std::env::var("FWLIDAR_PYTHON") {
        return Some(PathBuf::from(p));
    }
    let venv = Path::new(ROOT).join(".venv/bin/python");
    venv.exists().then_some(venv)
}

#[test]
fn numpy_reads_replay_outputs() {
    let Some(py) = python() else {
        let msg = "numpy reader check needs a Python with numpy: set FWLIDAR_PYTHON or run .ci/run \
                   (it creates .venv)";
        if std::env::var_os("CI").is_some() {
            panic!("{msg}");
        }
        eprintln!("SKIPPED: {msg}");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // The README's main job (the embedded configuration) ...
    let out = dir.path().join("out");
    let o = Command::new(BIN)
        .args(["replay", "--out", out.to_str().unwrap(), "--no-progress"])
        .current_dir(ROOT)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // ... and the same with the text outputs asked for.
    let embedded = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml")).unwrap();
    let text = embedded
        .replace("waveform_format = \"npy\"", "waveform_format = \"csv\"")
        .replace("\nreturns = false", "\nreturns = true");
    assert_ne!(text, embedded);
    let config = dir.path().join("csv.toml");
    std::fs::write(&config, text).unwrap();
    let csv = dir.path().join("csv");
    let o = Command::new(BIN)
        .args([
            "replay",
            "--out",
            csv.to_str().unwrap(),
            "--no-progress",
            "--config",
        ])
        .arg(&config)
        .current_dir(ROOT)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = Command::new(&py)
        .arg(Path::new(ROOT).join("tests/python/read_outputs.py"))
        .arg(&out)
        .arg(&csv)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", py.display()));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "numpy check failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    eprintln!("{stdout}");
    assert!(stdout.contains("4000 segments of 2000 pulses"), "{stdout}");
}
