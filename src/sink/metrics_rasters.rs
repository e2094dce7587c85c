//! Forest structure rasters from the per-pulse metrics (`rasters/` in the output folder):
//!
//! - `rasters/chm.vrt` over `rasters/chm/chm_<ix>_<iy>.tif`: canopy height model, the highest
//!   `canopy_height` (canopy top above the ground) of the pulses whose canopy top falls in each
//!   `chm_cell_m` cell (default 1 m);
//! - `rasters/metrics.vrt` over `rasters/metrics/metrics_<ix>_<iy>.tif`: per `profile_cell_m`
//!   cell (default 10 m) the mean `rh25`, `rh50`, `rh75`, `rh98`, `rh100`, `cover`, `pai`,
//!   `fhd`, `ground_sigma_m`, `energy_lowest_m` and the pulse density (pulses with metrics per
//!   m²), one band each, named.
//!
//! Each tile covers `raster_tile_m` × `raster_tile_m` metres of the plane (tiles of both
//! products line up; a tile file exists only where pulses landed) and is a Cloud-Optimized
//! GeoTIFF (`src/raster/cog.rs`: tiled 256 × 256, DEFLATE level 1 with the floating-point
//! predictor, overviews, CRS, nodata −9999); the VRTs mosaic them for GDAL, QGIS and rasterio.
//!
//! Pulses are placed in the canopy height model where their beam met the canopy top
//! (`pulse_metrics.csv`'s `top_x`, `top_y`: off nadir the top lies `height × tan θ` from the
//! ground point, so this is the angular rectification of the CHM) and in the profile rasters
//! at their ground position (`x`, `y`), in the CRS of their geometry, which must be projected (an EPSG code, stated by the input or decided by
//! georeferencing). Pulses without metrics or geometry are counted, not placed.
//!
//! The tiles are kept in memory (20 bytes per cell and band) and written when the run ends.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use crate::forest::pulse_metrics::{MetricsStatus, WaveformMetrics};
use crate::pulse::Pulse;
use crate::raster::cog::{CogOptions, write_cog};
use crate::raster::grid::{CellGrid, CellStat};
use crate::raster::vrt::{VrtTile, write_vrt};
use crate::raster::{Raster, RasterError};
use crate::sink::{PulseSink, SinkError};

/// Nodata value of the rasters.
pub const NODATA: f32 = -9999.0;

/// The bands of the profile-resolution raster: name, unit and how to read it from a pulse.
pub const PROFILE_BANDS: [(&str, &str); 10] = [
    ("rh25", "m"),
    ("rh50", "m"),
    ("rh75", "m"),
    ("rh98", "m"),
    ("rh100", "m"),
    ("cover", "1"),
    ("pai", "m2/m2"),
    ("fhd", "1"),
    ("ground_sigma_m", "m"),
    ("energy_lowest_m", "1"),
];

/// The values of [`PROFILE_BANDS`] of one pulse's (or one cell's) metrics, in band order.
pub fn profile_values(m: &WaveformMetrics) -> [f32; 10] {
    [
        m.rh[25],
        m.rh[50],
        m.rh[75],
        m.rh[98],
        m.rh[100],
        m.cover,
        m.pai,
        m.fhd,
        m.ground_sigma_m,
        m.energy_lowest_m,
    ]
}

/// Where a pulse's canopy height goes in the canopy height model: its canopy top's x, y
/// (`top_xyz`), or the ground point's when the top has no position.
pub fn chm_position(m: &WaveformMetrics) -> [f64; 2] {
    if m.top_xyz[0].is_finite() && m.top_xyz[1].is_finite() {
        [m.top_xyz[0], m.top_xyz[1]]
    } else {
        [m.ground_xyz[0], m.ground_xyz[1]]
    }
}

/// Raster settings (`[output]`: `rasters`, `chm_cell_m`, `profile_cell_m`, `raster_tile_m`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterSettings {
    /// Canopy height model cell, m.
    pub chm_cell_m: f64,
    /// Cell of the other metrics, m.
    pub profile_cell_m: f64,
    /// Tile side, m (a multiple of both cells).
    pub tile_m: f64,
}

