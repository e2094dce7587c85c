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
//! Tiles are written as the flight leaves them. A tile closes by the voxel tiles' rule
//! ([`CloseRule`]: `[voxels] close_after_s` of GPS time without a pulse and outside the swath, or
//! early when `[voxels] max_open_tiles` are open): its COGs are written (atomically) and the VRTs
//! rewritten (atomically), so a reader sees a valid mosaic of the tiles closed so far during the
//! flight. The rest close at the end. Closing also saves the tile's per-cell accumulators
//! (`rasters/accumulators/<chm|metrics>_<ix>_<iy>.cells`, [`CellGrid::save_cells`]: the cells
//! holding a value); a pulse landing in a closed tile (a later flight line, a late pulse)
//! reopens it and reads them back exactly, so the final rasters are bit-identical to keeping
//! every tile to the end. The accumulators are removed when the run ends.
//!
//! Memory: at most `max_open_tiles` open tiles (one more while a pulse straddles two), each 20
//! bytes per cell and grid — (`raster_tile_m`/`chm_cell_m`)² CHM cells plus 10 ×
//! (`raster_tile_m`/`profile_cell_m`)² profile cells, 22 MB at the defaults — and about 200
//! bytes per tile written (the VRT lists); nothing grows with the number of pulses.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use crate::forest::products::{
    PROFILE_BANDS, PULSE_DENSITY_BAND, ProfileBand, chm_position, chm_raster, cog_options,
    metrics_raster, profile_bands, profile_values, tile_path,
};
use crate::geo::crs::epsg_of;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::Pulse;
use crate::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
use crate::raster::RasterError;
use crate::raster::cog::write_cog;
use crate::raster::grid::CellGrid;
use crate::raster::vrt::{VrtTile, write_vrt};
use crate::sink::SinkReport;
use crate::voxel::tiles::CloseRule;

/// Raster settings (`[output]`: `rasters`, `chm_cell_m`, `profile_cell_m`, `raster_tile_m`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterSettings {
    /// Canopy height model cell, m.
    pub chm_cell_m: f64,
    /// Cell of the other metrics, m.
    pub profile_cell_m: f64,
    /// Tile side, m (a multiple of both cells).
    pub tile_m: f64,
    /// A tile closes (its COGs written, the VRTs rewritten) once no pulse has landed in it for
    /// this long (pulse time, s) and it lies outside the swath: `[voxels] close_after_s`, the
    /// voxel tiles' rule ([`CloseRule`]). `f64::INFINITY`: every tile at the end of the run.
    pub close_after_s: f64,
    /// Tiles open at most; beyond, the one landed in least recently closes early
    /// (`[voxels] max_open_tiles`).
    pub max_open_tiles: usize,
}

/// Where the CRS comes from: stated by the input, or decided by georeferencing during the run.
#[derive(Clone, Debug)]
pub enum RasterCrs {
    /// Known at the start (`EPSG:<code>` or WKT), or `None` (no rasters).
    Known(Option<String>),
    /// Decided at the first position fix.
    Decided(Arc<OnceLock<String>>),
}

/// The metrics rasters' report (`summary.json` → `sinks.metrics_rasters`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct MetricsRastersReport {
    /// Pulses placed in the rasters.
    pub pulses_placed: u64,
    /// Pulses without metrics.
    pub without_metrics: u64,
    /// Pulses without a position or CRS.
    pub without_position_or_crs: u64,
    /// The rasters' EPSG code, once known.
    pub epsg: Option<u32>,
    /// Canopy height model cell, m.
    pub chm_cell_m: f64,
    /// Metrics raster cell, m.
    pub profile_cell_m: f64,
    /// What was written (`rasters/chm.vrt (N tiles)`).
    pub written: Vec<String>,
    /// Tiles close this long after the flight leaves them, s.
    pub close_after_s: f64,
    /// Most tiles open at once.
    pub max_open_tiles: usize,
    /// The tiles' lifecycle.
    pub tiles: RasterTileStats,
}

