//! The IGN LiDAR-HD DTM (GeoTIFF, Lambert-93) read by `fwlidar::geo::dem`, sampled at the
//! ground points of the same tile's point cloud, which a real LAZ reader (laspy with lazrs, in
//! the venv `tests/run.sh` makes) extracts: the residuals say whether our reader puts every pixel
//! where it belongs.

mod common;

use std::process::Command;

use common::{fixture, python};
use fwlidar::geo::dem::Dem;

#[test]
fn ign_dtm_agrees_with_its_own_ground_points() {
    let tif = fixture("dem/ign_lidarhd/DTM_test_data_77055_627760_LA93_IGN69_50CM.tif");
    let laz = fixture("dem/ign_lidarhd/test_data_77055_627760_LA93_IGN69.laz");
    let dem = Dem::open(&tif).unwrap();
    assert_eq!(dem.size, (100, 100));
    assert_eq!(dem.pixel, [0.5, 0.5]);
    assert_eq!(dem.epsg, Some(2154));
    assert_eq!(dem.nodata, Some(-9999.0));
    dem.check_crs("dtm", 2154).unwrap();
    assert!(dem.check_crs("dtm", 32631).is_err());

    let script = "import laspy, sys\n\
                  las = laspy.read(sys.argv[1])\n\
                  g = las.classification == 2\n\
                  print(int(g.sum()), len(las.points))\n\
                  for x, y, z in zip(las.x[g], las.y[g], las.z[g]):\n\
                  \x20   print(f'{x:.3f} {y:.3f} {z:.3f}')\n";
    let out = Command::new(python())
        .args(["-c", script, laz.to_str().unwrap()])
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "laspy/lazrs could not read the LAZ: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    let head: Vec<usize> = lines
        .next()
        .unwrap()
        .split(' ')
        .map(|v| v.parse().unwrap())
        .collect();
    assert_eq!(
        head,
        vec![22_343, 60_653],
        "ground points, all points (MANIFEST)"
    );
    let points: Vec<Vec<f64>> = lines
        .map(|l| l.split(' ').map(|x| x.parse().unwrap()).collect())
        .collect();
    let mut residuals = Vec::new();
    let mut outside = 0;
    for v in &points {
        match dem.height_at(v[0], v[1]) {
            Some(z) => residuals.push(v[2] - z),
            None => outside += 1,
        }
    }
    // The same with the grid misplaced by one pixel (what a corner/centre or tie-point slip
    // would do): the check must be able to tell.
    let mut shifted = dem.clone();
    shifted.first_centre[0] += 0.5;
    shifted.first_centre[1] -= 0.5;
    let mut shifted_abs: Vec<f64> = points
        .iter()
        .filter_map(|v| shifted.height_at(v[0], v[1]).map(|z| (v[2] - z).abs()))
        .collect();
    shifted_abs.sort_by(f64::total_cmp);
    let shifted_mad50 = shifted_abs[shifted_abs.len() / 2];
    let n = residuals.len();
    let mut abs: Vec<f64> = residuals.iter().map(|r| r.abs()).collect();
    abs.sort_by(f64::total_cmp);
    let mut sorted = residuals.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[n / 2];
    let mad50 = abs[n / 2];
    let p95 = abs[(n as f64 * 0.95) as usize];
    eprintln!(
        "DTM at {n} ground points ({outside} outside the pixel centres or next to nodata): \
         residual median {median:+.3} m, |residual| median {mad50:.3} m, p95 {p95:.3} m, max {:.3} m; \
         grid one pixel off: |residual| median {shifted_mad50:.3} m",
        abs[n - 1]
    );
    // The DTM was made from these ground points (0.5 m cells). Figures: docs/navigation.md.
    assert!(outside < n / 10, "{outside} of {} outside", n + outside);
    assert!(median.abs() < 0.02, "bias {median}");
    // This tile is gentle terrain: a one-pixel slip of the grid raises the median |residual|
    // from 12 to 21 mm, so the bar sits between them (and the slipped grid must fail it).
    const BAR: f64 = 0.015;
    assert!(mad50 < BAR, "median |residual| {mad50}");
    assert!(p95 < 0.25, "p95 {p95}");
    assert!(
        shifted_mad50 > BAR,
        "a one-pixel slip must fail the bar: {shifted_mad50} against {mad50}"
    );
}

/// Writes a GeoTIFF DEM in UTM 36S (EPSG:32736) around the bundled sample's flight line: a
/// plane `h = −0.5 + 0.01 (x − x0)` on 1 m pixels, with one nodata pixel far from the line.
fn write_utm36s_dem(path: &std::path::Path) -> (f64, f64) {
    let (x0, y0) = (357_676.0, 7_235_440.0); // top-left corner
    let mut first = true;
    common::write_utm36s_dem(path, (x0, y0), (40, 40), |x, _| {
        if std::mem::take(&mut first) {
            -9999.0
        } else {
            (-0.5 + 0.01 * (x - x0)) as f32
        }
    });
    (x0, y0)
}

/// Replays the bundled sample with the embedded configuration plus `keys` in its
/// `[georeference]` table (the file written into `dir`); the process output and the output folder.
fn replay_with_georeference_keys(
    dir: &std::path::Path,
    keys: &str,
) -> (std::process::Output, std::path::PathBuf) {
    replay_with_config(dir, |c| {
        c.replace(
            "on_missing = \"drop\"",
            &format!("on_missing = \"drop\"\n{keys}"),
        )
    })
}