/// Where the CRS comes from: stated by the input, or decided by georeferencing during the run.
#[derive(Clone, Debug)]
pub enum RasterCrs {
    /// Known at the start (`EPSG:<code>` or WKT), or `None` (no rasters).
    Known(Option<String>),
    /// Decided at the first position fix.
    Decided(Arc<OnceLock<String>>),
}

/// The EPSG code of a CRS given as `EPSG:<code>` or as WKT with an EPSG identifier (the last
/// one: the CRS's own, after those of its parts).
pub fn epsg_of(crs: &str) -> Option<u32> {
    let t = crs.trim();
    if let Some(code) = t.strip_prefix("EPSG:") {
        return code.trim().parse().ok();
    }
    let at = t.rfind("\"EPSG\",")?;
    let rest = t[at + 7..].trim_start().trim_start_matches('"');
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

/// Writes the metrics rasters.
pub struct MetricsRastersSink {
    dir: PathBuf,
    settings: RasterSettings,
    crs: RasterCrs,
    epsg: Option<u32>,
    chm: BTreeMap<(i64, i64), CellGrid>,
    profile: BTreeMap<(i64, i64), Vec<CellGrid>>,
    placed: u64,
    without_metrics: u64,
    without_position: u64,
    written: Vec<String>,
}

impl MetricsRastersSink {
    /// Rasters into `out_dir/rasters` (created at the end, when there is something to write).
    pub fn new(out_dir: &Path, settings: RasterSettings, crs: RasterCrs) -> Self {
        MetricsRastersSink {
            dir: out_dir.join("rasters"),
            settings,
            crs,
            epsg: None,
            chm: BTreeMap::new(),
            profile: BTreeMap::new(),
            placed: 0,
            without_metrics: 0,
            without_position: 0,
            written: Vec::new(),
        }
    }

    /// The EPSG code of the pulses' CRS, when it is one we can project with (a code found in a
    /// WKT may be a unit's or a datum's: only a code that names a CRS is taken).
    fn crs_epsg(&mut self) -> Option<u32> {
        if self.epsg.is_none() {
            let code = match &self.crs {
                RasterCrs::Known(Some(c)) => epsg_of(c),
                RasterCrs::Known(None) => None,
                RasterCrs::Decided(cell) => cell.get().and_then(|c| epsg_of(c)),
            };
            self.epsg = code.filter(|&c| crate::geo::crs::OutputCrs::from_epsg(c).is_ok());
        }
        self.epsg
    }

    fn cells(&self, cell: f64) -> usize {
        (self.settings.tile_m / cell).round().max(1.0) as usize
    }

    fn place(&mut self, m: &WaveformMetrics) -> Result<(), RasterError> {
        let [x, y, _] = m.ground_xyz;
        let s = self.settings;
        let n = self.cells(s.chm_cell_m);
        // The canopy height where the beam met the canopy top (off nadir, `height × tan θ` from
        // the ground point: the angular rectification); the profiles at the ground point.
        let [cx, cy] = chm_position(m);
        let key = CellGrid::tile_of(cx, cy, n, s.chm_cell_m);
        let g = match self.chm.entry(key) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(e) => {
                e.insert(CellGrid::for_tile(key.0, key.1, n, s.chm_cell_m)?)
            }
        };
        g.add(cx, cy, m.canopy_height);
        let n = self.cells(s.profile_cell_m);
        let key = CellGrid::tile_of(x, y, n, s.profile_cell_m);
        let grids = match self.profile.entry(key) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(e) => {
                let mut grids = Vec::with_capacity(PROFILE_BANDS.len());
                for _ in 0..PROFILE_BANDS.len() {
                    grids.push(CellGrid::for_tile(key.0, key.1, n, s.profile_cell_m)?);
                }
                e.insert(grids)
            }
        };
        for (g, v) in grids.iter_mut().zip(profile_values(m)) {
            g.add(x, y, v);
        }
        self.placed += 1;
        Ok(())
    }

    fn write_all(&mut self) -> Result<(), RasterError> {
        let Some(epsg) = self.crs_epsg() else {
            return Ok(());
        };
        if self.chm.is_empty() {
            return Ok(());
        }
        let mut bands: Vec<ProfileBand> = PROFILE_BANDS
            .iter()
            .enumerate()
            .map(|(i, &(name, unit))| ProfileBand {
                name,
                unit,
                grid: i,
                stat: CellStat::Mean,
            })
            .collect();
        bands.push(ProfileBand {
            name: "pulse_density",
            unit: "1/m2",
            grid: 0,
            stat: CellStat::Density,
        });
        let (chm, metrics) = write_rasters(&self.dir, epsg, &self.chm, &self.profile, &bands)?;
        self.written = vec![
            format!("rasters/chm.vrt ({chm} tiles)"),
            format!("rasters/metrics.vrt ({metrics} tiles)"),
        ];
        Ok(())
    }
}