/// Counters of the raster tiles' lifecycle (`summary.json`: `sinks.metrics_rasters.tiles`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RasterTileStats {
    /// Tiles opened in memory (a tile holds its CHM and profile grids), reopenings included.
    pub opened: u64,
    /// Tiles closed while pulses were still coming: their COGs written and the VRTs rewritten
    /// then.
    pub closed_during_run: u64,
    /// Of those, closed because `max_open_tiles` were open.
    pub closed_early: u64,
    /// Tiles closed when the run ended.
    pub closed_at_end: u64,
    /// Tiles opened again after closing (a later flight line, or a late pulse), their
    /// accumulators read back from `rasters/accumulators/`.
    pub reopened: u64,
    /// Most tiles open at once.
    pub peak_open: usize,
    /// Memory of one open tile's grids, bytes (20 per cell: CHM cells + 10 × profile cells).
    pub tile_bytes: usize,
    /// VRT mosaics written (each rewrite counts).
    pub vrt_writes: u64,
    /// Accumulator files written for closed tiles, bytes in all.
    pub accumulator_bytes: u64,
    /// Time spent closing tiles (COGs, VRTs, accumulators) and reading accumulators back,
    /// seconds (the lifecycle's cost; placing the pulses is not in it).
    pub io_s: f64,
}

/// An open tile: its grids (made at the first pulse of each product) and when a pulse last
/// landed in it.
struct OpenTile {
    chm: Option<CellGrid>,
    profile: Option<Vec<CellGrid>>,
    /// Pulse time of the latest pulse placed, GPS seconds.
    last_s: f64,
    /// The latest pulse (the sink's count) placed.
    last_pulse: u64,
}

/// Writes the metrics rasters.
pub struct MetricsRastersSink {
    dir: PathBuf,
    settings: RasterSettings,
    crs: RasterCrs,
    epsg: Option<u32>,
    /// Open tiles by number ([`CellGrid::tile_of`]).
    open: HashMap<(i64, i64), OpenTile>,
    rule: CloseRule,
    /// The tiles closed so far (their COGs on disk, listed by the VRTs), per product.
    chm_written: BTreeMap<(i64, i64), VrtTile>,
    metrics_written: BTreeMap<(i64, i64), VrtTile>,
    /// The VRT of the product lists tiles not yet in the file.
    chm_vrt_stale: bool,
    metrics_vrt_stale: bool,
    /// `rasters/` and its subfolders are made (and stale accumulators removed).
    dirs_ready: bool,
    bands: Vec<ProfileBand>,
    stats: RasterTileStats,
    placed: u64,
    without_metrics: u64,
    without_position: u64,
    written: Vec<String>,
    /// Reused: the tiles to close, the bytes of an accumulator file.
    idle: Vec<(i64, i64)>,
    buf: Vec<u8>,
}

impl MetricsRastersSink {
    /// Rasters into `out_dir/rasters` (created when the first tile closes).
    pub fn new(out_dir: &Path, settings: RasterSettings, crs: RasterCrs) -> Self {
        let mut bands = profile_bands(&[]);
        bands.push(PULSE_DENSITY_BAND);
        let cells = |c: f64| (settings.tile_m / c).round().max(1.0) as usize;
        let tile_bytes = 20
            * (cells(settings.chm_cell_m).pow(2)
                + PROFILE_BANDS.len() * cells(settings.profile_cell_m).pow(2));
        MetricsRastersSink {
            dir: out_dir.join("rasters"),
            settings,
            crs,
            epsg: None,
            open: HashMap::new(),
            rule: CloseRule::new(settings.close_after_s),
            chm_written: BTreeMap::new(),
            metrics_written: BTreeMap::new(),
            chm_vrt_stale: false,
            metrics_vrt_stale: false,
            dirs_ready: false,
            bands,
            stats: RasterTileStats {
                tile_bytes,
                ..RasterTileStats::default()
            },
            placed: 0,
            without_metrics: 0,
            without_position: 0,
            written: Vec::new(),
            idle: Vec::new(),
            buf: Vec::new(),
        }
    }

