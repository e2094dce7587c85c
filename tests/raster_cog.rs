//! Our Cloud-Optimized GeoTIFFs and VRT mosaics opened by the real readers: GDAL's `gdalinfo`
//! (Debian `gdal-bin`), rasterio (its own GDAL build) and `rio cogeo validate`'s checker
//! (`rio_cogeo.cogeo.cog_validate`), all installed by `tests/run.sh`. A missing reader fails the
//! test, naming that command.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use fwlidar::raster::{
    CellGrid, CellStat, CogOptions, Raster, VrtTile, write_cog, write_vrt, write_vrt_files,
};
use serde_json::Value;

const ND: f32 = -9999.0;

/// A 700 × 500 pattern in UTM 18N with nodata holes (whole blocks and scattered cells).
fn pattern() -> Raster {
    let (w, h) = (700, 500);
    let mut r = Raster::new(w, h, 583_000.0, 4_507_000.0, 0.5, 32618, ND);
    let band = (0..w * h)
        .map(|i| {
            let (c, r) = (i % w, i / w);
            if (100..180).contains(&c) && (300..420).contains(&r) || (c * 7 + r * 13) % 97 == 0 {
                ND
            } else {
                ((c as f32) * 0.037).sin() * 12.0 + (r as f32) * 0.041 + 20.0
            }
        })
        .collect();
    r.push_band("canopy_height", "m", band);
    r
}

/// The first overview as the writer documents it: each side halved (rounding up), the mean of
/// the valid cells of each 2 × 2 block, nodata where none is valid.
fn expected_overview(r: &Raster) -> (usize, usize, Vec<f32>) {
    let (w, h) = (r.width.div_ceil(2), r.height.div_ceil(2));
    let b = &r.bands[0];
    let mut out = vec![ND; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut vals = Vec::new();
            for yy in [2 * y, 2 * y + 1] {
                for xx in [2 * x, 2 * x + 1] {
                    if yy < r.height && xx < r.width && b[yy * r.width + xx] != ND {
                        vals.push(f64::from(b[yy * r.width + xx]));
                    }
                }
            }
            if !vals.is_empty() {
                out[y * w + x] = (vals.iter().sum::<f64>() / vals.len() as f64) as f32;
            }
        }
    }
    (w, h, out)
}

fn write_f32(path: &Path, v: &[f32]) {
    let bytes: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
    std::fs::write(path, bytes).unwrap();
}

/// `gdalinfo -json FILE` (GDAL's own reader); fails the test when gdalinfo is missing or fails.
fn gdalinfo(path: &Path) -> Value {
    common::gdalinfo_json(path)
}

/// The Python with rasterio and rio-cogeo; fails the test naming `tests/run.sh` when it lacks them.
fn rasterio_python() -> PathBuf {
    common::python_with(&["rasterio", "rio_cogeo", "numpy"])
}

const PY_READ: &str = r#"
import json, sys
import numpy as np
import rasterio
path, expected, ovr_expected = sys.argv[1], sys.argv[2], sys.argv[3]
out = {}
with rasterio.open(path) as ds:
    a = ds.read()
    exp = np.fromfile(expected, dtype="<f4").reshape(a.shape)
    out.update(
        driver=ds.driver, dtype=ds.dtypes[0], count=ds.count, width=ds.width, height=ds.height,
        epsg=ds.crs.to_epsg(), transform=list(ds.transform)[:6], nodata=ds.nodata,
        block=list(ds.block_shapes[0]), overviews=ds.overviews(1),
        descriptions=list(ds.descriptions), units=list(ds.units),
        mismatches=int(np.sum(a.view(np.uint32) != exp.view(np.uint32))),
        nodata_cells=int(np.sum(a == ds.nodata)),
    )
if ovr_expected != "-":
    with rasterio.open(path, OVERVIEW_LEVEL=0) as o:
        b = o.read(1)
        e = np.fromfile(ovr_expected, dtype="<f4").reshape(b.shape)
        out["ovr_shape"] = list(b.shape)
        out["ovr_mismatches"] = int(np.sum(b.view(np.uint32) != e.view(np.uint32)))
    from rio_cogeo.cogeo import cog_validate
    valid, errors, warnings = cog_validate(path)
    out["cog_valid"], out["cog_errors"], out["cog_warnings"] = valid, errors, warnings
print(json.dumps(out))
"#;

fn py_read(py: &Path, path: &Path, expected: &Path, ovr: Option<&Path>) -> Value {
    let o = Command::new(py)
        .arg("-c")
        .arg(PY_READ)
        .arg(path)
        .arg(expected)
        .arg(ovr.map_or("-".into(), |p| p.display().to_string()))
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "rasterio on {}: {}",
        path.display(),
        common::text(&o.stderr)
    );
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    println!("rasterio {}: {v}", path.display());
    v
}