/// One band of the profile-resolution raster: its name and unit, which of a tile's
/// [`CellGrid`]s it is read from, and by which statistic.
#[derive(Clone, Copy, Debug)]
pub struct ProfileBand {
    /// Band name (GDAL's description), e.g. `rh98`.
    pub name: &'static str,
    /// Unit, e.g. `m`.
    pub unit: &'static str,
    /// Index of the grid in each tile's `Vec<CellGrid>`.
    pub grid: usize,
    /// The statistic of that grid written.
    pub stat: CellStat,
}

/// Writes the two raster products into `dir` (created if missing): `chm.vrt` over
/// `chm/chm_<ix>_<iy>.tif` (band `canopy_height`, the per-cell maximum of each tile's grid) and
/// `metrics.vrt` over `metrics/metrics_<ix>_<iy>.tif` (one band per [`ProfileBand`]), every
/// tile a COG in EPSG `epsg` with nodata [`NODATA`]. Tiles are keyed by
/// [`CellGrid::tile_of`]. Returns the tiles written (CHM, metrics). Shared by the run's sink
/// and `fwlidar metrics` (`crate::forest::store_metrics`).
pub fn write_rasters(
    dir: &Path,
    epsg: u32,
    chm: &BTreeMap<(i64, i64), CellGrid>,
    profile: &BTreeMap<(i64, i64), Vec<CellGrid>>,
    bands: &[ProfileBand],
) -> Result<(usize, usize), RasterError> {
    let opt = CogOptions {
        deflate_level: 1,
        ..CogOptions::default()
    };
    let io = |e: std::io::Error, p: &Path| RasterError::Io {
        file: p.display().to_string(),
        source: e,
    };
    for sub in ["chm", "metrics"] {
        let d = dir.join(sub);
        std::fs::create_dir_all(&d).map_err(|e| io(e, &d))?;
    }
    let mut chm_tiles = Vec::new();
    for (&(ix, iy), g) in chm {
        let mut r = g.to_raster(epsg, NODATA, &[CellStat::Max]);
        r.band_names[0] = "canopy_height".into();
        r.band_units[0] = "m".into();
        let path = dir.join("chm").join(format!("chm_{ix}_{iy}.tif"));
        write_cog(&path, &r, &opt)?;
        chm_tiles.push(VrtTile::of(&path, &r));
    }
    if !chm_tiles.is_empty() {
        write_vrt(&dir.join("chm.vrt"), &chm_tiles)?;
    }
    let mut tiles = Vec::new();
    for (&(ix, iy), grids) in profile {
        let g0 = &grids[0];
        let (ox, oy) = g0.origin();
        let mut r = Raster::new(
            g0.width(),
            g0.height(),
            ox,
            oy,
            g0.cell_size(),
            epsg,
            NODATA,
        );
        for b in bands {
            let g = grids.get(b.grid).ok_or_else(|| {
                RasterError::invalid(
                    &dir.join("metrics.vrt"),
                    format!(
                        "band {} reads grid {}, the tile has {}",
                        b.name,
                        b.grid,
                        grids.len()
                    ),
                )
            })?;
            r.push_band(b.name, b.unit, g.band(b.stat, NODATA));
        }
        let path = dir.join("metrics").join(format!("metrics_{ix}_{iy}.tif"));
        write_cog(&path, &r, &opt)?;
        tiles.push(VrtTile::of(&path, &r));
    }
    if !tiles.is_empty() {
        write_vrt(&dir.join("metrics.vrt"), &tiles)?;
    }
    Ok((chm_tiles.len(), tiles.len()))
}

fn sink_error(e: RasterError) -> SinkError {
    SinkError::Io {
        path: "rasters".into(),
        source: std::io::Error::other(e.to_string()),
    }
}

