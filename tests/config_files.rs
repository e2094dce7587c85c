//! Every `.toml` file under `config/` must validate (whatever its kind).

use std::path::{Path, PathBuf};

use fwlidar::config::{Validated, validate_any};

fn toml_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let entries = std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    for entry in entries {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            toml_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "toml") {
            out.push(path);
        }
    }
}

#[test]
fn every_config_file_validates() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
    let mut files = Vec::new();
    toml_files(&dir, &mut files);
    files.sort();
    assert!(
        files.len() >= 4,
        "expected at least 4 .toml files under {}, found {files:?}",
        dir.display()
    );
    let mut failures = Vec::new();
    for file in &files {
        if let Err(e) = validate_any(file) {
            failures.push(e.to_string());
        }
    }
    assert!(
        failures.is_empty(),
        "invalid config files:\n{}",
        failures.join("\n")
    );
}

#[test]
fn shipped_files_are_the_kinds_they_claim() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
    for name in ["replay.toml", "onboard.toml"] {
        let v = validate_any(dir.join(name)).unwrap_or_else(|e| panic!("{e}"));
        assert!(matches!(v, Validated::Run(_)), "{name}");
    }
    for name in ["optech_altm3100ea_cao.toml", "riegl_lms_q680i.toml"] {
        let v = validate_any(dir.join("sensors").join(name)).unwrap_or_else(|e| panic!("{e}"));
        let Validated::Sensor(s) = v else {
            panic!("{name} is not a sensor profile")
        };
        // The CAO footprint at 1000 m is 0.56 m (Wu et al.).
        if name.starts_with("optech") {
            assert!((s.sensor.footprint_m(1000.0) - 0.56).abs() < 1e-9);
        }
    }
    let Validated::Run(onboard) = validate_any(dir.join("onboard.toml")).unwrap() else {
        unreachable!()
    };
    assert_eq!(
        onboard.pipeline.input_edge,
        fwlidar::config::FullPolicy::DropNewest
    );
}
