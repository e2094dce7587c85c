//! The described-scene simulator end to end: `fwlidar simulate` writes a capture and its truth;
//! `fwlidar replay` of that capture (navigation decoded, trajectory, lever arm, boresight, scan
//! angles, georeference) puts every echo where the truth says the beam met the scene.

mod common;

use std::collections::HashMap;
use std::path::Path;

use common::{ROOT, fwlidar, text};
use fwlidar::geo::crs::OutputCrs;
use fwlidar::sim::world::flight::Frames;
use fwlidar::voxel::zarr::ZarrStore;

/// A bare sloped terrain scanned by an oscillating mirror, with a sensor mounted with a lever
/// arm and a boresight misalignment, in the given navigation format.
fn bare_scene(dir: &Path, nav_format: &str) -> std::path::PathBuf {
    let scene = format!(
        r#"
seed = 4
effects = ["off_nadir"]
[origin]
lat_deg = -24.99
lon_deg = 31.59
height_m = 120.0
[terrain]
kind = "plane"
slope_deg = 8.0
aspect_deg = 300.0
[flight]
altitude_m = 900.0
speed_mps = 65.0
pulse_rate_hz = 20000.0
lines = [{{ start_m = [-30.0, -20.0], end_m = [30.0, 10.0] }}]
max_pulses = 4000
scan = {{ pattern = "oscillating", half_angle_deg = 18.0, rate_hz = 25.0 }}
[sensor]
outgoing_fwhm_ns = 4.0
window_top_m = 20.0
return_samples = 200
[sensor.inline]
name = "test sensor with a lever arm and a boresight"
wavelength_nm = 1064.0
pulse_fwhm_ns = 4.0
pulse_rate_hz = 20000.0
beam_divergence_mrad = 0.3
sample_interval_ns = 1.0
bits_per_sample = 16
digitizer_gain_v_per_dn = 0.001
digitizer_offset_v = 0.0
lever_arm_m = [0.4, -0.3, 1.2]
boresight_deg = [0.2, -0.15, 0.3]
calibration_constant = 1.0
[navigation]
rate_hz = 100.0
formats = ["{nav_format}"]
"#
    );
    let path = dir.join("bare.toml");
    std::fs::write(&path, scene).unwrap();
    path
}

/// `fwlidar simulate --scene SCENE --out OUT --no-progress` with `extra` arguments.
fn simulate(scene: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "simulate",
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ];
    args.extend_from_slice(extra);
    fwlidar(&args)
}

/// Ground truth per pulse: the terrain point of its (single, axis) ray, scene frame.
fn truth_points(csv: &Path) -> HashMap<u64, [f64; 3]> {
    let body = std::fs::read_to_string(csv).unwrap();
    let mut out = HashMap::new();
    for line in body.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        if f[2] == "terrain" {
            let p = [f[6], f[7], f[8]].map(|v| v.parse::<f64>().unwrap());
            out.insert(f[0].parse().unwrap(), p);
        }
    }
    out
}

/// Per pulse, the amplitude-weighted mean position of its fitted returns (deconvolution can
/// split one echo into two close components; their weighted mean is the echo's position).
fn returns(out: &Path) -> Vec<(u64, [f64; 3])> {
    let body = std::fs::read_to_string(out.join("returns.csv")).unwrap();
    let mut lines = body.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let (id, a, x, y, z) = (
        col("pulse_id"),
        col("amplitude_v"),
        col("x"),
        col("y"),
        col("z"),
    );
    let mut sums: std::collections::BTreeMap<u64, [f64; 4]> = Default::default();
    for l in lines {
        let f: Vec<&str> = l.split(',').collect();
        let v = |i: usize| f[i].parse::<f64>().unwrap();
        let s = sums.entry(f[id].parse().unwrap()).or_default();
        let w = v(a);
        s[0] += w;
        s[1] += w * v(x);
        s[2] += w * v(y);
        s[3] += w * v(z);
    }
    sums.into_iter()
        .map(|(k, s)| (k, [s[1] / s[0], s[2] / s[0], s[3] / s[0]]))
        .collect()
}

