//! Helpers shared by the integration tests: the real binary, and the real-data fixtures.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `fwlidar` binary built for these tests.
pub const BIN: &str = env!("CARGO_BIN_EXE_fwlidar");
/// The repository root.
pub const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The `replay` flags that ask for the text outputs (`pulses.csv` + `waveforms.csv`,
/// `returns.csv`) beside the default binary ones, for tests that read them.
pub const CSV_OUTPUTS: [&str; 4] = [
    "--set",
    "output.waveform_format=csv",
    "--set",
    "output.returns=true",
];

/// Runs `fwlidar` with `args` from the repository root.
pub fn fwlidar(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .current_dir(ROOT)
        .output()
        .expect("run fwlidar")
}

/// Bytes as text, lossily.
pub fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A real-data fixture file: `$FWLIDAR_FIXTURES/<rel>`, else `<root>/tests/data/<rel>` (the
/// repository carries every file its tests read; `tests/data/MANIFEST.md`). Panics naming the
/// missing file.
pub fn fixture(rel: &str) -> PathBuf {
    fwlidar::fixtures::path(rel)
}

/// The Python with the real readers of our outputs (numpy, laspy, lazrs): `$FWLIDAR_PYTHON`,
/// else `.venv/bin/python` (made by `.ci/run`). Panics saying how to get it.
pub fn python() -> PathBuf {
    if let Ok(p) = std::env::var("FWLIDAR_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = Path::new(ROOT).join(".venv/bin/python");
    assert!(
        venv.exists(),
        "this check needs Python with numpy, laspy and lazrs: set FWLIDAR_PYTHON or run .ci/run \
         (it creates .venv with them); {} is missing",
        venv.display()
    );
    venv
}
