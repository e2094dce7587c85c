//! Where the real-instrument test files are: the tests, the benchmarks and the fuzz corpus
//! script read real files recorded by other people's instruments (`tests/data/MANIFEST.md`
//! gives each file's source, instrument and licence).
//!
//! The repository carries them in `tests/data/`, so a clone with nothing beside it passes its
//! tests; `FWLIDAR_FIXTURES` points at another folder of the same layout (e.g. a shared
//! fixtures folder holding more files than the repository does).

use std::path::PathBuf;

/// The environment variable naming another fixtures folder.
pub const ENV: &str = "FWLIDAR_FIXTURES";

/// The fixtures folder: `$FWLIDAR_FIXTURES` when set, else `<repository>/tests/data`.
pub fn dir() -> PathBuf {
    match std::env::var_os(ENV) {
        Some(p) => PathBuf::from(p),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data"),
    }
}

/// The fixture `rel` (a path relative to the fixtures folder, e.g.
/// `"nav/gpsd/rst39.log"`). Panics naming the file looked for when it is missing: the
/// repository carries every fixture its tests use, so a missing one is a broken checkout or a
/// `FWLIDAR_FIXTURES` pointing at the wrong folder.
pub fn path(rel: &str) -> PathBuf {
    let p = dir().join(rel);
    assert!(
        p.is_file(),
        "missing real-data fixture {} (the repository carries it in tests/data, see \
         tests/data/MANIFEST.md; {ENV} overrides the folder)",
        p.display()
    );
    p
}