    /// The lifecycle's counters so far.
    pub fn tile_stats(&self) -> &RasterTileStats {
        &self.stats
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

    fn place(&mut self, m: &WaveformMetrics, now_s: f64) -> Result<(), RasterError> {
        let [x, y, _] = m.ground_xyz;
        let s = self.settings;
        let n = self.cells(s.chm_cell_m);
        // The canopy height where the beam met the canopy top (off nadir, `height × tan θ` from
        // the ground point: the angular rectification); the profiles at the ground point.
        let [cx, cy] = chm_position(m);
        let key = CellGrid::tile_of(cx, cy, n, s.chm_cell_m);
        let t = self.open_tile(key, now_s)?;
        let g = match &mut t.chm {
            Some(g) => g,
            None => t
                .chm
                .insert(CellGrid::for_tile(key.0, key.1, n, s.chm_cell_m)?),
        };
        g.add(cx, cy, m.canopy_height);
        let n = self.cells(s.profile_cell_m);
        let key = CellGrid::tile_of(x, y, n, s.profile_cell_m);
        let t = self.open_tile(key, now_s)?;
        let grids = match &mut t.profile {
            Some(g) => g,
            None => {
                let mut grids = Vec::with_capacity(PROFILE_BANDS.len());
                for _ in 0..PROFILE_BANDS.len() {
                    grids.push(CellGrid::for_tile(key.0, key.1, n, s.profile_cell_m)?);
                }
                t.profile.insert(grids)
            }
        };
        for (g, v) in grids.iter_mut().zip(profile_values(m)) {
            g.add(x, y, v);
        }
        self.placed += 1;
        Ok(())
    }

    /// The open tile `key`, noting the pulse (`self.placed`, at `now_s`) in it; opening it
    /// (closing the tile landed in least recently when `max_open_tiles` are open) and reading
    /// back what it held when it closed before.
    fn open_tile(&mut self, key: (i64, i64), now_s: f64) -> Result<&mut OpenTile, RasterError> {
        self.rule.touched([key.0, key.1]);
        let pulse = self.placed;
        if !self.open.contains_key(&key) {
            if self.open.len() >= self.settings.max_open_tiles.max(1) {
                // Not a tile this pulse has landed in (the bound gives way by one then).
                let oldest = self
                    .open
                    .iter()
                    .filter(|(_, t)| t.last_pulse < pulse)
                    .min_by(|a, b| a.1.last_s.total_cmp(&b.1.last_s).then(a.0.cmp(b.0)))
                    .map(|(k, _)| *k);
                if let Some(k) = oldest {
                    self.close_tile(k, true)?;
                    self.stats.closed_early += 1;
                    self.stats.closed_during_run += 1;
                    self.write_vrts()?;
                }
            }
            let mut t = OpenTile {
                chm: None,
                profile: None,
                last_s: now_s,
                last_pulse: pulse,
            };
            let (chm, metrics) = (
                self.chm_written.contains_key(&key),
                self.metrics_written.contains_key(&key),
            );
            let started = std::time::Instant::now();
            if chm || metrics {
                self.stats.reopened += 1;
            }
            if chm {
                let n = self.cells(self.settings.chm_cell_m);
                let mut g = CellGrid::for_tile(key.0, key.1, n, self.settings.chm_cell_m)?;
                let path = self.accumulators(key, "chm");
                let bytes = std::fs::read(&path).map_err(|e| RasterError::io(&path, e))?;
                g.load_cells(&bytes, &path)?;
                t.chm = Some(g);
            }
            if metrics {
                let n = self.cells(self.settings.profile_cell_m);
                let path = self.accumulators(key, "metrics");
                let bytes = std::fs::read(&path).map_err(|e| RasterError::io(&path, e))?;
                let mut rest = bytes.as_slice();
                let mut grids = Vec::with_capacity(PROFILE_BANDS.len());
                for _ in 0..PROFILE_BANDS.len() {
                    let mut g = CellGrid::for_tile(key.0, key.1, n, self.settings.profile_cell_m)?;
                    rest = g.load_cells(rest, &path)?;
                    grids.push(g);
                }
                t.profile = Some(grids);
            }
            self.stats.io_s += started.elapsed().as_secs_f64();
            self.open.insert(key, t);
            self.stats.opened += 1;
            self.stats.peak_open = self.stats.peak_open.max(self.open.len());
        }
        let t = self
            .open
            .get_mut(&key)
            .ok_or_else(|| RasterError::invalid(&self.dir, "an open tile went missing"))?;
        t.last_s = now_s;
        t.last_pulse = pulse;
        Ok(t)
    }

    /// The accumulator file of tile `key` of `product` (`chm` or `metrics`).
    fn accumulators(&self, key: (i64, i64), product: &str) -> PathBuf {
        self.dir
            .join("accumulators")
            .join(format!("{product}_{}_{}.cells", key.0, key.1))
    }

    /// Makes `rasters/chm`, `rasters/metrics` and an empty `rasters/accumulators` (those of an
    /// earlier run in the same folder are not this run's).
    fn ready_dirs(&mut self) -> Result<(), RasterError> {
        if self.dirs_ready {
            return Ok(());
        }
        let acc = self.dir.join("accumulators");
        if acc.exists() {
            std::fs::remove_dir_all(&acc).map_err(|e| RasterError::io(&acc, e))?;
        }
        for d in [self.dir.join("chm"), self.dir.join("metrics"), acc] {
            std::fs::create_dir_all(&d).map_err(|e| RasterError::io(&d, e))?;
        }
        self.dirs_ready = true;
        Ok(())
    }

    /// Writes the COGs of tile `key` and frees it; with `keep`, also its accumulators, for the
    /// tile to reopen exactly (not at the end of the run). The VRTs are rewritten by
    /// [`Self::write_vrts`].
    fn close_tile(&mut self, key: (i64, i64), keep: bool) -> Result<(), RasterError> {
        let Some(t) = self.open.remove(&key) else {
            return Ok(());
        };
        let Some(epsg) = self.crs_epsg() else {
            return Ok(());
        };
        let started = std::time::Instant::now();
        self.ready_dirs()?;
        if let Some(g) = &t.chm {
            let r = chm_raster(g, epsg);
            let path = tile_path(&self.dir, "chm", key);
            write_cog(&path, &r, &cog_options())?;
            self.chm_written.insert(key, VrtTile::of(&path, &r));
            self.chm_vrt_stale = true;
            if keep {
                self.buf.clear();
                g.save_cells(&mut self.buf);
                self.save_accumulators(key, "chm")?;
            }
        }
        if let Some(grids) = &t.profile {
            let vrt = self.dir.join("metrics.vrt");
            let r = metrics_raster(grids, &self.bands, epsg, &vrt)?;
            let path = tile_path(&self.dir, "metrics", key);
            write_cog(&path, &r, &cog_options())?;
            self.metrics_written.insert(key, VrtTile::of(&path, &r));
            self.metrics_vrt_stale = true;
            if keep {
                self.buf.clear();
                for g in grids {
                    g.save_cells(&mut self.buf);
                }
                self.save_accumulators(key, "metrics")?;
            }
        }
        self.stats.io_s += started.elapsed().as_secs_f64();
        Ok(())
    }

    /// Writes `self.buf` as the accumulators of tile `key`. Not synced: they serve this run
    /// only (the next run in the folder clears them), so a crash cannot leave one to be misread.
    fn save_accumulators(&mut self, key: (i64, i64), product: &str) -> Result<(), RasterError> {
        let path = self.accumulators(key, product);
        let buf = &self.buf;
        std::fs::write(&path, buf).map_err(|e| RasterError::io(&path, e))?;
        self.stats.accumulator_bytes += buf.len() as u64;
        Ok(())
    }

    /// Rewrites (atomically) the VRTs that lack closed tiles: a reader sees the mosaic of the
    /// tiles closed so far.
    fn write_vrts(&mut self) -> Result<(), RasterError> {
        let started = std::time::Instant::now();
        if self.chm_vrt_stale && !self.chm_written.is_empty() {
            let tiles: Vec<VrtTile> = self.chm_written.values().cloned().collect();
            write_vrt(&self.dir.join("chm.vrt"), &tiles)?;
            self.stats.vrt_writes += 1;
        }
        self.chm_vrt_stale = false;
        if self.metrics_vrt_stale && !self.metrics_written.is_empty() {
            let tiles: Vec<VrtTile> = self.metrics_written.values().cloned().collect();
            write_vrt(&self.dir.join("metrics.vrt"), &tiles)?;
            self.stats.vrt_writes += 1;
        }
        self.metrics_vrt_stale = false;
        self.stats.io_s += started.elapsed().as_secs_f64();
        Ok(())
    }

    /// Closes the tiles the flight has left (the voxel tiles' rule, [`CloseRule`]), given the
    /// time of the pulse about to be placed.
    fn close_idle(&mut self, now_s: f64) -> Result<(), RasterError> {
        let Some(swath) = self.rule.due(now_s) else {
            return Ok(());
        };
        let mut idle = std::mem::take(&mut self.idle);
        idle.clear();
        for (k, t) in &self.open {
            if self.rule.closes(&swath, [k.0, k.1], t.last_s, now_s) {
                idle.push(*k);
            }
        }
        // Deterministic order (the files do not depend on it; the order they appear does).
        idle.sort_unstable();
        let mut result = Ok(());
        for &k in &idle {
            result = self.close_tile(k, true);
            if result.is_err() {
                break;
            }
            self.stats.closed_during_run += 1;
        }
        if result.is_ok() && !idle.is_empty() {
            result = self.write_vrts();
        }
        self.idle = idle;
        result
    }

    /// Closes every open tile, rewrites the VRTs and removes the accumulators (end of the run).
    fn close_all(&mut self) -> Result<(), RasterError> {
        let mut keys: Vec<(i64, i64)> = self.open.keys().copied().collect();
        keys.sort_unstable();
        for k in keys {
            self.close_tile(k, false)?;
            self.stats.closed_at_end += 1;
        }
        self.write_vrts()?;
        let acc = self.dir.join("accumulators");
        if self.dirs_ready && acc.exists() {
            std::fs::remove_dir_all(&acc).map_err(|e| RasterError::io(&acc, e))?;
        }
        if !self.chm_written.is_empty() {
            self.written = vec![
                format!("rasters/chm.vrt ({})", tiles(self.chm_written.len())),
                format!(
                    "rasters/metrics.vrt ({})",
                    tiles(self.metrics_written.len())
                ),
            ];
        }
        Ok(())
    }
}

fn sink_error(e: RasterError) -> SinkError {
    SinkError::Io {
        path: "rasters".into(),
        source: std::io::Error::other(e.to_string()),
    }
}

impl PulseSink for MetricsRastersSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "metrics_rasters"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        if !self.open.is_empty() {
            self.close_idle(p.gps_time).map_err(sink_error)?;
        }
        let Some(m) = p.metrics.as_ref().filter(|m| m.status == MetricsStatus::Ok) else {
            self.without_metrics += 1;
            return Ok(());
        };
        if !m.ground_xyz.iter().all(|v| v.is_finite()) || self.crs_epsg().is_none() {
            self.without_position += 1;
            return Ok(());
        }
        let m = *m;
        self.place(&m, p.gps_time).map_err(sink_error)
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
        self.close_all().map_err(sink_error)
    }

    fn report(&self) -> SinkReport {
        SinkReport::MetricsRasters(MetricsRastersReport {
            pulses_placed: self.placed,
            without_metrics: self.without_metrics,
            without_position_or_crs: self.without_position,
            epsg: self.epsg,
            chm_cell_m: self.settings.chm_cell_m,
            profile_cell_m: self.settings.profile_cell_m,
            written: self.written.clone(),
            close_after_s: self.settings.close_after_s,
            max_open_tiles: self.settings.max_open_tiles,
            tiles: self.stats.clone(),
        })
    }
}