#[test]
fn a_simulated_scan_georeferences_onto_its_truth() {
    for nav in ["novatel", "nmea"] {
        let dir = tempfile::tempdir().unwrap();
        let scene = bare_scene(dir.path(), nav);
        let cap = dir.path().join("bare.fwcap");
        let o = simulate(&scene, &cap, &["--no-truth-voxels"]);
        assert!(o.status.success(), "{}", text(&o.stderr));
        let out = dir.path().join("out");
        let o = fwlidar(&[
            "replay",
            cap.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
            "--set",
            "output.returns=true",
        ]);
        assert!(o.status.success(), "{}", text(&o.stderr));
        let truth = truth_points(&dir.path().join("bare.scatterers.csv"));
        assert_eq!(truth.len(), 4000);
        let frames = Frames::new(-24.99, 31.59, 120.0);
        let crs = OutputCrs::from_epsg(32736).unwrap();
        let rets = returns(&out);
        assert!(rets.len() >= 3990, "{nav}: {} returns", rets.len());
        let (mut worst_h, mut worst_v) = (0.0f64, 0.0f64);
        let mut scan_min = f64::INFINITY;
        for (id, p) in &rets {
            let t = truth[id];
            let g = frames.geodetic(t);
            let want = crs.project(g.lat_deg, g.lon_deg, g.height_m).unwrap();
            let dh = ((p[0] - want[0]).powi(2) + (p[1] - want[1]).powi(2)).sqrt();
            worst_h = worst_h.max(dh);
            if std::env::var("DEBUG_SIM").is_ok() && (p[2] - want[2]).abs() > 0.01 {
                eprintln!(
                    "{id} {:?} {:.3} {:.3} {:.3}",
                    t,
                    p[0] - want[0],
                    p[1] - want[1],
                    p[2] - want[2]
                );
            }
            worst_v = worst_v.max((p[2] - want[2]).abs());
            scan_min = scan_min.min(t[0] - (-30.0));
        }
        // Measured: 1-2 mm horizontally, 4-5 mm vertically with either format (NMEA's 0.01°
        // attitude is exact because the simulator flies level on a 0.01° heading; its
        // positions carry 2 mm). The residue is the echo fit on 1 ns samples.
        let tol = 0.01;
        assert!(
            worst_h < tol && worst_v < tol,
            "{nav}: worst horizontal {worst_h:.4} m, vertical {worst_v:.4} m"
        );
        eprintln!("{nav}: worst horizontal {worst_h:.4} m, vertical {worst_v:.4} m");
    }
}