#[test]
fn cog_opens_in_gdal_and_rasterio_with_the_values_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("chm.tif");
    let r = pattern();
    write_cog(&path, &r, &CogOptions::default()).unwrap();
    let holes = r.bands[0].iter().filter(|&&v| v == ND).count();
    assert!(holes > 9000, "{holes} nodata cells");

    {
        let info = gdalinfo(&path);
        println!(
            "gdalinfo: size {} geoTransform {} IMAGE_STRUCTURE {} band 1 {}",
            info["size"],
            info["geoTransform"],
            info["metadata"]["IMAGE_STRUCTURE"],
            info["bands"][0]
        );
        assert_eq!(info["driverShortName"], "GTiff");
        assert_eq!(info["size"], serde_json::json!([700, 500]));
        let gt: Vec<f64> = serde_json::from_value(info["geoTransform"].clone()).unwrap();
        assert_eq!(gt, [583_000.0, 0.5, 0.0, 4_507_000.0, 0.0, -0.5]);
        let wkt = info["coordinateSystem"]["wkt"].as_str().unwrap();
        assert!(
            wkt.contains("WGS 84 / UTM zone 18N") && wkt.contains("ID[\"EPSG\",32618]"),
            "{wkt}"
        );
        assert_eq!(
            info["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"], "COG",
            "GDAL recognises the COG layout from the ghost header"
        );
        assert_eq!(
            info["metadata"]["IMAGE_STRUCTURE"]["COMPRESSION"],
            "DEFLATE"
        );
        assert_eq!(info["metadata"]["IMAGE_STRUCTURE"]["PREDICTOR"], "3");
        let b = &info["bands"][0];
        assert_eq!(b["type"], "Float32");
        assert_eq!(b["block"], serde_json::json!([256, 256]));
        assert_eq!(b["noDataValue"], -9999.0);
        assert_eq!(b["description"], "canopy_height");
        assert_eq!(b["unit"], "m");
        let ovr = b["overviews"].as_array().unwrap();
        assert_eq!(ovr.len(), 2, "{ovr:?}");
        assert_eq!(ovr[0]["size"], serde_json::json!([350, 250]));
        assert_eq!(ovr[1]["size"], serde_json::json!([175, 125]));
    }

    {
        let py = rasterio_python();
        let exp = dir.path().join("expected.f32");
        write_f32(&exp, &r.bands[0]);
        let (ow, oh, ov) = expected_overview(&r);
        let ovr = dir.path().join("ovr.f32");
        write_f32(&ovr, &ov);
        let v = py_read(&py, &path, &exp, Some(&ovr));
        assert_eq!(v["driver"], "GTiff");
        assert_eq!(v["dtype"], "float32");
        assert_eq!(
            (v["width"].as_u64(), v["height"].as_u64()),
            (Some(700), Some(500))
        );
        assert_eq!(v["epsg"], 32618);
        assert_eq!(v["nodata"], -9999.0);
        assert_eq!(v["block"], serde_json::json!([256, 256]));
        assert_eq!(v["overviews"], serde_json::json!([2, 4]));
        assert_eq!(v["descriptions"], serde_json::json!(["canopy_height"]));
        assert_eq!(v["units"], serde_json::json!(["m"]));
        assert_eq!(v["mismatches"], 0, "every Float32 value bit for bit");
        assert_eq!(v["nodata_cells"], holes as u64);
        assert_eq!(v["ovr_shape"], serde_json::json!([oh, ow]));
        assert_eq!(v["ovr_mismatches"], 0, "the 2× overview as documented");
        assert_eq!(
            v["cog_valid"], true,
            "rio cogeo validate: errors {} warnings {}",
            v["cog_errors"], v["cog_warnings"]
        );
        assert_eq!(v["cog_warnings"], serde_json::json!([]));
    }
}

