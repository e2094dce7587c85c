//! `summary.json` stays what it was: replays of the README sample, a LAS, a PulseWaves and a GEDI
//! file give summaries byte for byte equal to the committed ones (`tests/golden/summary_*.json`,
//! made by the code before the reports were typed), apart from timings: every latency figure,
//! the wall time, the rate, the raster writer's I/O time and the pool's allocations (which depend
//! on thread scheduling) are set to 0, and the output folder is written `OUT`.
//!
//! The key order is part of what is compared: the summary is compared as text, line by line.
//! `FWLIDAR_UPDATE_GOLDEN=1` writes the golden files from this build instead (after a change of
//! what a report says, reviewed in the diff); `FWLIDAR_BIN` runs another binary.

mod common;

use std::path::{Path, PathBuf};

use common::{fixture, text};

/// Keys whose numbers are timings (or depend on thread scheduling).
const TIMING_KEYS: [&str; 10] = [
    "mean_ns",
    "p50_ns",
    "p99_ns",
    "p999_ns",
    "max_ns",
    "wall_time_s",
    "pulses_per_s",
    "io_s",
    "pool_allocations",
    "count_ns",
];

/// `summary.json` with its timings set to 0 and `out` written `OUT`.
fn normalised(summary: &str, out: &Path) -> String {
    let out = out.display().to_string();
    // Fixtures named from another folder (`FWLIDAR_FIXTURES`) read as the repository's.
    let fixtures = fwlidar::fixtures::dir().display().to_string();
    summary
        .lines()
        .map(|l| {
            let l = l.replace(&out, "OUT").replace(&fixtures, "tests/data");
            let trimmed = l.trim_start();
            let key = trimmed
                .strip_prefix('"')
                .and_then(|k| k.split_once("\": "))
                .map(|(k, _)| k);
            match key {
                Some(k) if TIMING_KEYS.contains(&k) => {
                    let indent = &l[..l.len() - trimmed.len()];
                    let comma = if l.ends_with(',') { "," } else { "" };
                    format!("{indent}\"{k}\": 0{comma}")
                }
                _ => l,
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

fn replay(name: &str, input: &Path) {
    let bin = std::env::var("FWLIDAR_BIN").unwrap_or_else(|_| common::BIN.to_string());
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join(name);
    // Inputs named relative to the repository, as the README's command does: the summary names
    // them as given.
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let input = input.strip_prefix(repo).unwrap_or(input);
    let o = std::process::Command::new(bin)
        .current_dir(repo)
        .args([
            "replay",
            input.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--workers", "2", "--no-progress"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{name}: {}", text(&o.stderr));
    let got = normalised(
        &std::fs::read_to_string(out.join("summary.json")).unwrap(),
        &out,
    );
    let golden = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(format!("summary_{name}.json"));
    if std::env::var_os("FWLIDAR_UPDATE_GOLDEN").is_some() {
        std::fs::create_dir_all(golden.parent().unwrap()).unwrap();
        std::fs::write(&golden, got + "\n").unwrap();
        return;
    }
    let want =
        std::fs::read_to_string(&golden).unwrap_or_else(|e| panic!("{}: {e}", golden.display()));
    for (i, (g, w)) in got.lines().zip(want.lines()).enumerate() {
        assert_eq!(g, w, "{name}: summary.json line {} differs", i + 1);
    }
    assert_eq!(
        got.lines().count(),
        want.lines().count(),
        "{name}: summary.json has another number of lines"
    );
}

#[test]
fn the_readme_samples_summary_is_unchanged() {
    replay(
        "readme",
        &PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("replay/two_layer.fwcap"),
    );
}

#[test]
fn a_las_replays_summary_is_unchanged() {
    replay(
        "las",
        &fixture("waveform/riegl_q680i/100429_152240_2535pt_UTM.las"),
    );
}

#[test]
fn a_pulsewaves_replays_summary_is_unchanged() {
    replay(
        "pulsewaves",
        &fixture("waveform/pulsewaves/lvis_example1.pls"),
    );
}

#[test]
fn a_gedi_replays_summary_is_unchanged() {
    replay(
        "gedi",
        &fixture("waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5"),
    );
}

#[test]
fn timings_are_normalised_and_nothing_else() {
    let s = "{\n  \"workers\": 2,\n  \"service\": {\n    \"count\": 5,\n    \"p50_ns\": 2585,\n    \"max_ns\": 9\n  },\n  \"store\": \"/x/out/voxels.zarr\",\n  \"wall_time_s\": 0.3\n}";
    assert_eq!(
        normalised(s, Path::new("/x/out")),
        "{\n  \"workers\": 2,\n  \"service\": {\n    \"count\": 5,\n    \"p50_ns\": 0,\n    \"max_ns\": 0\n  },\n  \"store\": \"OUT/voxels.zarr\",\n  \"wall_time_s\": 0\n}"
    );
}
