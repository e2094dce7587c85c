//! `fwlidar metrics STORE --out DIR` (issue 20, "rasters as flown"): forest structure rasters
//! recomputed from the voxel store a replay wrote, opened by GDAL's `gdalinfo` and rasterio
//! (a missing reader fails the test, naming `tests/run.sh`), and checked against the scene truth and the replay's
//! own per-pulse rasters.

mod common;

use std::path::Path;
use std::process::Command;

fn replay(capture: &str, out: &Path) {
    let o = common::fwlidar(&[
        "replay",
        capture,
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
        "--set",
        "output.las=false",
        "--set",
        "output.waveforms=false",
    ]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    assert!(out.join("voxels.zarr/zarr.json").exists());
}

fn metrics(store: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "metrics",
        store.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
    ];
    args.extend_from_slice(extra);
    common::fwlidar(&args)
}

/// Runs a Python script with the rasterio of `common::python()` (a missing rasterio fails the
/// test, naming `tests/run.sh`); its JSON output.
fn python(script: &str, args: &[&Path]) -> serde_json::Value {
    let py = common::python_with(&["numpy", "rasterio"]);
    let o = Command::new(&py)
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("run python");
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// Median of each named band's valid cells, the CRS and the size of a raster.
const BAND_MEDIANS: &str = r#"
import sys, json, numpy as np, rasterio
out = {}
for path in sys.argv[1:]:
    with rasterio.open(path) as ds:
        a = ds.read()
        valid = a[0] != ds.nodata
        out[path] = {"epsg": ds.crs.to_epsg(), "res": ds.res[0], "cells": int(valid.sum()),
                     "width": ds.width, "height": ds.height,
                     "median": {d: float(np.median(a[i][a[i] != ds.nodata]))
                                for i, d in enumerate(ds.descriptions)}}
print(json.dumps(out))
"#;

#[test]
fn metrics_from_the_two_layer_store_match_the_scene_and_the_per_pulse_rasters() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    replay("replay/two_layer.fwcap", &out);
    let m = dir.path().join("m");
    let o = metrics(&out.join("voxels.zarr"), &m, &[]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let stdout = common::text(&o.stdout);
    assert!(stdout.contains("EPSG:32736"), "{stdout}");
    for f in ["chm.vrt", "metrics.vrt", "metrics.json"] {
        assert!(m.join(f).exists(), "{f}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(m.join("metrics.json")).unwrap()).unwrap();
    // The default cell is the voxel column (0.5 m); the replay's settings were found.
    assert_eq!(report["cell_m"], 0.5, "{report}");
    assert_eq!(report["settings_from"], "store configuration", "{report}");
    assert!(report["cells_ok"][0].as_u64().unwrap() >= 1, "{report}");

    {
        let info = common::gdalinfo_json(&m.join("metrics.vrt"));
        let wkt = info["coordinateSystem"]["wkt"].as_str().unwrap_or("");
        assert!(wkt.contains("UTM zone 36S"), "{wkt}");
        // One raster tile of 512 × 512 cells of 0.5 m.
        assert_eq!(info["size"], serde_json::json!([512, 512]), "{info}");
        assert_eq!(info["geoTransform"][1], 0.5);
        let names: Vec<&str> = info["bands"]
            .as_array()
            .unwrap()
            .iter()
            .map(|b| b["description"].as_str().unwrap_or(""))
            .collect();
        assert_eq!(names[..5], ["rh25", "rh50", "rh75", "rh98", "rh100"]);
        assert_eq!(names.last(), Some(&"pulse_density"));
        assert!(names.contains(&"ground_z") && names.contains(&"cover"));
    }

    let store_chm = m.join("chm.vrt");
    let store_metrics = m.join("metrics.vrt");
    let pulse_metrics = out.join("rasters/metrics.vrt");
    let v = python(BAND_MEDIANS, &[&store_chm, &store_metrics, &pulse_metrics]);
    let s_chm = &v[store_chm.to_str().unwrap()];
    let s = &v[store_metrics.to_str().unwrap()];
    let p = &v[pulse_metrics.to_str().unwrap()];
    assert_eq!(s_chm["epsg"], 32736, "{v}");
    assert_eq!(s["epsg"], 32736, "{v}");
    assert_eq!(s_chm["res"], 0.5, "{v}");
    let med = |r: &serde_json::Value, b: &str| r["median"][b].as_f64().unwrap();
    // The canopy plane is 15 m above the ground. The deconvolved echo keeps a σ of about
    // 0.45 m (ground_sigma_m), so RH98 sits up to ~2σ above the plane: measured 15.85 m.
    let rh98 = med(s, "rh98");
    assert!((15.0..16.5).contains(&rh98), "store RH98 {rh98}");
    // The store's canopy height (RH100 of the column, the 3 % start of the deconvolved profile)
    // sits above the 15 m plane by the deconvolved echo's leading edge: measured 16.28 m. The
    // per-pulse RH100 of the replay's own rasters starts on the raw waveform smoothed by the
    // outgoing pulse's σ, 3 noise σ above the noise, so it is higher still (17.22 m).
    let chm = med(s_chm, "canopy_height");
    let per_pulse = med(p, "rh100");
    assert!((15.0..17.0).contains(&chm), "store CHM {chm}");
    assert!(
        per_pulse > chm - 0.5 && per_pulse < chm + 1.5,
        "store CHM {chm} against per-pulse RH100 {per_pulse}"
    );
    assert!((chm - med(s, "rh100")).abs() < 1e-4);
    // The ground: flat, where the per-pulse metrics put it (0.26-0.29 m in pulse_metrics.csv).
    let csv = std::fs::read_to_string(out.join("pulse_metrics.csv")).unwrap();
    let mut zs: Vec<f64> = csv
        .lines()
        .skip(1)
        .filter(|l| l.split(',').nth(5) == Some("ok"))
        .map(|l| l.split(',').nth(4).unwrap().parse().unwrap())
        .collect();
    zs.sort_by(f64::total_cmp);
    let ground = med(s, "ground_z");
    assert!(
        (ground - zs[zs.len() / 2]).abs() < 0.2,
        "store ground {ground} against per-pulse {}",
        zs[zs.len() / 2]
    );
    // 40 % of each footprint is intercepted: cover near 0.4 (measured 0.42; the per-pulse
    // median is 0.33).
    let cover = med(s, "cover");
    assert!((0.35..0.5).contains(&cover), "cover {cover}");
    assert!(med(s, "pai") > 0.5, "PAI {}", med(s, "pai"));
    // 2000 pulses over the few 0.5 m columns the capture hits.
    assert!(med(s, "pulse_density") > 100.0, "{v}");
}

#[test]
fn tree_plot_canopy_heights_from_the_store_follow_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let truth = dir.path().join("truth");
    replay("replay/tree_plot.fwcap", &out);
    // The truth capture: the same shots with a 2 ns pulse and no effects; its per-pulse CHM is
    // the reference.
    replay("replay/tree_plot.truth.fwcap", &truth);
    let store = out.join("voxels.zarr");
    let m1 = dir.path().join("m1");
    let o = metrics(&store, &m1, &["--cell", "1"]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    // Cells of 0.5 m and of 10 m (which straddle the store's 16 m tiles): every column's
    // pulses land in exactly one cell either way.
    let m05 = dir.path().join("m05");
    let m10 = dir.path().join("m10");
    for (d, cell) in [(&m05, "0.5"), (&m10, "10")] {
        let o = metrics(&store, d, &["--cell", cell]);
        assert!(o.status.success(), "{}", common::text(&o.stderr));
    }
    let script = r#"
import sys, json, numpy as np, rasterio
from rasterio.windows import from_bounds
def common(a_path, b_path):
    with rasterio.open(a_path) as A, rasterio.open(b_path) as B:
        l = max(A.bounds.left, B.bounds.left); r = min(A.bounds.right, B.bounds.right)
        bt = max(A.bounds.bottom, B.bounds.bottom); t = min(A.bounds.top, B.bounds.top)
        wa = A.read(1, window=from_bounds(l, bt, r, t, A.transform))
        wb = B.read(1, window=from_bounds(l, bt, r, t, B.transform))
        m = (wa != A.nodata) & (wb != B.nodata)
        d = np.abs(wa[m] - wb[m])
        return {"cells": int(m.sum()), "median_abs": float(np.median(d)),
                "p75_abs": float(np.percentile(d, 75))}
def pulses(path):
    with rasterio.open(path) as ds:
        i = list(ds.descriptions).index("pulse_density") + 1
        a = ds.read(i)
        return float(a[a != ds.nodata].sum() * ds.res[0] * ds.res[1])
store, raw, truth, m05, m10 = sys.argv[1:]
print(json.dumps({"store": common(store, truth), "per_pulse": common(raw, truth),
                  "pulses_05": pulses(m05), "pulses_10": pulses(m10)}))
"#;
    let v = python(
        script,
        &[
            &m1.join("chm.vrt"),
            &out.join("rasters/chm.vrt"),
            &truth.join("rasters/chm.vrt"),
            &m05.join("metrics.vrt"),
            &m10.join("metrics.vrt"),
        ],
    );
    println!("{v}");
    let s = &v["store"];
    // Every 1 m cell of the replay's CHM has one from the store (434 on this plot).
    assert!(s["cells"].as_u64().unwrap() >= 400, "{v}");
    // Measured: median |store − truth| 0.31 m, 75th percentile 0.6 m. The tail (about 6 % of
    // the cells, under the densest crowns) is where the ground echo is weaker than the modes'
    // 6 % of the profile's peak and the lowest mode is in the crown (docs/forest.md).
    let med = s["median_abs"].as_f64().unwrap();
    assert!(med < 0.5, "store CHM against the truth: {v}");
    // The raw per-pulse CHM (16 ns pulse, 2.5 m on bare ground) is further from the truth.
    assert!(
        med < v["per_pulse"]["median_abs"].as_f64().unwrap(),
        "the store's CHM should beat the raw per-pulse one: {v}"
    );
    // The pulses of the 0.5 m columns and of the 10 m cells across tiles are the same.
    let (a, b) = (
        v["pulses_05"].as_f64().unwrap(),
        v["pulses_10"].as_f64().unwrap(),
    );
    assert!(a > 1000.0 && (a - b).abs() < 1e-3 * a, "{v}");
}

#[test]
fn bad_stores_and_a_non_empty_output_are_refused_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nowhere.zarr");
    let out = dir.path().join("m");
    let o = metrics(&missing, &out, &[]);
    assert_eq!(o.status.code(), Some(1));
    let err = common::text(&o.stderr);
    assert!(
        err.contains(missing.to_str().unwrap()) && err.contains("does not exist"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written for a missing store");

    // A folder that is not a store, and one whose metadata is damaged.
    let empty = dir.path().join("empty.zarr");
    std::fs::create_dir(&empty).unwrap();
    let o = metrics(&empty, &out, &[]);
    assert_eq!(o.status.code(), Some(1));
    let err = common::text(&o.stderr);
    assert!(err.contains("not a voxel store"), "{err}");
    let bad = dir.path().join("bad.zarr");
    std::fs::create_dir(&bad).unwrap();
    std::fs::write(bad.join("zarr.json"), "{ not json").unwrap();
    let o = metrics(&bad, &out, &[]);
    assert_eq!(o.status.code(), Some(1));
    let err = common::text(&o.stderr);
    assert!(
        err.contains(bad.join("zarr.json").to_str().unwrap()) && err.contains("not JSON"),
        "{err}"
    );

    // A non-empty output folder needs --force; bad options are usage errors.
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "x").unwrap();
    let o = metrics(&bad, &out, &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(common::text(&o.stderr).contains("--force"));
    let o = metrics(&bad, &dir.path().join("m2"), &["--cell=-1"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(common::text(&o.stderr).contains("--cell"));
}