#[test]
fn a_described_scene_writes_its_truth_and_truth_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("plot.fwcap");
    let scene = Path::new(ROOT).join("config/scenes/tree_plot.toml");
    let o = simulate(&scene, &cap, &["--set", "flight.grid.rows=10"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    for f in [
        "plot.fwcap",
        "plot.truth.fwcap",
        "plot.scatterers.csv",
        "plot.truth.json",
        "plot.truth/voxels.zarr/zarr.json",
        "plot.truth/truth_voxels.toml",
    ] {
        assert!(dir.path().join(f).exists(), "{f} missing");
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("plot.truth.json")).unwrap())
            .unwrap();
    assert_eq!(summary["pulses_recorded"], 400);
    // The truth voxels: every pulse deposited; leaves up to the tallest tree in the rows
    // flown (the first 10 rows: y from -9.75 to -5.25 m, trees 1, 2 and 5 reach into them).
    let mut store = ZarrStore::open(&dir.path().join("plot.truth/voxels.zarr")).unwrap();
    let tiles = store.read_all().unwrap();
    let total: i64 = tiles
        .iter()
        .flat_map(|(_, d)| d.present().into_iter().map(move |k| (d, k)))
        .filter_map(|(d, k)| d.chunk(k as usize))
        .flat_map(|c| {
            c.touched_columns()
                .filter_map(|col| c.column(col))
                .flat_map(|v| v.sum_q.iter())
        })
        .sum();
    assert!(total > 0);
    // A real client reads it: the ground at 0 m, the crowns' tops up to the tallest tree in
    // these rows (trees 1, 2 and 5: 14, 11 and 12 m; the footprint and the 2 ns pulse add a
    // little above).
    let o = std::process::Command::new(common::python())
        .arg(Path::new(ROOT).join("tests/python/check_truth_voxels.py"))
        .arg(dir.path().join("plot.truth/voxels.zarr"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    eprintln!("truth voxels: {v}");
    let (ground, top) = (
        v["ground_m"].as_f64().unwrap(),
        v["top_m"].as_f64().unwrap(),
    );
    assert!(ground.abs() <= 0.3, "ground level {ground} m");
    assert!((13.0..=15.5).contains(&top), "canopy top {top} m");
    // Rerunning into the same files is refused, nothing is overwritten.
    let before = std::fs::read(&cap).unwrap();
    let o = simulate(&scene, &cap, &[]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o.stderr));
    assert!(text(&o.stderr).contains("never overwritten"));
    assert_eq!(std::fs::read(&cap).unwrap(), before);
    // The same scene and seed give the same bytes.
    let again = dir.path().join("again.fwcap");
    let o = simulate(
        &scene,
        &again,
        &["--no-truth-voxels", "--set", "flight.grid.rows=10"],
    );
    assert!(o.status.success());
    assert_eq!(std::fs::read(&again).unwrap(), before);
    // A bad override names the key.
    let o = simulate(
        &scene,
        &dir.path().join("x.fwcap"),
        &["--set", "flight.scan.zenith_deg=75"],
    );
    assert_eq!(o.status.code(), Some(2));
    assert!(
        text(&o.stderr).contains("zenith_deg"),
        "{}",
        text(&o.stderr)
    );
    assert!(!dir.path().join("x.fwcap").exists());
}

#[test]
fn the_described_replay_samples_are_reproducible() {
    let dir = tempfile::tempdir().unwrap();
    for (name, extra) in [
        ("tree_plot", vec![]),
        ("grass_patches", vec![]),
        ("survey_line", vec!["--pulses", "6000"]),
    ] {
        let out = dir.path().join(format!("{name}.fwcap"));
        let scene = Path::new(ROOT).join(format!("config/scenes/{name}.toml"));
        let mut args = vec!["--no-truth-voxels"];
        args.extend(extra);
        let o = simulate(&scene, &out, &args);
        assert!(o.status.success(), "{}", text(&o.stderr));
        for suffix in ["fwcap", "truth.fwcap"] {
            let committed = Path::new(ROOT).join(format!("replay/{name}.{suffix}"));
            let fresh = dir.path().join(format!("{name}.{suffix}"));
            assert!(
                std::fs::read(&fresh).unwrap() == std::fs::read(&committed).unwrap(),
                "{} differs from a fresh simulation: regenerate it (bash replay/regenerate.sh)",
                committed.display()
            );
            assert!(std::fs::metadata(&committed).unwrap().len() < 5_000_000);
        }
    }
}

#[test]
fn tradeoff_scores_a_scene_step_by_step() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Path::new(ROOT).join("config/scenes/tree_plot.toml");
    let o = fwlidar(&[
        "tradeoff",
        "--scene",
        scene.to_str().unwrap(),
        "--pulses",
        "400",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let csv = std::fs::read_to_string(dir.path().join("scene_steps.csv")).unwrap();
    let rows: HashMap<String, Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[0].to_string(),
                f[1..].iter().map(|v| v.parse::<f64>().unwrap()).collect(),
            )
        })
        .collect();
    for step in [
        "raw",
        "denoise",
        "rl iterations=20",
        "gold iterations=20",
        "wiener",
        "nnls max_iterations=100",
        "nnls_or_rl threshold=0.5",
        "georeference",
        "voxelise (rl 20 through 2 ns; georeferenced)",
    ] {
        let r = &rows[step];
        assert!(r[0] >= 395.0, "{step} scored");
        // scored, rmse, rmse_2ns, detection, false, sam, median time.
        assert!(r[..7].iter().all(|v| v.is_finite()), "{step}: {r:?}");
        assert!(r[6] > 0.0, "{step} timed");
    }
    // The georeference through the navigation stream puts the echoes within a millimetre.
    let g = &rows["georeference"];
    assert!(g[9] < 1e-3 && g[9] > 0.0, "position error RMS {} m", g[9]);
    // Columns: scored, rmse, rmse_2ns, detection, false, sam, median, p99.
    let (raw, rl, den) = (&rows["raw"], &rows["rl iterations=20"], &rows["denoise"]);
    assert!(
        rl[1] < raw[1],
        "deconvolution lowers the RMSE: {} vs {}",
        rl[1],
        raw[1]
    );
    assert!(rl[4] < raw[4] - 1.0, "fewer false peaks than raw");
    assert!(rl[5] < raw[5], "a smaller spectral angle");
    assert!(den[3] < raw[3], "denoise removes the noise peaks");
    assert!(
        std::fs::read_to_string(dir.path().join("scene_steps.md"))
            .unwrap()
            .contains("| rl iterations=20 |")
    );
    // Scratch voxels are gone.
    assert!(std::fs::read_dir(dir.path()).unwrap().all(|e| {
        !e.unwrap()
            .file_name()
            .to_string_lossy()
            .starts_with(".scene")
    }));
}