/// `1 tile`, `6 tiles`.
fn tiles(n: usize) -> String {
    if n == 1 {
        "1 tile".into()
    } else {
        format!("{n} tiles")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::forest::products::NODATA;
    use crate::raster::grid::CellStat;

    fn settings(close_after_s: f64, max_open_tiles: usize) -> RasterSettings {
        RasterSettings {
            chm_cell_m: 1.0,
            profile_cell_m: 10.0,
            tile_m: 100.0,
            close_after_s,
            max_open_tiles,
        }
    }

    fn sink(dir: &Path, settings: RasterSettings) -> MetricsRastersSink {
        MetricsRastersSink::new(dir, settings, RasterCrs::Known(Some("EPSG:32618".into())))
    }

    #[test]
    fn pulses_land_in_their_cells_and_tiles_are_written() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = sink(dir.path(), settings(2.0, 64));
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
        // The CHM cell holding the two first pulses keeps the higher.
        let g = sink.open[&(0, 0)].chm.as_ref().unwrap();
        let band = g.band(CellStat::Max, NODATA);
        let (col, row) = g.cell_of(5.5, 5.5).unwrap();
        assert_eq!(band[row * g.width() + col], 14.0);
        // The off-nadir pulse's height stands where its beam met the canopy top.
        let (col, row) = g.cell_of(8.5, 5.5).unwrap();
        assert_eq!(band[row * g.width() + col], 20.0);
        sink.finish().unwrap();
        let r = serde_json::to_value(sink.report()).unwrap();
        assert_eq!(r["pulses_placed"], 4);
        assert_eq!(r["without_metrics"], 1);
        assert_eq!(r["tiles"]["closed_at_end"], 2, "{r}");
        assert_eq!(r["tiles"]["closed_during_run"], 0, "{r}");
        let d = dir.path().join("rasters");
        assert!(d.join("chm/chm_0_0.tif").exists() && d.join("chm/chm_1_0.tif").exists());
        assert!(d.join("metrics/metrics_0_0.tif").exists() && d.join("chm.vrt").exists());
        assert!(!d.join("accumulators").exists(), "removed at the end");
    }

    /// Pulse `i` of a synthetic flight at time `t` with its ground at (x, y): heights and the
    /// other metrics vary from pulse to pulse (some RH50 NaN).
    fn flight_pulse(i: u64, t: f64, x: f64, y: f64) -> Pulse {
        let h = 5.0 + ((i * 7919) % 1000) as f32 / 97.0;
        let mut m = WaveformMetrics {
            status: MetricsStatus::Ok,
            ground_xyz: [x, y, 100.0],
            cover: (i % 10) as f32 / 10.0 + 0.05,
            pai: h / 7.0,
            fhd: (i % 7) as f32 / 3.0,
            ground_sigma_m: 0.3 + (i % 5) as f32 * 0.01,
            energy_lowest_m: 0.1,
            ..Default::default()
        };
        for (k, v) in m.rh.iter_mut().enumerate() {
            *v = h * k as f32 / 100.0;
        }
        m.canopy_height = m.rh[100];
        if i.is_multiple_of(13) {
            m.rh[50] = f32::NAN;
        }
        Pulse {
            pulse_id: i,
            gps_time: t,
            metrics: Some(m),
            ..Default::default()
        }
    }

    /// Two passes at 50 m/s over x ∈ [0, 400) m (4 tiles of 100 m), y ∈ [20, 80) m: east, then
    /// 10 s later back west 3 m further north; the first pass's pulses and the second's.
    fn flight() -> (Vec<Pulse>, Vec<Pulse>) {
        let n = 4000u64;
        let one = (0..n)
            .map(|i| {
                let y = 20.0 + ((i * 37) % 600) as f64 * 0.1;
                flight_pulse(i, i as f64 * 0.002, i as f64 * 0.1, y)
            })
            .collect();
        let two = (0..n)
            .map(|i| {
                let y = 23.0 + ((i * 53) % 570) as f64 * 0.1;
                flight_pulse(n + i, 18.0 + i as f64 * 0.002, 399.95 - i as f64 * 0.1, y)
            })
            .collect();
        (one, two)
    }

    /// Every file under `dir`, by path relative to it, with its bytes.
    fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
        let mut out = BTreeMap::new();
        let mut todo = vec![dir.to_path_buf()];
        while let Some(d) = todo.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    todo.push(p);
                } else {
                    let rel = p.strip_prefix(dir).unwrap().to_path_buf();
                    out.insert(rel, std::fs::read(&p).unwrap());
                }
            }
        }
        out
    }

    #[test]
    fn tiles_close_behind_the_flight_and_the_rasters_equal_keeping_all_to_the_end() {
        let (one, two) = flight();
        // Reference: nothing closes before the end.
        let all = tempfile::tempdir().unwrap();
        let mut kept = sink(all.path(), settings(f64::INFINITY, usize::MAX));
        for p in one.iter().chain(&two) {
            kept.write(p).unwrap();
        }
        assert!(
            !all.path().join("rasters").exists(),
            "nothing written before the end"
        );
        kept.finish().unwrap();
        let s = kept.tile_stats();
        assert_eq!(
            (s.closed_during_run, s.closed_at_end, s.reopened),
            (0, 4, 0)
        );
        let expected = files(&all.path().join("rasters"));
        assert_eq!(
            expected.len(),
            2 * 4 + 2,
            "4 tiles of each product and two VRTs"
        );

        // Closing behind the flight (0.5 s), and closing early by the cap (one tile open).
        for (close_after_s, max_open) in [(0.5, 64), (f64::INFINITY, 1), (0.5, 2)] {
            let dir = tempfile::tempdir().unwrap();
            let mut flown = sink(dir.path(), settings(close_after_s, max_open));
            for p in &one {
                flown.write(p).unwrap();
            }
            let d = dir.path().join("rasters");
            // The tiles the first pass left are on disk, with mosaics of them, before the end.
            let vrt = std::fs::read_to_string(d.join("chm.vrt")).unwrap();
            for ix in 0..3 {
                assert!(d.join(format!("chm/chm_{ix}_0.tif")).exists());
                assert!(d.join(format!("metrics/metrics_{ix}_0.tif")).exists());
                assert!(vrt.contains(&format!("chm_{ix}_0.tif")), "{vrt}");
            }
            assert!(d.join("metrics.vrt").exists());
            assert!(
                flown.open.len() <= max_open,
                "{} tiles open, at most {max_open}",
                flown.open.len()
            );
            let closed = flown.tile_stats().closed_during_run;
            assert!(closed >= 3, "{closed} closed during the first pass");
            for p in &two {
                flown.write(p).unwrap();
            }
            assert!(flown.tile_stats().reopened >= 3, "{:?}", flown.tile_stats());
            flown.finish().unwrap();
            let s = flown.tile_stats().clone();
            assert!(s.peak_open <= max_open, "{s:?}");
            if max_open == 1 {
                assert!(s.closed_early > 0, "{s:?}");
            }
            let got = files(&d);
            assert_eq!(
                got.keys().collect::<Vec<_>>(),
                expected.keys().collect::<Vec<_>>(),
                "{close_after_s} s, {max_open} open"
            );
            for (k, v) in &expected {
                assert!(
                    got[k] == *v,
                    "{} differs ({close_after_s} s, {max_open} open)",
                    k.display()
                );
            }
            let r = serde_json::to_value(flown.report()).unwrap();
            assert_eq!(
                r["tiles"]["closed_during_run"].as_u64().unwrap()
                    + r["tiles"]["closed_at_end"].as_u64().unwrap(),
                r["tiles"]["opened"].as_u64().unwrap(),
                "{r}"
            );
        }
    }
}
