//! The real-data files the tests read are the repository's own (`tests/data`): unchanged from
//! their sources (`SHA256SUMS`) and each described in `tests/data/MANIFEST.md` (source,
//! instrument, licence).

use std::path::Path;
use std::process::Command;

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data");

fn files(dir: &Path, out: &mut Vec<String>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            files(&p, out);
        } else {
            let rel = p.strip_prefix(DATA).unwrap().to_string_lossy().into_owned();
            out.push(rel);
        }
    }
}

#[test]
fn every_fixture_is_unchanged_and_described_in_the_manifest() {
    let sums = std::fs::read_to_string(Path::new(DATA).join("SHA256SUMS")).unwrap();
    let listed: Vec<&str> = sums
        .lines()
        .map(|l| {
            l.split_once("  ")
                .expect("sha256sum line")
                .1
                .trim_start_matches("./")
        })
        .collect();
    let mut present = Vec::new();
    files(Path::new(DATA), &mut present);
    present.retain(|f| f != "MANIFEST.md" && f != "SHA256SUMS");
    present.sort();
    let mut sorted = listed.clone();
    sorted.sort();
    assert_eq!(
        present, sorted,
        "tests/data and its SHA256SUMS list different files"
    );

    let out = Command::new("sha256sum")
        .args(["--check", "--quiet", "SHA256SUMS"])
        .current_dir(DATA)
        .output()
        .expect("run sha256sum");
    assert!(
        out.status.success(),
        "a fixture differs from its recorded checksum:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );

    let manifest = std::fs::read_to_string(Path::new(DATA).join("MANIFEST.md")).unwrap();
    for f in &listed {
        let path = Path::new(f);
        let name = path.file_name().unwrap().to_string_lossy();
        let stem = path.file_stem().unwrap().to_string_lossy();
        let folder = path.parent().unwrap().to_string_lossy();
        let described = manifest.contains(&*name)
            || manifest.contains(&format!("{folder}/{stem}"))
            || manifest.contains(&format!("`{folder}/*"));
        assert!(described, "{f} is not described in tests/data/MANIFEST.md");
    }
}

#[test]
fn the_tests_find_the_fixtures_inside_the_repository() {
    if std::env::var_os(fwlidar::fixtures::ENV).is_some() {
        return; // another folder was chosen on purpose
    }
    let dir = fwlidar::fixtures::dir();
    assert!(
        dir.starts_with(env!("CARGO_MANIFEST_DIR")),
        "{}",
        dir.display()
    );
    assert!(fwlidar::fixtures::path("nav/gpsd/rst39.log").is_file());
}