impl PulseSink for MetricsRastersSink {
    fn name(&self) -> &'static str {
        "metrics_rasters"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        let Some(m) = p.metrics.as_ref().filter(|m| m.status == MetricsStatus::Ok) else {
            self.without_metrics += 1;
            return Ok(());
        };
        if !m.ground_xyz.iter().all(|v| v.is_finite()) || self.crs_epsg().is_none() {
            self.without_position += 1;
            return Ok(());
        }
        let m = *m;
        self.place(&m).map_err(sink_error)
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        Ok(())
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        if self.epsg.is_none() && self.without_position > 0 {
            tracing::warn!(
                pulses = self.without_position,
                "no metrics rasters: the pulses' CRS has no EPSG code of a CRS (set \
                 [georeference] output_epsg, or the input's CRS); pulse_metrics.csv has them"
            );
        }
        self.write_all().map_err(sink_error)
    }

    fn report(&self) -> serde_json::Value {
        serde_json::json!({
            "pulses_placed": self.placed,
            "without_metrics": self.without_metrics,
            "without_position_or_crs": self.without_position,
            "epsg": self.epsg,
            "chm_cell_m": self.settings.chm_cell_m,
            "profile_cell_m": self.settings.profile_cell_m,
            "written": self.written,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn epsg_from_code_or_wkt() {
        assert_eq!(epsg_of("EPSG:32618"), Some(32618));
        assert_eq!(
            epsg_of(
                r#"PROJCRS["WGS 84 / UTM zone 18N",BASEGEOGCRS["WGS 84",ID["EPSG",4326]],ID["EPSG",32618]]"#
            ),
            Some(32618)
        );
        assert_eq!(
            epsg_of(
                r#"PROJCS["x",GEOGCS["y",AUTHORITY["EPSG","4326"]],AUTHORITY["EPSG","32736"]]"#
            ),
            Some(32736)
        );
        assert_eq!(epsg_of("LOCAL_CS[\"x\"]"), None);
    }

    #[test]
    fn pulses_land_in_their_cells_and_tiles_are_written() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = MetricsRastersSink::new(
            dir.path(),
            RasterSettings {
                chm_cell_m: 1.0,
                profile_cell_m: 10.0,
                tile_m: 100.0,
            },
            RasterCrs::Known(Some("EPSG:32618".into())),
        );
        let mut p = Pulse::default();
        // The last pulse met its canopy top 3 m east of its ground point (off nadir).
        for (i, (x, y, h, dx)) in [
            (5.5, 5.5, 12.0f32, 0.0),
            (5.7, 5.2, 14.0, 0.0),
            (150.0, 20.0, 3.0, 0.0),
            (5.5, 5.5, 20.0, 3.0),
        ]
        .into_iter()
        .enumerate()
        {
            let mut m = WaveformMetrics {
                status: MetricsStatus::Ok,
                ground_xyz: [x, y, 100.0],
                top_xyz: [x + dx, y, 100.0 + f64::from(h)],
                cover: 0.5,
                canopy_height: h,
                ..Default::default()
            };
            m.rh = [h; 101];
            p.pulse_id = i as u64;
            p.metrics = Some(m);
            sink.write(&p).unwrap();
        }
        p.metrics = None;
        sink.write(&p).unwrap();
        sink.finish().unwrap();
        let r = sink.report();
        assert_eq!(r["pulses_placed"], 4);
        assert_eq!(r["without_metrics"], 1);
        let d = dir.path().join("rasters");
        assert!(d.join("chm/chm_0_0.tif").exists() && d.join("chm/chm_1_0.tif").exists());
        assert!(d.join("metrics/metrics_0_0.tif").exists() && d.join("chm.vrt").exists());
        // The CHM cell holding the two first pulses keeps the higher.
        let g = &sink.chm[&(0, 0)];
        let band = g.band(CellStat::Max, NODATA);
        let (col, row) = g.cell_of(5.5, 5.5).unwrap();
        assert_eq!(band[row * g.width() + col], 14.0);
        // The off-nadir pulse's height stands where its beam met the canopy top.
        let (col, row) = g.cell_of(8.5, 5.5).unwrap();
        assert_eq!(band[row * g.width() + col], 20.0);
    }
}
