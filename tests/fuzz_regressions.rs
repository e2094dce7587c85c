//! Regressions found while fuzzing (see `fuzz/README.md`): each test feeds the input that broke
//! a parser or loader, which must return an error rather than panic, hang or exhaust memory.

use fwlidar::config::RunConfig;
use fwlidar::core::toml_load::load_str;
use fwlidar::sim::SceneFile;

/// Found while writing the `config_load` fuzz target (2026-11-22; spotted in the loader and
/// confirmed by feeding this text to the target, which libFuzzer stopped with out-of-memory):
/// a run configuration whose `sensor_profile` names a device that never ends. The loader read
/// the profile with `std::fs::read`, whose buffer grew until allocation failed.
#[cfg(unix)]
#[test]
fn run_config_sensor_profile_that_never_ends_is_an_error() {
    let err = load_str::<RunConfig>("sensor_profile = \"/dev/zero\"\n", "fuzz.toml")
        .expect_err("/dev/zero is not a sensor profile");
    let text = err.to_string();
    assert!(
        text.contains("sensor_profile") && text.contains("larger than"),
        "{text}"
    );
}

/// As above, through a simulator scene's `sensor_profile` (read by a second reader).
#[cfg(unix)]
#[test]
fn scene_sensor_profile_that_never_ends_is_an_error() {
    let err = load_str::<SceneFile>("[scene]\nsensor_profile = \"/dev/zero\"\n", "fuzz.toml")
        .expect_err("/dev/zero is not a sensor profile");
    let text = err.to_string();
    assert!(
        text.contains("sensor_profile") && text.contains("larger than"),
        "{text}"
    );
}

/// A regular file far larger than any configuration is refused without being read whole.
#[test]
fn oversized_profile_file_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let big = dir.path().join("big.toml");
    std::fs::write(&big, vec![b'#'; 4 << 20]).unwrap();
    let text = format!("sensor_profile = {:?}\n", big.display().to_string());
    let err = load_str::<RunConfig>(&text, dir.path().join("run.toml"))
        .expect_err("a 4 MiB profile is refused");
    assert!(err.to_string().contains("larger than"), "{err}");
}
