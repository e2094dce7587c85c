//! Every `.toml` file under `config/` must validate (whatever its kind).

use std::path::{Path, PathBuf};

use fwlidar::cli::validate::{Validated, validate_any};

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
        fwlidar::pipeline::edge::FullPolicy::DropNewest
    );
}

/// `[navigation]`: serial ports and the rollover date are checked with their field paths.
#[test]
fn navigation_serial_ports_and_earliest_date_are_checked() {
    use fwlidar::config::RunConfig;
    use fwlidar::core::toml_load::load_str;
    let good = "[navigation]\nearliest_date = \"2019-04-07\"\n\
                [[navigation.serial]]\ndevice = \"/dev/ttyUSB0\"\nbaud = 115200\nparity = \"none\"\n\
                [[navigation.serial]]\ndevice = \"/dev/ttyUSB1\"\nbaud = 9600\nport = 1\n";
    let c: RunConfig = load_str(good, "good.toml").unwrap();
    assert_eq!(c.navigation.serial.len(), 2);
    assert_eq!(c.navigation.serial[0].reconnect_ms, 500, "default");
    assert_eq!(
        c.navigation.earliest_days(),
        Some(fwlidar::nav::nmea::days_from_civil(2019, 4, 7))
    );
    let bad = "[navigation]\nearliest_date = \"2019-02-30\"\n\
               [[navigation.serial]]\ndevice = \"\"\nbaud = 10\n\
               [[navigation.serial]]\ndevice = \"/dev/ttyS0\"\nbaud = 9600\n";
    let e = load_str::<RunConfig>(bad, "bad.toml")
        .unwrap_err()
        .to_string();
    for needle in [
        "navigation.earliest_date",
        "navigation.serial[0].device",
        "navigation.serial[0].baud",
        "navigation.serial[1].port",
    ] {
        assert!(e.contains(needle), "`{needle}` in {e}");
    }
    let typo = "[[navigation.serial]]\ndevice = \"/dev/ttyS0\"\nbaud = 9600\nparity = \"mark\"\n";
    let e = load_str::<RunConfig>(typo, "typo.toml")
        .unwrap_err()
        .to_string();
    assert!(e.contains("parity"), "{e}");
}