/// Replays the bundled sample with the embedded configuration as `edit` changes it (the file
/// written into `dir`); the process output and the output folder.
fn replay_with_config(
    dir: &std::path::Path,
    edit: impl Fn(String) -> String,
) -> (std::process::Output, std::path::PathBuf) {
    let config = edit(
        std::fs::read_to_string(std::path::Path::new(common::ROOT).join("config/replay.toml"))
            .unwrap(),
    );
    let cfg = dir.join("run.toml");
    std::fs::write(&cfg, config).unwrap();
    let out = dir.join("out");
    let o = common::fwlidar(&[
        "replay",
        "replay/two_layer.fwcap",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--no-progress",
        "--set",
        "output.returns=true",
    ]);
    (o, out)
}

/// Replay of the sample with a DEM: `returns.csv` gains `height_above_ground` = z − DEM(x, y),
/// checked against the plane the DEM was written from.
#[test]
fn replay_gives_each_return_its_height_above_the_dem() {
    let dir = tempfile::tempdir().unwrap();
    let dem = dir.path().join("dem36s.tif");
    let (x0, _) = write_utm36s_dem(&dem);
    let (o, out) =
        replay_with_georeference_keys(dir.path(), &format!("dem = \"{}\"", dem.display()));
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let csv = std::fs::read_to_string(out.join("returns.csv")).unwrap();
    let mut lines = csv.lines();
    assert!(
        lines
            .next()
            .unwrap()
            .ends_with(",x,y,z,height_above_ground,backscatter")
    );
    let mut n = 0;
    for l in lines {
        let f: Vec<f64> = l.split(',').skip(8).map(|v| v.parse().unwrap()).collect();
        let ground = -0.5 + 0.01 * (f[0] - x0);
        assert!((f[3] - (f[2] - ground)).abs() < 0.002, "{l}");
        n += 1;
    }
    assert!(n > 3000);
}

/// A DEM in another CRS than the named output CRS is refused when the configuration is loaded,
/// naming the file and both codes; nothing is written.
#[test]
fn a_dem_in_another_crs_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let tif = fixture("dem/ign_lidarhd/DTM_test_data_77055_627760_LA93_IGN69_50CM.tif");
    let (o, out) = replay_with_georeference_keys(
        dir.path(),
        &format!("dem = \"{}\"\noutput_epsg = 32736", tif.display()),
    );
    let err = common::text(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("georeference.dem")
            && err.contains("DTM_test_data")
            && err.contains("EPSG:2154")
            && err.contains("EPSG:32736"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written on a refused DEM");
}

/// Voxel heights above the DEM (`[voxels] height = "above_dem"`), read with xarray: the z
/// coordinate is the height above ground, every return lies in an occupied voxel at its
/// `height_above_ground`, and the ground layer's peak sits at the returns' height above the DEM.
#[test]
fn voxels_above_the_dem_put_the_ground_where_the_dem_says() {
    let dir = tempfile::tempdir().unwrap();
    let dem = dir.path().join("dem36s.tif");
    write_utm36s_dem(&dem);
    let (o, out) = replay_with_config(dir.path(), |c| {
        let c = c
            .replace(
                "on_missing = \"drop\"",
                &format!("on_missing = \"drop\"\ndem = \"{}\"", dem.display()),
            )
            .replace("height = \"absolute\"", "height = \"above_dem\"");
        assert!(c.contains("height = \"above_dem\""));
        c
    });
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let script = r#"
import csv, sys, json, numpy as np, xarray as xr
out = sys.argv[1]
ds = xr.open_zarr(out + "/voxels.zarr", consolidated=False)
assert ds.z.attrs["standard_name"] == "height_above_ground", ds.z.attrs
assert ds.attrs["height"] == "above_dem"
with open(out + "/returns.csv") as f:
    rows = list(csv.DictReader(f))
x = np.array([float(r["x"]) for r in rows]); y = np.array([float(r["y"]) for r in rows])
h = np.array([float(r["height_above_ground"]) for r in rows])
win = ds.sel(x=slice(x.min() - 2, x.max() + 2), y=slice(y.min() - 2, y.max() + 2)).load()
v = ds.attrs["voxel_size_m"]
xi = np.floor((x - float(win.x[0]) + v[0] / 2) / v[0]).astype(int)
yi = np.floor((y - float(win.y[0]) + v[1] / 2) / v[1]).astype(int)
zi = np.floor((h - float(win.z[0]) + v[2] / 2) / v[2]).astype(int)
n = win.sample_count.values
ok = (zi >= 0) & (zi < n.shape[0])
assert np.all(n[zi[ok], yi[ok], xi[ok]] > 0), "a return in an empty voxel"
s = win.intensity_sum.values.sum(axis=(1, 2)) / np.maximum(n.sum(axis=(1, 2)), 1)
z = win.z.values
peak = z[z < 7.5][np.argmax(s[z < 7.5])]
ground = np.median(h[h < 7.5])
assert abs(peak - ground) < 0.5, (peak, ground)
print(json.dumps({"peak": float(peak), "ground_returns": float(ground)}))
"#;
    let o = std::process::Command::new(common::python())
        .args(["-c", script])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}{}",
        common::text(&o.stdout),
        common::text(&o.stderr)
    );
}
