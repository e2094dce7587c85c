//! Real readers of our outputs: numpy, laspy and pyproj read what the README's `replay` wrote
//! (`tests/python/read_outputs.py`): `waveforms.npy` equal to the CSV form of the same run,
//! `returns.las` with its CRS where `returns.csv` puts the returns.
//!
//! The interpreter is `common::python()`: a missing one fails the test, naming `tests/run.sh`.

mod common;

use std::path::Path;
use std::process::Command;

use common::{BIN, ROOT};

#[test]
fn numpy_reads_replay_outputs() {
    let py = common::python_with(&["numpy", "laspy", "pyproj"]);
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