/// Four tiles made by `CellGrid` (2 × 2 tiles of 300 × 200 cells of 1 m), a VRT over them;
/// the mosaic GDAL and rasterio read equals the tiles.
#[test]
fn vrt_of_four_cellgrid_tiles_mosaics_them() {
    let dir = tempfile::tempdir().unwrap();
    let cells = 250;
    let value = |x: f64, y: f64| ((x * 0.01).sin() * 10.0 + y * 0.002) as f32;
    // Points at cell centres of tiles (ix, iy) ∈ {10, 11} × {-3, -2}, skipping a diagonal band
    // (empty cells: nodata in `max`, 0 in `count`) and twice in some cells (max of the two).
    let mut paths = Vec::new();
    let mut infos = Vec::new();
    let mut expect: Vec<(f64, f64, f32, f32)> = Vec::new(); // (x, y, max, count) per cell
    for (ix, iy) in [(10, -3), (11, -3), (10, -2), (11, -2)] {
        let mut g = CellGrid::for_tile(ix, iy, cells, 1.0).unwrap();
        let (ox, oy) = g.origin();
        for row in 0..cells {
            for col in 0..cells {
                let (x, y) = (ox + col as f64 + 0.5, oy - row as f64 - 0.5);
                if (col + row) % 50 == 7 {
                    expect.push((x, y, ND, 0.0));
                    continue;
                }
                assert!(g.add(x, y, value(x, y)));
                let mut max = value(x, y);
                let mut n = 1.0;
                if col % 3 == 0 {
                    assert!(g.add(x + 0.2, y - 0.2, max + 1.0));
                    max += 1.0;
                    n += 1.0;
                }
                expect.push((x, y, max, n));
            }
        }
        let mut r = g.to_raster(32618, ND, &[CellStat::Max, CellStat::Count]);
        r.band_names[0] = "canopy_height".into();
        r.band_units[0] = "m".into();
        let p = dir.path().join(format!("chm_{ix}_{iy}.tif"));
        write_cog(&p, &r, &CogOptions::default()).unwrap();
        infos.push(VrtTile::of(&p, &r));
        paths.push(p);
    }
    let vrt = dir.path().join("chm.vrt");
    write_vrt_files(&vrt, &paths).unwrap();
    // Reading the tiles back gives the same grid as describing them from the rasters.
    let read: Vec<VrtTile> = paths.iter().map(|p| VrtTile::read(p).unwrap()).collect();
    for (a, b) in read.iter().zip(&infos) {
        assert_eq!(
            (
                a.width,
                a.height,
                a.origin_x,
                a.origin_y,
                a.cell_size,
                a.epsg,
                a.nodata,
                a.bands
            ),
            (
                b.width,
                b.height,
                b.origin_x,
                b.origin_y,
                b.cell_size,
                b.epsg,
                b.nodata,
                b.bands
            )
        );
    }
    let vrt2 = dir.path().join("chm_named.vrt");
    write_vrt(&vrt2, &infos).unwrap();
    let text = std::fs::read_to_string(&vrt2).unwrap();
    assert!(text.contains("<Description>canopy_height</Description>"));
    assert!(
        text.contains("relativeToVRT=\"1\">chm_10_-3.tif<"),
        "{text}"
    );

    // The mosaic's expected bands: origin (2500, −250), 500 × 500 cells.
    let (x0, y0, w, h) = (2500.0, -250.0, 2 * cells, 2 * cells);
    let mut max = vec![ND; w * h];
    let mut count = vec![0f32; w * h];
    for &(x, y, m, n) in &expect {
        let (c, r) = ((x - x0).floor() as usize, (y0 - y).floor() as usize);
        max[r * w + c] = m;
        count[r * w + c] = n;
    }

    // A tile on another grid is refused, naming it.
    let mut off = infos[0].clone();
    off.origin_x += 0.5;
    off.path = "shifted.tif".into();
    let e = write_vrt(&dir.path().join("bad.vrt"), &[infos[1].clone(), off]).unwrap_err();
    assert!(!dir.path().join("bad.vrt").exists());
    assert!(e.to_string().contains("shifted.tif"), "{e}");

    for v in [&vrt, &vrt2] {
        {
            let info = gdalinfo(v);
            assert_eq!(info["driverShortName"], "VRT");
            assert_eq!(info["size"], serde_json::json!([w, h]));
            let gt: Vec<f64> = serde_json::from_value(info["geoTransform"].clone()).unwrap();
            assert_eq!(gt, [x0, 1.0, 0.0, y0, 0.0, -1.0]);
            let wkt = info["coordinateSystem"]["wkt"].as_str().unwrap();
            assert!(wkt.contains("ID[\"EPSG\",32618]"), "{wkt}");
            assert_eq!(info["bands"].as_array().unwrap().len(), 2);
            assert_eq!(info["bands"][0]["noDataValue"], -9999.0);
        }
    }
    {
        let py = rasterio_python();
        let exp = dir.path().join("mosaic.f32");
        let mut both = max.clone();
        both.extend_from_slice(&count);
        write_f32(&exp, &both);
        let v = py_read(&py, &vrt2, &exp, None);
        assert_eq!(v["driver"], "VRT");
        assert_eq!(v["epsg"], 32618);
        assert_eq!(v["count"], 2);
        assert_eq!(
            v["descriptions"],
            serde_json::json!(["canopy_height", "count"])
        );
        assert_eq!(
            v["mismatches"], 0,
            "the mosaic equals the tiles cell for cell"
        );
        assert_eq!(
            v["nodata_cells"],
            max.iter().filter(|&&m| m == ND).count() as u64
        );
    }
}