#[test]
fn the_experiment_matrix_runs_every_combination() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Path::new(ROOT).join("config/scenes/tree_plot.toml");
    let o = fwlidar(&[
        "tradeoff",
        "--scene",
        scene.to_str().unwrap(),
        "--matrix",
        "--widths-ns",
        "4,16",
        "--zeniths-deg",
        "0,20",
        "--azimuths-deg",
        "0,90",
        "--pulses",
        "200",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let csv = std::fs::read_to_string(dir.path().join("scene_matrix.csv")).unwrap();
    // 2 widths × (nadir once + 20° at two azimuths) × 10 steps.
    assert_eq!(csv.lines().count(), 1 + 2 * 3 * 10, "{csv}");
    let rl_sam = |w: &str, z: &str, a: &str| -> f64 {
        csv.lines()
            .find(|l| l.starts_with(&format!("{w},{z},{a},rl ")))
            .map(|l| l.split(',').nth(9).unwrap().parse().unwrap())
            .unwrap()
    };
    // Deconvolution does better on the short pulse than on the long one.
    assert!(rl_sam("4", "0", "0") < rl_sam("16", "0", "0"));
    assert!(
        std::fs::read_to_string(dir.path().join("scene_matrix.md"))
            .unwrap()
            .contains("| 16 | 20 | 90 |")
    );
}

/// `fwlidar simulate` writes the trees and their first-order branches it traces
/// (`<stem>.trees.csv`, `<stem>.branches.csv`): every branch echo of the tree plot lies on one
/// of its tree's listed branch cylinders, and the counts are the scene's (`branch_count`).
#[test]
fn the_branch_truth_is_what_the_simulator_traces() {
    let dir = tempfile::tempdir().unwrap();
    let cap = dir.path().join("plot.fwcap");
    let o = fwlidar(&[
        "simulate",
        "--scene",
        "config/scenes/tree_plot.toml",
        "--no-truth-voxels",
        "--out",
        cap.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let rows = |name: &str| -> Vec<HashMap<String, String>> {
        let t = std::fs::read_to_string(dir.path().join(name)).unwrap();
        let mut lines = t.lines();
        let head: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
        lines
            .map(|l| {
                head.iter()
                    .cloned()
                    .zip(l.split(',').map(String::from))
                    .collect()
            })
            .collect()
    };
    let f = |r: &HashMap<String, String>, k: &str| -> f64 { r[k].parse().unwrap() };
    let trees = rows("plot.trees.csv");
    let branches = rows("plot.branches.csv");
    // tree_plot's branch_count per tree: 6, 5, 8, 5, 6, 10.
    let mut per_tree = [0usize; 6];
    for b in &branches {
        per_tree[f(b, "tree_id") as usize] += 1;
    }
    assert_eq!(per_tree, [6, 5, 8, 5, 6, 10]);
    // Each branch in the scene frame: tree, base on the stem, unit axis, length, radius.
    type Axis = (usize, [f64; 3], [f64; 3], f64, f64);
    let axes: Vec<Axis> = branches
        .iter()
        .map(|b| {
            let t = &trees[f(b, "tree_id") as usize];
            let (z, a) = (
                f(b, "zenith_deg").to_radians(),
                f(b, "azimuth_deg").to_radians(),
            );
            (
                f(b, "tree_id") as usize,
                [f(t, "scene_x"), f(t, "scene_y"), f(b, "base_height_m")],
                [z.sin() * a.sin(), z.sin() * a.cos(), z.cos()],
                f(b, "length_m"),
                f(b, "radius_m"),
            )
        })
        .collect();
    let mut hits = 0;
    for s in rows("plot.scatterers.csv") {
        if s["kind"] != "branch" {
            continue;
        }
        hits += 1;
        let tree: usize = s["object"].parse().unwrap();
        let p = [f(&s, "east_m"), f(&s, "north_m"), f(&s, "up_m")];
        let nearest = axes
            .iter()
            .filter(|a| a.0 == tree)
            .map(|(_, b, d, len, r)| {
                let v = [p[0] - b[0], p[1] - b[1], p[2] - b[2]];
                let along = (v[0] * d[0] + v[1] * d[1] + v[2] * d[2]).clamp(0.0, *len);
                let q = [
                    b[0] + along * d[0],
                    b[1] + along * d[1],
                    b[2] + along * d[2],
                ];
                ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt() - r
            })
            .fold(f64::INFINITY, f64::min);
        assert!(
            nearest < 0.01,
            "branch echo {p:?} of tree {tree} is {nearest} m off its branches"
        );
    }
    assert!(hits > 100, "{hits} branch echoes");
}
