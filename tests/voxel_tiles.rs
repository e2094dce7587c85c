//! Voxel tiles end to end: replay writes `voxels.zarr`, read by zarr-python and xarray (real
//! clients) with values checked, opened as the README says with no warning and arrays fitted
//! to the tiles written; kill -9 and a rerun give the uninterrupted run's store, bit for bit;
//! `fwlidar merge` adds stores exactly; bad outputs are refused clearly.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{BIN, ROOT, fwlidar, python, text};
use fwlidar::voxel::tile::{Dense, TileData};
use fwlidar::voxel::zarr::ZarrStore;

fn replay(input: &Path, out: &Path, config: Option<&Path>) -> std::process::Output {
    let mut args = vec![
        "replay".to_string(),
        input.display().to_string(),
        "--out".into(),
        out.display().to_string(),
        "--no-progress".into(),
    ];
    args.extend(common::CSV_OUTPUTS.map(String::from));
    if let Some(c) = config {
        args.push("--config".into());
        args.push(c.display().to_string());
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    fwlidar(&args)
}

fn sample() -> PathBuf {
    Path::new(ROOT).join("replay/two_layer.fwcap")
}

/// The embedded configuration without its calibrate stage: voxels hold volts.
fn volts_config(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml")).unwrap();
    let start = text
        .find("[[pipeline.stages]]\ntype = \"calibrate\"")
        .unwrap();
    let end = start + text[start..].find("\n[georeference]").unwrap();
    let p = dir.join("volts.toml");
    let mut text = format!("{}{}", &text[..start], &text[end..]);
    // The last `las = false` is [voxels]'s ([output]'s returns.las is on by default).
    let at = text.rfind("\nlas = false").unwrap();
    text.replace_range(at..at + "\nlas = false".len(), "\nlas = true");
    assert!(text.contains("[output]") && text.matches("\nlas = true").count() == 2);
    std::fs::write(&p, text).unwrap();
    p
}

/// `tests/python/check_fitted_store.py` on a finished store: opened by `xr.open_zarr(store)`
/// with warnings as errors, arrays spanning exactly the recorded tiles; its figures.
fn check_fitted(store: &Path) -> serde_json::Value {
    let o = Command::new(python())
        .arg(Path::new(ROOT).join("tests/python/check_fitted_store.py"))
        .arg(store)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "fitted-store check of {} failed:\n{}\n{}",
        store.display(),
        text(&o.stdout),
        text(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

fn summary_of(out: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap()
}

/// The README's main job, then exactly what a user types: `xr.open_zarr(store)` with no
/// argument and `.sample_count.sum()`. It must open without a warning (consolidated metadata),
/// hold arrays no larger than the tiles written, and sum to the bins the summary reports.
#[test]
fn the_readme_replay_opens_in_xarray_and_sums_without_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    // `cargo run --release -- replay replay/two_layer.fwcap --out out`, from the repository.
    let o = fwlidar(&[
        "replay",
        "replay/two_layer.fwcap",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let store = out.join("voxels.zarr");
    let o = Command::new(python())
        .args(["-W", "error", "-c"])
        .arg(
            "import sys, json\n\
             import xarray as xr\n\
             ds = xr.open_zarr(sys.argv[1])\n\
             total = ds.sample_count.sum()\n\
             print(json.dumps({'sum': int(total), 'shape': list(ds.sample_count.shape),\n\
                               'x': [float(v) for v in ds.x.values],\n\
                               'y': [float(v) for v in ds.y.values]}))\n",
        )
        .arg(&store)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert_eq!(text(&o.stderr), "", "python wrote to stderr (a warning?)");
    let got: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let summary = summary_of(&out);
    let vox = &summary["sinks"]["voxels"];
    let deposited = vox["deposits"]["bins_deposited"].as_u64().unwrap();
    assert!(deposited > 0);
    assert_eq!(got["sum"].as_u64(), Some(deposited), "{got}");
    // The tiles written: the store's records, on the grid anchored at the CRS origin.
    let records: Vec<[i64; 2]> = common::committed_tiles(&store).into_keys().collect();
    assert_eq!(
        records.len() as u64,
        vox["tiles"]["in_store"].as_u64().unwrap()
    );
    let low = |a: usize| records.iter().map(|t| t[a]).min().unwrap();
    let hi = |a: usize| records.iter().map(|t| t[a]).max().unwrap();
    assert!(
        (hi(0) - low(0) + 1) * (hi(1) - low(1) + 1) <= 4,
        "a small store: {records:?}"
    );
    // The arrays start at the corner of the group of tiles (the default: 16 × 16 tiles a shard
    // file, counted from the grid's first tile) that holds the south-west tile.
    let opened = ZarrStore::open(&store).unwrap();
    let group = opened.layout_choice().group.map_or(1, |g| g.tiles as i64);
    assert_eq!(group, 16, "the default layout groups tiles");
    let first = opened.grid().tile_min;
    let lo = |a: usize| low(a) - (low(a) - first[a]).rem_euclid(group);
    let (nx, ny) = ((hi(0) - lo(0) + 1) as u64, (hi(1) - lo(1) + 1) as u64);
    // The fitted height: from the lowest to the highest height chunk written.
    let levels = vox["arrays"]["shape"][0].as_u64().unwrap();
    assert!(levels > 0 && levels.is_multiple_of(64), "{vox}");
    assert_eq!(
        got["shape"],
        serde_json::json!([levels, ny * 32, nx * 32]),
        "{got}"
    );
    // Coordinates: the voxel centres of those tiles (16 m tiles of 0.5 m voxels).
    let xs: Vec<f64> = serde_json::from_value(got["x"].clone()).unwrap();
    let ys: Vec<f64> = serde_json::from_value(got["y"].clone()).unwrap();
    for (i, x) in xs.iter().enumerate() {
        assert_eq!(*x, lo(0) as f64 * 16.0 + 0.25 + i as f64 * 0.5);
    }
    for (j, y) in ys.iter().enumerate() {
        assert_eq!(*y, lo(1) as f64 * 16.0 + 0.25 + j as f64 * 0.5);
    }
    assert_eq!(vox["arrays"]["tile_min"], serde_json::json!([lo(0), lo(1)]));
    assert_eq!(vox["arrays"]["fitted"], true);
    // The whole check: every recorded tile where the arrays say, nothing elsewhere.
    let fitted = check_fitted(&store);
    assert_eq!(fitted["samples"].as_u64(), Some(deposited));
}

/// A run that deposits nothing (the configured extent lies elsewhere) leaves a store with
/// empty arrays that xarray opens, without a warning, and sums to 0.
#[test]
fn a_run_that_deposits_nothing_leaves_empty_arrays_xarray_opens() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("elsewhere.toml");
    let text_cfg = std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml")).unwrap();
    assert!(text_cfg.contains("\n[voxels]\n"));
    std::fs::write(
        &cfg,
        text_cfg.replace(
            "\n[voxels]\n",
            "\n[voxels]\nextent_m = [0.0, 0.0, 16.0, 16.0]\n",
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let o = replay(&sample(), &out, Some(&cfg));
    assert!(o.status.success(), "{}", text(&o.stderr));
    let vox = &summary_of(&out)["sinks"]["voxels"];
    assert_eq!(vox["deposits"]["bins_deposited"], 0);
    assert!(vox["deposits"]["bins_outside_extent"].as_u64().unwrap() > 0);
    let fitted = check_fitted(&out.join("voxels.zarr"));
    assert_eq!(fitted["samples"], 0);
    assert_eq!(fitted["shape"], serde_json::json!([0, 0, 0]));
}

fn check_with_xarray(out: &Path, mode: &str) -> serde_json::Value {
    let o = Command::new(python())
        .arg(Path::new(ROOT).join("tests/python/check_voxels.py"))
        .arg(out)
        .arg(mode)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "xarray/zarr check failed:\n{}\n{}",
        text(&o.stdout),
        text(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn replay_writes_tiles_that_xarray_reads_with_the_right_values() {
    let dir = tempfile::tempdir().unwrap();
    // The embedded default: calibrated backscatter.
    let out = dir.path().join("out");
    let o = replay(&sample(), &out, None);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let stdout = text(&o.stdout);
    let line = common::summary_output(&stdout, "voxels.zarr").unwrap_or_default();
    assert!(
        line.starts_with("450000 bins of 2000 pulses in 1 tile; ") && line.ends_with(" on disk"),
        "{stdout}"
    );
    let figures = check_with_xarray(&out, "calibrated");
    assert_eq!(figures["bins"], 450000);
    // Without the calibrate stage: volts, summed exactly as waveforms.csv has them.
    let volts = dir.path().join("volts");
    let o = replay(&sample(), &volts, Some(&volts_config(dir.path())));
    assert!(o.status.success(), "{}", text(&o.stderr));
    let figures = check_with_xarray(&volts, "volts");
    assert_eq!(figures["bins"], 450000);
    // The tile as a LAS point cloud (laspy): one point per occupied voxel, the same totals.
    let las: Vec<PathBuf> = std::fs::read_dir(volts.join("voxels_las"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(las.len(), 1, "{las:?}");
    let o = Command::new(python())
        .arg("-c")
        .arg(
            "import sys, json, laspy, numpy as np, xarray as xr\n\
             las = laspy.read(sys.argv[1])\n\
             assert las.header.point_format.id == 6\n\
             names = list(las.point_format.extra_dimension_names)\n\
             assert names == ['mean', 'maximum', 'samples', 'pulses'], names\n\
             n = np.asarray(las.samples, dtype=np.float64)\n\
             s = float((np.asarray(las.mean, dtype=np.float64) * n).sum())\n\
             w = [v.string for v in las.header.vlrs if hasattr(v, 'string')]\n\
             assert w and 'UTM zone 36S' in w[0], w\n\
             print(json.dumps({'points': len(las.points), 'samples': int(n.sum()), 'sum': s}))\n",
        )
        .arg(&las[0])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["samples"], 450000, "{v}");
    let sum = v["sum"].as_f64().unwrap();
    let want = figures["sum_v"].as_f64().unwrap();
    assert!((sum - want).abs() < 1e-4 * want.abs(), "{sum} vs {want}");
    assert!(v["points"].as_u64().unwrap() > 200, "{v}");
}

/// A run configuration: denoise + Richardson-Lucy (slow enough to be killed mid-run), small
/// tiles that close soon after the flight leaves them.
fn crash_config(dir: &Path) -> PathBuf {
    crash_config_with(dir, "")
}

/// `crash_config` with `voxels` lines added (e.g. the store's layout).
fn crash_config_with(dir: &Path, voxels: &str) -> PathBuf {
    let p = dir.join("crash.toml");
    std::fs::write(
        &p,
        r#"
[pipeline]
workers = 1
[[pipeline.stages]]
type = "denoise"
[[pipeline.stages]]
type = "deconvolve"
method = { method = "richardson_lucy", iterations = 40 }
kernel = "outgoing"
max_samples = 1024
[georeference]
enabled = true
[output]
waveforms = false
returns = false
[voxels]
enabled = true
z_range_m = [-5.0, 30.0]
tile_columns = 4
close_after_s = 0.02
max_open_tiles = 8
"#
        .to_string()
            + voxels,
    )
    .unwrap();
    p
}

fn simulate(dir: &Path, pulses: u64, seed: u64, name: &str) -> PathBuf {
    let cap = dir.join(name);
    let o = fwlidar(&[
        "simulate",
        "--scene",
        "config/scenes/two_layer.toml",
        "--pulses",
        &pulses.to_string(),
        "--seed",
        &seed.to_string(),
        "--out",
        cap.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    cap
}

/// Every file of a store below its data arrays, with its bytes.
fn store_files(root: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(base: &Path, dir: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                let rel = p.strip_prefix(base).unwrap().display().to_string();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(root, root, &mut m);
    m
}

#[test]
fn kill_9_during_a_replay_then_rerun_equals_an_uninterrupted_run() {
    // A file per tile, committed tile by tile.
    kill_9_then_rerun("shard_tiles = 0\n", 20);
}

#[test]
fn kill_9_during_a_replay_of_grouped_tiles_then_rerun_equals_an_uninterrupted_run() {
    // Tiles grouped into shard files of 2 × 2 tiles (so that groups are written while the run
    // goes on), committed by journal lines.
    kill_9_then_rerun("shard_tiles = 2\nshard_height_chunks = 1\n", 3);
}

/// Replays a line whole, then again killed (SIGKILL) once four tiles are committed, then
/// reruns the killed one: the store must be the whole run's, byte for byte.
fn kill_9_then_rerun(layout: &str, min_files: usize) {
    let dir = tempfile::tempdir().unwrap();
    let cap = simulate(dir.path(), 20_000, 7, "line.fwcap");
    let cfg = crash_config_with(dir.path(), layout);
    let whole = dir.path().join("whole");
    let o = replay(&cap, &whole, Some(&cfg));
    assert!(o.status.success(), "{}", text(&o.stderr));

    let cut = dir.path().join("cut");
    let mut child = Command::new(BIN)
        .args([
            "replay",
            cap.to_str().unwrap(),
            "--out",
            cut.to_str().unwrap(),
        ])
        .args(["--config", cfg.to_str().unwrap(), "--no-progress"])
        .args(common::CSV_OUTPUTS)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let committed = || common::committed_tiles(&cut.join("voxels.zarr")).len();
    // Four tiles committed: at most one batch of them can be in the middle of its commit.
    while committed() < 4 {
        assert!(t0.elapsed() < Duration::from_secs(60), "no tile closed");
        if child.try_wait().unwrap().is_some() {
            panic!("the replay finished before it could be killed: make the input longer");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    assert!(
        !cut.join("summary.json").exists(),
        "the run was killed before its end"
    );

    // Every tile closed before the kill is valid for a real reader.
    let o = Command::new(python())
        .arg(Path::new(ROOT).join("tests/python/check_killed_store.py"))
        .arg(cut.join("voxels.zarr"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}{}", text(&o.stdout), text(&o.stderr));
    let read: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(read["tiles"].as_u64().unwrap() >= 3, "{read}");

    // The rerun resumes and ends with the same files, byte for byte: chunks (at the keys of
    // the fitted arrays), coordinates, metadata and tile records (watermarks).
    let o = replay(&cap, &cut, Some(&cfg));
    assert!(o.status.success(), "{}", text(&o.stderr));
    let summary = summary_of(&cut);
    let resumed = summary["sinks"]["voxels"]["deposits"]["bins_resumed"]
        .as_u64()
        .unwrap();
    assert!(resumed > 0, "the rerun skipped what the store held");
    let (a, b) = (
        store_files(&whole.join("voxels.zarr")),
        store_files(&cut.join("voxels.zarr")),
    );
    let chunks = a.keys().filter(|k| k.contains("/c/0/")).count();
    assert!(chunks > min_files, "{chunks} chunk files");
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (k, v) in &a {
        assert!(b[k] == *v, "{k} differs after kill -9 and rerun");
    }
    // Both fitted to their tiles, which xarray reads without a warning.
    let fa = check_fitted(&whole.join("voxels.zarr"));
    let fb = check_fitted(&cut.join("voxels.zarr"));
    assert_eq!(fa, fb);
    assert_eq!(
        fa["samples"],
        summary_of(&whole)["sinks"]["voxels"]["deposits"]["bins_deposited"]
    );

    // A rerun of a complete store changes nothing.
    let o = replay(&cap, &cut, Some(&cfg));
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert_eq!(store_files(&cut.join("voxels.zarr")), a);
}

fn read_all(root: &Path) -> BTreeMap<[i64; 2], Dense> {
    ZarrStore::open(root)
        .unwrap()
        .read_all()
        .unwrap()
        .into_iter()
        .map(|(t, d)| (t, d.dense()))
        .collect()
}

#[test]
fn merge_adds_stores_exactly_and_refuses_what_does_not_fit() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = crash_config(dir.path());
    let mut roots = Vec::new();
    for seed in [1u64, 2] {
        let cap = simulate(dir.path(), 3000, seed, &format!("s{seed}.fwcap"));
        let out = dir.path().join(format!("o{seed}"));
        let o = replay(&cap, &out, Some(&cfg));
        assert!(o.status.success(), "{}", text(&o.stderr));
        roots.push(out.join("voxels.zarr"));
    }
    let m1 = dir.path().join("m1.zarr");
    let m2 = dir.path().join("m2.zarr");
    let o = fwlidar(&[
        "merge",
        roots[0].to_str().unwrap(),
        roots[1].to_str().unwrap(),
        "--out",
        m1.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(
        text(&o.stdout).contains("merged 2 stores"),
        "{}",
        text(&o.stdout)
    );
    let o = fwlidar(&[
        "merge",
        roots[1].to_str().unwrap(),
        roots[0].to_str().unwrap(),
        "--out",
        m2.to_str().unwrap(),
        "--no-progress",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    // Same bytes whatever the order: chunks, coordinates, metadata, records.
    assert_eq!(store_files(&m1), store_files(&m2));
    // The merged arrays span the tiles of both flights (not the union of their 8 km extents),
    // and hold all their samples.
    let (f0, f1, fm) = (
        check_fitted(&roots[0]),
        check_fitted(&roots[1]),
        check_fitted(&m1),
    );
    let n = |v: &serde_json::Value, k: &str| v[k].as_u64().unwrap();
    assert_eq!(n(&fm, "samples"), n(&f0, "samples") + n(&f1, "samples"));
    assert_eq!(n(&fm, "pulses"), n(&f0, "pulses") + n(&f1, "pulses"));
    assert!(
        n(&fm, "tiles") < n(&f0, "tiles") + n(&f1, "tiles"),
        "shared tiles"
    );
    // Element-wise: sums and counts add, maxima take the larger.
    let (a, b, m) = (read_all(&roots[0]), read_all(&roots[1]), read_all(&m1));
    assert!(!m.is_empty());
    let mut overlapping = 0;
    for (t, md) in &m {
        let empty = TileData::new(1, md.sum_q.len(), 1).dense();
        let (ad, bd) = (a.get(t).unwrap_or(&empty), b.get(t).unwrap_or(&empty));
        if a.contains_key(t) && b.contains_key(t) {
            overlapping += 1;
        }
        for i in 0..md.sum_q.len() {
            assert_eq!(md.sum_q[i], ad.sum_q[i] + bd.sum_q[i]);
            assert_eq!(md.samples[i], ad.samples[i] + bd.samples[i]);
            assert_eq!(md.pulses[i], ad.pulses[i] + bd.pulses[i]);
            let want = ad.max[i].max(bd.max[i]);
            assert_eq!(md.max[i].to_bits(), want.to_bits());
        }
    }
    assert!(overlapping > 0, "the two flights share tiles");

    // An existing output is never overwritten; a store of another grid is refused.
    let o = fwlidar(&[
        "merge",
        roots[0].to_str().unwrap(),
        "--out",
        m1.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(text(&o.stderr).contains("exists"), "{}", text(&o.stderr));
    let other_cfg = dir.path().join("other.toml");
    std::fs::write(
        &other_cfg,
        std::fs::read_to_string(&cfg)
            .unwrap()
            .replace("tile_columns = 4", "tile_columns = 8"),
    )
    .unwrap();
    let cap = dir.path().join("s1.fwcap");
    let other = dir.path().join("other");
    assert!(replay(&cap, &other, Some(&other_cfg)).status.success());
    let m3 = dir.path().join("m3.zarr");
    let o = fwlidar(&[
        "merge",
        roots[0].to_str().unwrap(),
        other.join("voxels.zarr").to_str().unwrap(),
        "--out",
        m3.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o.stderr).contains("tile sizes differ: 4 and 8 columns"),
        "{}",
        text(&o.stderr)
    );
    assert!(!m3.exists());
}

#[test]
fn an_output_that_cannot_hold_the_store_is_a_clear_error_and_nothing_is_changed() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    // voxels.zarr is a plain file.
    std::fs::write(out.join("voxels.zarr"), b"precious").unwrap();
    let o = replay(&sample(), &out, None);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stderr));
    let err = text(&o.stderr);
    assert!(err.contains("voxels.zarr"), "{err}");
    assert_eq!(std::fs::read(out.join("voxels.zarr")).unwrap(), b"precious");

    // A store written by another run (another configuration) is refused, not mixed into.
    let out2 = dir.path().join("out2");
    assert!(replay(&sample(), &out2, None).status.success());
    let before = store_files(&out2.join("voxels.zarr"));
    let cfg = dir.path().join("c.toml");
    std::fs::write(
        &cfg,
        std::fs::read_to_string(Path::new(ROOT).join("config/replay.toml"))
            .unwrap()
            .replace("cutoff_ghz = 0.2", "cutoff_ghz = 0.25"),
    )
    .unwrap();
    let o = replay(&sample(), &out2, Some(&cfg));
    assert_eq!(o.status.code(), Some(1));
    let err = text(&o.stderr);
    assert!(err.contains("written by another run"), "{err}");
    assert!(err.contains("nothing was changed"), "{err}");
    assert_eq!(store_files(&out2.join("voxels.zarr")), before);
}

mod damaged_store {
    use super::*;
    use proptest::prelude::*;

    /// A small store with two tiles, written once and copied for each case.
    fn pristine() -> &'static Path {
        static DIR: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
        DIR.get_or_init(|| {
            use fwlidar::voxel::grid::{Grid, VoxelConfig};
            use fwlidar::voxel::zarr::StoreInfo;
            let dir = tempfile::tempdir().unwrap();
            let grid = Grid::new(
                &VoxelConfig {
                    extent_m: Some([0.0, 0.0, 16.0, 8.0]),
                    z_range_m: [0.0, 0.6],
                    tile_columns: 4,
                    ..VoxelConfig::default()
                },
                [0.0, 0.0],
            );
            let mut s = ZarrStore::create_or_open(
                &dir.path().join("v.zarr"),
                grid.clone(),
                StoreInfo {
                    crs_wkt: None,
                    epsg: Some(32736),
                    intensity_units: "V".into(),
                    run_key: "p".into(),
                    configuration: String::new(),
                },
            )
            .unwrap();
            let mut t = TileData::for_grid(&grid);
            t.deposit(3, 1000, 1.0);
            t.pass(3);
            s.write_tile([0, 0], &t, 7).unwrap();
            s.write_tile([1, 0], &t, 9).unwrap();
            dir
        })
        .path()
    }

    fn copy_dir(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let p = e.unwrap().path();
            let q = to.join(p.file_name().unwrap());
            if p.is_dir() {
                copy_dir(&p, &q);
            } else {
                std::fs::copy(&p, &q).unwrap();
            }
        }
    }

    proptest! {
        #![proptest_config(common::proptest_cases(64, "proptest-regressions/tests/voxel_tiles.txt"))]
        /// Opening and reading a store whose files were cut, overwritten or garbled returns an
        /// error or data, never panics (the reader behind `merge` and resuming).
        #[test]
        fn a_damaged_store_never_panics(
            which in 0usize..64,
            cut in proptest::option::of(0usize..4096),
            flips in proptest::collection::vec((0usize..4096, any::<u8>()), 0..8),
        ) {
            let dir = tempfile::tempdir().unwrap();
            let root = dir.path().join("v.zarr");
            copy_dir(&pristine().join("v.zarr"), &root);
            let files: Vec<String> = store_files(&root).into_keys().collect();
            let victim = root.join(&files[which % files.len()]);
            let mut bytes = std::fs::read(&victim).unwrap();
            if let Some(c) = cut {
                bytes.truncate(c.min(bytes.len()));
            }
            for (at, v) in flips {
                if !bytes.is_empty() {
                    let i = at % bytes.len();
                    bytes[i] = v;
                }
            }
            std::fs::write(&victim, &bytes).unwrap();
            if let Ok(mut s) = ZarrStore::open(&root) {
                let g = s.grid();
                let chunk_ok = g.chunk_voxels() <= 1 << 20 && g.height_chunks() <= 1 << 20;
                if chunk_ok {
                    let mut d = TileData::for_grid(g);
                    for t in s.tiles() {
                        let _ = s.read_tile(t, &mut d);
                    }
                }
            }
        }
    }
}

/// A full disk: the replay stops with an error naming the voxel file it could not write and
/// "No space left on device", exit 1; the input is untouched. Needs a small tmpfs, so root (CI
/// runs as root); elsewhere the test says it could not mount and checks nothing.
#[test]
fn a_full_disk_stops_the_replay_with_an_error_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("small");
    let _disk = common::Tmpfs::mount(&mnt, "48k");
    // Voxels only (the CSV outputs would fill the disk first, which is the same path).
    let cfg = dir.path().join("voxels_only.toml");
    std::fs::write(
        &cfg,
        std::fs::read_to_string(volts_config(dir.path()))
            .unwrap()
            .replace("waveforms = true", "waveforms = false")
            .replace("returns = true", "returns = false"),
    )
    .unwrap();
    let input = sample();
    let before = std::fs::read(&input).unwrap();
    let out = mnt.join("out");
    let o = replay(&input, &out, Some(&cfg));
    assert_eq!(o.status.code(), Some(1), "{}", text(&o.stderr));
    let err = text(&o.stderr);
    assert!(err.contains("voxels.zarr"), "{err}");
    assert!(err.contains("No space left on device"), "{err}");
    assert_eq!(
        std::fs::read(&input).unwrap(),
        before,
        "the input is never touched"
    );
}

/// A new store at `root` on the default grid (every height, sparse chunks, sharded) over two
/// 16 m tiles, `[0, 0, 32, 16]` m, with run key `run_key`.
fn two_tile_default_store(
    root: &std::path::Path,
    run_key: &str,
) -> (fwlidar::voxel::grid::Grid, ZarrStore) {
    use fwlidar::voxel::grid::{Grid, VoxelConfig};
    use fwlidar::voxel::zarr::StoreInfo;
    let cfg = VoxelConfig {
        enabled: true,
        extent_m: Some([0.0, 0.0, 32.0, 16.0]),
        ..VoxelConfig::default()
    };
    let grid = Grid::new(&cfg, [0.0, 0.0]);
    let s = ZarrStore::create_or_open(
        root,
        grid.clone(),
        StoreInfo {
            crs_wkt: None,
            epsg: Some(32736),
            intensity_units: "V".into(),
            run_key: run_key.into(),
            configuration: String::new(),
        },
    )
    .unwrap();
    (grid, s)
}

/// On the default grid (every height on Earth, sparse height chunks) bins far above and below
/// any former fixed range land; only the height chunks holding them exist on disk (empty air is
/// absent); and zarr-python reads the zstd store back equal to what was deposited.
#[test]
fn far_heights_land_in_sparse_zstd_chunks_that_zarr_python_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("v.zarr");
    let (grid, mut s) = two_tile_default_store(&root, "far");
    assert_eq!(grid.chunk_levels(), 64);
    let level = |z: f64| ((z - grid.z_bottom_m) / grid.voxel_size_m[2]).floor() as usize;
    let l = grid.levels as usize;
    // Column (i=3, j=5) of tile (0, 0): a bin at 8500 m and one at -900 m; tile (1, 0): 12 m.
    let mut a = TileData::for_grid(&grid);
    let (k_hi, k_lo) = (level(8500.0), level(-900.0));
    a.deposit((5 * 32 + 3) * l + k_hi, 2_500_000, 2.5);
    a.pass((5 * 32 + 3) * l + k_hi);
    a.deposit((5 * 32 + 3) * l + k_lo, 1_000_000, 1.0);
    let mut b = TileData::for_grid(&grid);
    let k_mid = level(12.0);
    b.deposit(7 * l + k_mid, 3_000_000, 3.0);
    s.write_tile([0, 0], &a, 1).unwrap();
    s.write_tile([1, 0], &b, 2).unwrap();
    s.fit().unwrap();
    // Three height chunks hold data: only their chunks exist (4 arrays each).
    let chunk_files: Vec<String> = store_files(&root)
        .into_keys()
        .filter(|f| f.starts_with("sample_count/c/"))
        .collect();
    assert_eq!(chunk_files.len(), 3, "{chunk_files:?}");
    let span = *s.span();
    let kc = |k: usize| (k / 64) as u32;
    assert_eq!(span.level_chunk_min, kc(k_lo));
    assert_eq!(span.level_chunks, kc(k_hi) - kc(k_lo) + 1);
    let script = r#"
import sys, json, numpy as np, xarray as xr, zarr
ds = xr.open_zarr(sys.argv[1])
codecs = zarr.open_array(sys.argv[1] + "/sample_count").metadata.codecs
assert type(codecs[0]).__name__ == "ShardingCodec", codecs
assert any(type(c).__name__ == "ZstdCodec" for c in codecs[0].codecs), codecs
# Read each variable once: with dask installed, open_zarr is lazy and every `.values`
# reads the whole array again.
n, isum, pc = (ds[v].values for v in ("sample_count", "intensity_sum", "pulse_count"))
z, y, x = ds.z.values, ds.y.values, ds.x.values
hits = np.argwhere(n > 0)
out = []
for k, j, i in hits:
    out.append([float(z[k]), float(y[j]), float(x[i]), int(n[k, j, i]),
                float(isum[k, j, i]), int(pc[k, j, i])])
print(json.dumps(out))
"#;
    let o = Command::new(python())
        .arg("-c")
        .arg(script)
        .arg(&root)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    let got: Vec<[f64; 6]> = serde_json::from_slice(&o.stdout).unwrap();
    let centre = |k: usize| grid.z_bottom_m + (k as f64 + 0.5) * grid.voxel_size_m[2];
    let want = [
        [centre(k_lo), 2.75, 1.75, 1.0, 1.0, 0.0],
        [centre(k_mid), 0.25, 19.75, 1.0, 3.0, 0.0],
        [centre(k_hi), 2.75, 1.75, 1.0, 2.5, 1.0],
    ];
    assert_eq!(got.len(), 3, "{got:?}");
    for (g, w) in got.iter().zip(&want) {
        for (a, b) in g.iter().zip(w) {
            assert!((a - b).abs() < 1e-6, "{got:?} vs {want:?}");
        }
    }
}

/// Every voxel holding a sample or a pass, as `[k, j, i, sum_q, samples, max, pulses]` in the
/// fitted arrays' indices, from the Rust reader.
fn voxels_of(s: &mut ZarrStore) -> Vec<[f64; 7]> {
    let g = s.grid().clone();
    let span = *s.span();
    let (t, l, h) = (
        g.tile_columns as usize,
        g.levels as usize,
        g.chunk_levels() as usize,
    );
    let mut out = Vec::new();
    for (tile, d) in s.read_all().unwrap() {
        let (ox, oy) = (
            (tile[0] - span.tile_min[0]) as usize * t,
            (tile[1] - span.tile_min[1]) as usize * t,
        );
        for kc in d.present() {
            let c = d.chunk(kc as usize).unwrap();
            for col in 0..c.columns() {
                let Some(v) = c.column(col) else { continue };
                for kk in 0..h {
                    let k = kc as usize * h + kk;
                    if k < l && (v.samples[kk] > 0 || v.pulses[kk] > 0) {
                        let max = if v.max[kk].is_nan() {
                            -1.0
                        } else {
                            v.max[kk] as f64
                        };
                        out.push([
                            (k - span.level_chunk_min as usize * h) as f64,
                            (oy + col / t) as f64,
                            (ox + col % t) as f64,
                            v.sum_q[kk] as f64,
                            v.samples[kk] as f64,
                            max,
                            v.pulses[kk] as f64,
                        ]);
                    }
                }
            }
        }
    }
    out.sort_by(|a, b| a.partial_cmp(b).unwrap());
    out
}

/// zarr-python's view of the same voxels (and that every other voxel is fill value); with
/// `unshard`, it first rewrites the four data arrays unsharded (one zstd chunk per tile and
/// height chunk, as fwlidar wrote stores before sharding).
const ZARR_VOXELS: &str = r#"
import sys, json, numpy as np, zarr
from zarr.codecs import ZstdCodec
root, mode = sys.argv[1], sys.argv[2]
names = ["intensity_sum", "sample_count", "intensity_max", "pulse_count"]
if mode == "unshard":
    for a in names:
        old = zarr.open_array(root + "/" + a)
        data, attrs = old[:], dict(old.attrs)
        new = zarr.create_array(root + "/" + a, shape=old.shape, chunks=old.metadata.chunk_grid.chunk_shape,
                                dtype=old.dtype, fill_value=old.metadata.fill_value,
                                compressors=[ZstdCodec(level=1)], dimension_names=["z", "y", "x"],
                                attributes=attrs, overwrite=True)
        new[:] = data
else:
    c = zarr.open_array(root + "/sample_count").metadata.codecs
    assert len(c) == 1 and type(c[0]).__name__ == "ShardingCodec", c
    assert tuple(c[0].chunk_shape) == (64, 8, 8), c
    assert [type(x).__name__ for x in c[0].index_codecs] == ["BytesCodec"], c
s, n, m, p = (zarr.open_array(root + "/" + a)[:] for a in names)
held = (n > 0) | (p > 0)
assert (s[~held] == 0).all() and np.isnan(m[~held]).all()
out = [[int(k), int(j), int(i), int(s[k, j, i]), int(n[k, j, i]),
        -1.0 if np.isnan(m[k, j, i]) else float(m[k, j, i]), int(p[k, j, i])]
       for k, j, i in np.argwhere(held)]
print(json.dumps(out))
"#;

fn zarr_voxels(root: &Path, mode: &str) -> Vec<[f64; 7]> {
    let o = Command::new(python())
        .arg("-c")
        .arg(ZARR_VOXELS)
        .arg(root)
        .arg(mode)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    let mut v: Vec<[f64; 7]> = serde_json::from_slice(&o.stdout).unwrap();
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v
}

/// A sparse store (a few columns of two tiles) holds in each shard only the inner chunks where
/// a sample or a pass landed, the same ones in all four arrays (a pass-only block too);
/// zarr-python reads exactly the voxels the Rust reader reads. Rewritten by zarr-python in the
/// unsharded layout of earlier versions, the store reads the same in Rust.
#[test]
fn a_sparse_store_holds_only_the_inner_chunks_with_data_and_old_stores_still_read() {
    use fwlidar::voxel::zarr::ARRAYS;
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("v.zarr");
    let (grid, mut s) = two_tile_default_store(&root, "sparse");
    assert_eq!((grid.tile_columns, grid.chunk_levels()), (32, 64));
    let l = grid.levels as usize;
    let k = ((12.0 - grid.z_bottom_m) / grid.voxel_size_m[2]).floor() as usize;
    let k = k - k % 64 + 10; // 10 levels into its height chunk
    let mut a = TileData::for_grid(&grid);
    // Tile (0, 0): column (i=3, j=1) in inner chunk 0, a deposit and a pass; column
    // (i=17, j=30) in inner chunk 3·4 + 2 = 14, a pass only.
    a.deposit((32 + 3) * l + k, 2_500_000, 2.5);
    a.deposit((32 + 3) * l + k + 1, -400, -0.0004);
    a.pass((32 + 3) * l + k);
    a.pass((30 * 32 + 17) * l + k + 5);
    // Tile (1, 0): column (i=9, j=9), inner chunk 5, the next height chunk.
    let mut b = TileData::for_grid(&grid);
    b.deposit((9 * 32 + 9) * l + k + 64, 3_000_000, 3.0);
    s.write_tile([0, 0], &a, 1).unwrap();
    s.write_tile([1, 0], &b, 2).unwrap();
    s.fit().unwrap();
    let kc = (k / 64) as u32;
    for (tile, kcs, blocks) in [
        ([0, 0], vec![kc], vec![0, 14]),
        ([1, 0], vec![kc + 1], vec![5]),
    ] {
        for a in ARRAYS {
            let p = s.chunk_path(a, tile, kcs[0]).unwrap();
            let bytes = std::fs::read(&p).unwrap();
            let index: Vec<u64> = bytes[bytes.len() - 16 * 16..]
                .chunks_exact(8)
                .map(|w| u64::from_le_bytes(w.try_into().unwrap()))
                .collect();
            let present: Vec<usize> = (0..16).filter(|b| index[2 * b] != u64::MAX).collect();
            assert_eq!(present, blocks, "{a} {tile:?}");
            let data: u64 = present.iter().map(|b| index[2 * b + 1]).sum();
            assert_eq!(bytes.len() as u64, data + 16 * 16, "{a} {tile:?}");
            // A 64 × 8 × 8 inner chunk of nearly nothing compresses far below its 16 KB.
            assert!(
                data < 400 * present.len() as u64,
                "{a} {tile:?}: {data} bytes"
            );
        }
    }
    let rust = voxels_of(&mut s);
    assert_eq!(rust.len(), 4, "{rust:?}");
    let py = zarr_voxels(&root, "sharded");
    assert_eq!(py, rust);
    // The layout of earlier versions, as zarr-python writes it: read the same.
    drop(s);
    assert_eq!(zarr_voxels(&root, "unshard"), rust);
    let meta = std::fs::read_to_string(root.join("sample_count/zarr.json")).unwrap();
    assert!(!meta.contains("sharding_indexed"), "{meta}");
    let mut old = ZarrStore::open(&root).unwrap();
    assert_eq!(voxels_of(&mut old), rust);
}

/// A real GEDI L1B granule (the fixture: 32 shots of 2 beams) in the default layout, tiles
/// grouped into shard files, holds the same voxels tile by tile as the layout of a file per
/// tile, in a tenth of the files, and zarr-python reads every tile where the arrays say.
#[test]
fn a_gedi_granule_replays_into_grouped_shard_files_that_zarr_python_reads() {
    let dir = tempfile::tempdir().unwrap();
    let granule = common::fixture("waveform/gedi/GEDI01_B_O01964_beams0001_1011.h5");
    let run = |name: &str, layout: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "replay",
            granule.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--no-progress",
        ];
        args.extend_from_slice(layout);
        let o = fwlidar(&args);
        assert!(o.status.success(), "{}", text(&o.stderr));
        let files = store_files(&out.join("voxels.zarr"))
            .keys()
            .filter(|k| k.contains("/c/"))
            .count();
        let deposited = summary_of(&out)["sinks"]["voxels"]["deposits"]["bins_deposited"]
            .as_u64()
            .unwrap();
        (check_fitted(&out.join("voxels.zarr")), files, deposited)
    };
    let (grouped, grouped_files, deposited) = run("grouped", &[]);
    let (per_tile, per_tile_files, _) = run("per_tile", &["--set", "voxels.shard_tiles=0"]);
    assert!(deposited > 0);
    assert_eq!(grouped["samples"].as_u64(), Some(deposited), "{grouped}");
    assert!(grouped["tiles"].as_u64().unwrap() > 10, "{grouped}");
    // Tile by tile the same samples; the arrays of the grouped store start at a group's corner.
    assert_eq!(grouped["per_tile"], per_tile["per_tile"]);
    assert_eq!(grouped["pulses"], per_tile["pulses"]);
    assert!(
        grouped_files * 10 <= per_tile_files,
        "{grouped_files} shard files against {per_tile_files}"
    );
}