/// The run's metrics rasters while the flight goes on (`MetricsRastersSink`, issue 20 "rasters
/// as flown"): once the flight has left two tiles, GDAL and rasterio open `chm.vrt` and
/// `metrics.vrt` as a mosaic of those two, with the canopy heights of the pulses that landed
/// there; at the end the mosaic spans all three.
#[test]
fn the_run_s_mosaic_of_the_tiles_closed_so_far_opens_during_the_flight() {
    use fwlidar::pipeline::ports::PulseSink;
    use fwlidar::pulse::Pulse;
    use fwlidar::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
    use fwlidar::sink::metrics_rasters::{MetricsRastersSink, RasterCrs, RasterSettings};

    let dir = tempfile::tempdir().unwrap();
    let mut sink = MetricsRastersSink::new(
        dir.path(),
        RasterSettings {
            chm_cell_m: 1.0,
            profile_cell_m: 10.0,
            tile_m: 100.0,
            close_after_s: 0.5,
            max_open_tiles: 64,
        },
        RasterCrs::Known(Some("EPSG:32618".into())),
    );
    // East at 50 m/s over x ∈ [0, 300) m, y ∈ [10, 90) m, a pulse per 0.1 m; canopy heights
    // vary. The highest in the first two tiles, and the cells they hit.
    let n = 3000u64;
    let mut highest = f32::MIN;
    let mut cells = std::collections::HashSet::new();
    let vrt = dir.path().join("rasters/chm.vrt");
    let mut seen_midflight = false;
    for i in 0..n {
        let (x, y) = (i as f64 * 0.1, 10.0 + ((i * 37) % 800) as f64 * 0.1);
        let h = 3.0 + ((i * 7919) % 1000) as f32 / 50.0;
        let mut m = WaveformMetrics {
            status: MetricsStatus::Ok,
            ground_xyz: [x, y, 50.0],
            ..Default::default()
        };
        m.rh = [h; 101];
        m.canopy_height = h;
        let p = Pulse {
            pulse_id: i,
            gps_time: i as f64 * 0.002,
            metrics: Some(m),
            ..Default::default()
        };
        sink.write(&p).unwrap();
        if x < 200.0 {
            highest = highest.max(h);
            cells.insert((x.floor() as i64, y.floor() as i64));
        }
        // Flying over the third tile, 1.5 s after leaving the second (the rule: 0.5 s idle,
        // outside the swath of the last 0.5 to 1 s).
        if i == 2750 {
            assert_eq!(
                sink.tile_stats().closed_during_run,
                2,
                "{:?}",
                sink.tile_stats()
            );
            seen_midflight = true;
            {
                let info = gdalinfo(&vrt);
                assert_eq!(info["size"], serde_json::json!([200, 100]), "{info}");
                assert_eq!(info["bands"][0]["description"], "canopy_height");
            }
            let metrics = dir.path().join("rasters/metrics.vrt");
            {
                let info = gdalinfo(&metrics);
                assert_eq!(info["size"], serde_json::json!([20, 10]), "{info}");
                let bands = info["bands"].as_array().unwrap();
                assert_eq!(bands.len(), 11);
                assert_eq!(bands[10]["description"], "pulse_density");
            }
            {
                let py = rasterio_python();
                let script = "import sys, json, numpy as np, rasterio\n\
                    with rasterio.open(sys.argv[1]) as ds:\n    \
                    a = ds.read(1)\n    v = a[a != ds.nodata]\n    \
                    print(json.dumps({'max': float(v.max()), 'cells': int(v.size)}))";
                let o = Command::new(py)
                    .args(["-c", script])
                    .arg(&vrt)
                    .output()
                    .unwrap();
                assert!(o.status.success(), "{}", common::text(&o.stderr));
                let v: Value = serde_json::from_slice(&o.stdout).unwrap();
                assert_eq!(v["max"].as_f64().unwrap() as f32, highest, "{v}");
                assert_eq!(v["cells"].as_u64().unwrap() as usize, cells.len(), "{v}");
            }
        }
    }
    assert!(seen_midflight);
    sink.finish().unwrap();
    {
        let info = gdalinfo(&vrt);
        assert_eq!(info["size"], serde_json::json!([300, 100]), "{info}");
    }
    assert!(!dir.path().join("rasters/accumulators").exists());
}
