//! Helpers shared by the integration tests: the real binary, and the real-data fixtures.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `fwlidar` binary built for these tests.
pub const BIN: &str = env!("CARGO_BIN_EXE_fwlidar");
/// The repository root.
pub const ROOT: &str = env!("CARGO_MANIFEST_DIR");

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

/// A real-data fixture file: `$FWLIDAR_FIXTURES/<rel>`, else `<root>/../shared/fixtures/<rel>`.
/// Panics naming the missing file (CI has the folder; a fresh clone may not).
pub fn fixture(rel: &str) -> PathBuf {
    let base = std::env::var_os("FWLIDAR_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(ROOT).join("../shared/fixtures"));
    let p = base.join(rel);
    assert!(
        p.is_file(),
        "missing real-data fixture {} (set FWLIDAR_FIXTURES to the shared fixtures folder; see \
         its MANIFEST.md)",
        p.display()
    );
    p
}
