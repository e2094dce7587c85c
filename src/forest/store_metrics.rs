//! Forest structure rasters recomputed from a voxel store after the flight (`fwlidar metrics
//! STORE --out DIR`): the pseudo-waveform of a raster cell is its column of voxels.
//!
//! **What a voxel holds** (`crate::voxel::tile`): the sum of the intensity deposited by every
//! return bin that fell in it (the processed signal — denoised, deconvolved where the chain
//! deconvolves — times the calibration factor when a `calibrate` stage ran; integers of the
//! grid's `intensity_quantum`), the number of bins, their maximum, and the number of pulses whose
//! beam passed through it. Level `k` spans heights `z_bottom_m + k·dz` to `z_bottom_m +
//! (k+1)·dz` (ellipsoidal heights, or heights above the DEM in an `above_dem` store).
//!
//! **The profile of a cell.** The columns whose centres fall in a cell (default: one voxel
//! column; `cell_m` aggregates) are summed level by level, from the highest level that received
//! a bin down to the lowest, and divided by the cell's pulses (the sum over its columns of the
//! most pulses any voxel of the column saw): the mean energy per pulse at each height, in the
//! store's intensity units. Levels inside that span that received no bin are 0.
//!
//! **Metrics.** The profile is handed to the per-pulse computer
//! ([`MetricsComputer`](super::pulse_metrics::MetricsComputer)) as a waveform sampled every
//! `dz / (c/2)` ns, top first, without geometry (so a nadir view: zenith 0 in PAI, 1 m of height
//! per m of range), with the settings of the store's own `metrics` stage when its recorded
//! configuration has one (ρv/ρg, G, Ω, thresholds, PAVD and FHD bins), GEDI's defaults
//! otherwise. What differs from a pulse:
//!
//! - noise: the median and 1.4826 × MAD of the profile (the levels a cell's bins reached
//!   include the pulses' noise-only gate ahead of and after the echoes);
//! - smoothing: `smoothing_ns` (default [`DEFAULT_SMOOTHING_NS`], one 0.15 m level: the deposited
//!   signal was already denoised and, in the default chain, deconvolved, so the outgoing pulse's
//!   σ that the per-pulse metrics smooth with would blur it twice);
//! - the ground is the lowest mode of the cell's profile, never a DEM (in an `above_dem` store
//!   the levels are already heights above the DEM, and `ground_z` is the lowest mode's height
//!   above it);
//! - the canopy height (`canopy_height`, CHM) is RH100, as in the run's rasters.
//!
//! Products (`crate::forest::products::write_rasters`, the same COG + VRT writer as a run):
//! `chm.vrt` (one band, `canopy_height`, per `cell_m` cell) and `metrics.vrt` (per
//! `profile_cell_m` cell: `rh25`, `rh50`, `rh75`, `rh98`, `rh100`, `cover`, `pai`, `fhd`,
//! `ground_sigma_m`, `energy_lowest_m`, `ground_z`, `pulse_density`). Raster tiles are 512 × 512
//! cells.
//!
//! Tiles of the store are read one at a time, in order; a cell's profile is kept only until
//! every store tile that overlaps it has been read, so memory follows the cells that straddle
//! the tiles being read, not the store.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};

use super::pulse_metrics::{MAX_METRIC_SAMPLES, MetricsComputer, MetricsConfig, WaveformInput};
use crate::core::units::HALF_C_M_PER_NS;
use crate::forest::products::{PROFILE_BANDS, profile_bands, profile_values, write_rasters};
use crate::geo::crs::epsg_of;
use crate::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
use crate::raster::{CellGrid, RasterError};
use crate::voxel::grid::{Grid, Placer};
use crate::voxel::tile::TileData;
use crate::voxel::zarr::{StoreError, ZarrStore};

/// Default smoothing of a cell's profile, ns of two-way time (1 ns ≈ 0.15 m of height).
pub const DEFAULT_SMOOTHING_NS: f64 = 1.0;

/// Default least noise σ of a profile, fraction of its peak level (with GEDI's thresholds of 3
/// and 6 σ: the signal starts at 3 % of the peak, modes count from 6 %).
pub const DEFAULT_NOISE_FLOOR: f64 = 0.01;

/// Cells per side of a raster tile.
pub const RASTER_TILE_CELLS: usize = 512;

/// The bands of `metrics.vrt` after the replay's ([`PROFILE_BANDS`]), in order (the pulse
/// density is the last).
pub const STORE_EXTRA_BANDS: [(&str, &str); 2] = [("ground_z", "m"), ("pulse_density", "1/m2")];

/// Number of bands (and cell grids) of `metrics.vrt`.
const STORE_BAND_COUNT: usize = PROFILE_BANDS.len() + STORE_EXTRA_BANDS.len();

/// Errors of `fwlidar metrics`; each names the store or the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreMetricsError {
    /// The store cannot be opened or a tile cannot be read.
    #[error("voxel store {path}: {source}")]
    Store {
        /// The store given.
        path: String,
        /// What went wrong (names the file).
        source: StoreError,
    },
    /// The store is readable but cannot give rasters (no projected CRS, nothing in it).
    #[error("voxel store {path}: {what}")]
    Unusable {
        /// The store given.
        path: String,
        /// Why.
        what: String,
    },
    /// An option is out of range.
    #[error("{option}: {what}")]
    Option {
        /// The option, as on the command line.
        option: &'static str,
        /// What is wrong.
        what: String,
    },
    /// Writing a raster failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
}

/// Settings of [`compute_store_metrics`].
#[derive(Clone, Debug, PartialEq)]
pub struct StoreMetricsOptions {
    /// Cell of the canopy height model, m; default the voxel column (the grid's x size).
    pub cell_m: Option<f64>,
    /// Cell of `metrics.vrt`, m; default `cell_m`.
    pub profile_cell_m: Option<f64>,
    /// σ of the Gaussian smoothing of each profile, ns; default [`DEFAULT_SMOOTHING_NS`].
    pub smoothing_ns: f64,
    /// Cells with fewer pulses are left nodata. Default 1.
    pub min_pulses: u64,
    /// Least noise σ of a profile, as a fraction of its peak (the deposited signal is denoised,
    /// so most levels are exactly 0 and the MAD is 0). Default [`DEFAULT_NOISE_FLOOR`].
    pub noise_floor: f64,
}

impl Default for StoreMetricsOptions {
    fn default() -> Self {
        StoreMetricsOptions {
            cell_m: None,
            profile_cell_m: None,
            smoothing_ns: DEFAULT_SMOOTHING_NS,
            min_pulses: 1,
            noise_floor: DEFAULT_NOISE_FLOOR,
        }
    }
}

/// `metrics.json` of a store's rasters: the report, the store it came from and the seconds it
/// took, its keys in sorted order (`fwlidar metrics` and a campaign's mosaic write it).
pub fn metrics_json(report: &StoreMetricsReport, store: &Path, seconds: f64) -> serde_json::Value {
    #[derive(serde::Serialize)]
    struct File<'a> {
        #[serde(flatten)]
        report: &'a StoreMetricsReport,
        store: String,
        seconds: f64,
    }
    serde_json::to_value(File {
        report,
        store: store.display().to_string(),
        seconds,
    })
    .unwrap_or_default()
}

/// What a computation did (printed by the command, `metrics.json`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct StoreMetricsReport {
    /// EPSG code of the rasters.
    pub epsg: u32,
    /// Intensity units of the store.
    pub intensity_units: String,
    /// Where the metrics settings came from (`store configuration` or `defaults`).
    pub settings_from: String,
    /// CHM cell and profile cell, m.
    pub cell_m: f64,
    /// Profile cell, m.
    pub profile_cell_m: f64,
    /// Smoothing σ, ns.
    pub smoothing_ns: f64,
    /// Least noise σ, fraction of each profile's peak.
    pub noise_floor: f64,
    /// Store tiles read.
    pub tiles_read: u64,
    /// Voxel columns with at least one bin.
    pub columns: u64,
    /// Cells measured per product, and how many got metrics (`[chm, profile]`).
    pub cells: [u64; 2],
    /// Cells with metrics per product.
    pub cells_ok: [u64; 2],
    /// Cells without metrics, by status name (both products).
    pub cells_without: BTreeMap<String, u64>,
    /// Cells below `min_pulses`.
    pub cells_few_pulses: u64,
    /// Raster tiles written (`[chm, metrics]`).
    pub raster_tiles: [usize; 2],
    /// Most cell profiles held at once.
    pub peak_pending_cells: usize,
    /// Seconds reading and decompressing store tiles.
    pub read_s: f64,
    /// Seconds accumulating and measuring the profiles.
    pub measure_s: f64,
    /// Seconds writing the rasters.
    pub write_s: f64,
}

/// The accumulated profile of one cell: per height chunk the energy sums (quanta) and the bins
/// per level; and the pulses.
#[derive(Debug, Default)]
struct CellAcc {
    chunks: BTreeMap<u32, (Vec<i64>, Vec<u32>)>,
    pulses: u64,
}

/// The cells of one product being accumulated.
struct Product {
    cell: f64,
    pending: HashMap<(i64, i64), CellAcc>,
    remaining: HashMap<(i64, i64), u32>,
    peak: usize,
}

impl Product {
    fn new(cell: f64) -> Product {
        Product {
            cell,
            pending: HashMap::new(),
            remaining: HashMap::new(),
            peak: 0,
        }
    }

    fn key(&self, x: f64, y: f64) -> (i64, i64) {
        (
            (x / self.cell).floor() as i64,
            (y / self.cell).floor() as i64,
        )
    }

    /// The cells whose box meets the box `[x0, x1) × [y0, y1)`.
    /// Store tiles the cell `key` waits for: those of `unread` that overlap it, and the one
    /// being read.
    fn tiles_over(&self, key: (i64, i64), grid: &Grid, unread: &HashSet<[i64; 2]>) -> u32 {
        let (cx, cy) = key;
        let (x0, y0) = (cx as f64 * self.cell, cy as f64 * self.cell);
        let [sx, sy] = grid.tile_m();
        let tx0 = ((x0 - grid.origin_m[0]) / sx).floor() as i64;
        let ty0 = ((y0 - grid.origin_m[1]) / sy).floor() as i64;
        let tx1 = ((x0 + self.cell - grid.origin_m[0]) / sx).ceil() as i64;
        let ty1 = ((y0 + self.cell - grid.origin_m[1]) / sy).ceil() as i64;
        let mut count = 1u32;
        for ty in ty0..ty1 {
            for tx in tx0..tx1 {
                if unread.contains(&[tx, ty]) {
                    count += 1;
                }
            }
        }
        count
    }

    /// Counts one tile fewer for every cell over the box `x0, y0, x1, y1` (a tile just read);
    /// returns the cells that wait for no more, taken out, in row order.
    fn finished_over(&mut self, x0: f64, y0: f64, x1: f64, y1: f64) -> Vec<((i64, i64), CellAcc)> {
        let (lo, hi) = self.cells_over(x0, y0, x1, y1);
        let mut done = Vec::new();
        for cy in lo[1]..=hi[1] {
            for cx in lo[0]..=hi[0] {
                let key = (cx, cy);
                let Some(r) = self.remaining.get_mut(&key) else {
                    continue;
                };
                *r = r.saturating_sub(1);
                if *r == 0 {
                    self.remaining.remove(&key);
                    if let Some(acc) = self.pending.remove(&key) {
                        done.push((key, acc));
                    }
                }
            }
        }
        done
    }

    fn cells_over(&self, x0: f64, y0: f64, x1: f64, y1: f64) -> ([i64; 2], [i64; 2]) {
        let (a, b) = self.key(x0, y0);
        let c = (x1 / self.cell).ceil() as i64 - 1;
        let d = (y1 / self.cell).ceil() as i64 - 1;
        ([a, b], [c, d])
    }
}

/// The store's tile `t` box in CRS metres.
fn tile_box(grid: &Grid, t: [i64; 2]) -> [f64; 4] {
    let [sx, sy] = grid.tile_m();
    let x0 = grid.origin_m[0] + t[0] as f64 * sx;
    let y0 = grid.origin_m[1] + t[1] as f64 * sy;
    [x0, y0, x0 + sx, y0 + sy]
}

/// The `metrics` stage settings recorded in a store's configuration (TOML of the run), if any.
pub fn metrics_config_of(configuration: &str) -> Option<MetricsConfig> {
    let v: toml::Value = toml::from_str(configuration).ok()?;
    let stages = v.get("pipeline")?.get("stages")?.as_array()?;
    let mut t = stages
        .iter()
        .rev()
        .find(|s| s.get("type").and_then(|t| t.as_str()) == Some("metrics"))?
        .as_table()?
        .clone();
    t.remove("type");
    toml::Value::Table(t).try_into().ok()
}

/// Recomputes the forest structure rasters of the store at `store_path` into `out_dir`
/// (created if missing; files of the same names are replaced). `progress(done, total)` is
/// called after each store tile.
pub fn compute_store_metrics(
    store_path: &Path,
    out_dir: &Path,
    opts: &StoreMetricsOptions,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<StoreMetricsReport, StoreMetricsError> {
    check_options(opts)?;
    let (mut store, epsg) = open_store(store_path)?;
    let store_err = |source| StoreMetricsError::Store {
        path: store_path.display().to_string(),
        source,
    };
    let grid = store.grid().clone();
    let info = store.info().clone();
    let cell = opts.cell_m.unwrap_or(grid.voxel_size_m[0]);
    let profile_cell = opts.profile_cell_m.unwrap_or(cell);
    let (config, settings_from) = match metrics_config_of(&info.configuration) {
        Some(c) => (c, "store configuration"),
        None => (MetricsConfig::default(), "defaults"),
    };
    let mut report = StoreMetricsReport {
        epsg,
        intensity_units: info.intensity_units.clone(),
        settings_from: settings_from.into(),
        cell_m: cell,
        profile_cell_m: profile_cell,
        smoothing_ns: opts.smoothing_ns,
        noise_floor: opts.noise_floor,
        ..Default::default()
    };
    let same = (cell - profile_cell).abs() < 1e-9;
    let mut products = vec![Product::new(cell)];
    if !same {
        products.push(Product::new(profile_cell));
    }
    let mut out = Outputs::new(cell, profile_cell);
    let mut measurer = Measurer {
        computer: MetricsComputer::with_capacity(1024),
        config,
        smoothing_ns: opts.smoothing_ns,
        min_pulses: opts.min_pulses.max(1),
        noise_floor: opts.noise_floor,
        grid: grid.clone(),
        samples: Vec::new(),
        sorted: Vec::new(),
    };
    let tiles = store.tiles();
    let total = tiles.len() as u64;
    let mut unread: HashSet<[i64; 2]> = tiles.iter().copied().collect();
    let mut data = TileData::for_grid(&grid);
    let mut clock = std::time::Instant::now();
    let mut lap = |into: &mut f64| {
        let now = std::time::Instant::now();
        *into += (now - clock).as_secs_f64();
        clock = now;
    };
    for (n, &t) in tiles.iter().enumerate() {
        store.read_tile(t, &mut data).map_err(store_err)?;
        lap(&mut report.read_s);
        unread.remove(&t);
        report.tiles_read += 1;
        accumulate_tile(&data, t, &grid, &unread, &mut products, &mut report);
        // Cells this tile overlaps: one tile fewer to wait for; finished ones are measured.
        let [x0, y0, x1, y1] = tile_box(&grid, t);
        for (pi, p) in products.iter_mut().enumerate() {
            p.peak = p.peak.max(p.pending.len());
            for (key, acc) in p.finished_over(x0, y0, x1, y1) {
                let m = measurer.measure(&acc, key, p.cell, &mut report);
                out.place(pi, same, key, p.cell, &m, acc.pulses, &mut report)?;
            }
        }
        lap(&mut report.measure_s);
        progress(n as u64 + 1, total);
    }
    // Whatever is left (cells at the edge of what was read).
    for (pi, p) in products.iter_mut().enumerate() {
        let mut keys: Vec<(i64, i64)> = p.pending.keys().copied().collect();
        keys.sort();
        for key in keys {
            if let Some(acc) = p.pending.remove(&key) {
                let m = measurer.measure(&acc, key, p.cell, &mut report);
                out.place(pi, same, key, p.cell, &m, acc.pulses, &mut report)?;
            }
        }
    }
    report.peak_pending_cells = products.iter().map(|p| p.peak).sum();
    lap(&mut report.measure_s);
    if report.cells_ok[0] == 0 && report.cells_ok[1] == 0 {
        return Err(StoreMetricsError::Unusable {
            path: store_path.display().to_string(),
            what: format!(
                "no cell has metrics ({} tiles, {} columns with bins read); nothing written",
                report.tiles_read, report.columns
            ),
        });
    }
    let bands = profile_bands(&STORE_EXTRA_BANDS);
    report.raster_tiles = {
        let (a, b) = write_rasters(out_dir, epsg, &out.chm, &out.profile, &bands)?;
        [a, b]
    };
    lap(&mut report.write_s);
    Ok(report)
}

/// Opens the voxel store at `store_path` and finds its CRS's EPSG code (a projected CRS with
/// one: the rasters need it). The errors name the store.
fn open_store(store_path: &Path) -> Result<(ZarrStore, u32), StoreMetricsError> {
    let spath = store_path.display().to_string();
    let unusable = |what: String| StoreMetricsError::Unusable {
        path: spath.clone(),
        what,
    };
    if !store_path.join("zarr.json").is_file() {
        return Err(unusable(if store_path.exists() {
            "no zarr.json: not a voxel store (give the voxels.zarr folder a replay wrote)".into()
        } else {
            "does not exist".into()
        }));
    }
    let store = ZarrStore::open(store_path).map_err(|source| StoreMetricsError::Store {
        path: spath.clone(),
        source,
    })?;
    let info = store.info();
    let epsg = info
        .epsg
        .or_else(|| info.crs_wkt.as_deref().and_then(epsg_of))
        .filter(|&c| crate::geo::crs::OutputCrs::from_epsg(c).is_ok())
        .ok_or_else(|| {
            unusable(format!(
                "its CRS (EPSG {:?}) is not a projected CRS with an EPSG code; rasters need one",
                info.epsg
            ))
        })?;
    Ok((store, epsg))
}

/// Adds every column of tile `t` (its bins and pulses, in `data`) that holds a sample to the
/// cells of each product it lies in; a cell seen for the first time learns how many store tiles
/// it waits for (those of `unread` it overlaps, and this one).
fn accumulate_tile(
    data: &TileData,
    t: [i64; 2],
    grid: &Grid,
    unread: &HashSet<[i64; 2]>,
    products: &mut [Product],
    report: &mut StoreMetricsReport,
) {
    let placer = Placer::new(grid);
    let side = grid.tile_columns as i64;
    let levels_per_chunk = grid.chunk_levels() as usize;
    let present = data.present();
    for j in 0..side {
        for i in 0..side {
            let col = (j * side + i) as usize;
            // The column's bins and pulses.
            let mut any = false;
            let mut pulses = 0u32;
            for &kc in &present {
                if let Some(c) = data.chunk(kc as usize).and_then(|c| c.column(col)) {
                    if c.samples.iter().any(|&s| s > 0) {
                        any = true;
                    }
                    pulses = pulses.max(c.pulses.iter().copied().max().unwrap_or(0));
                }
            }
            if !any {
                continue;
            }
            report.columns += 1;
            let [x, y] = placer.column_centre([t[0] * side + i, t[1] * side + j]);
            for p in products.iter_mut() {
                let key = p.key(x, y);
                let acc = p.pending.entry(key).or_default();
                acc.pulses += u64::from(pulses);
                for &kc in &present {
                    let Some(c) = data.chunk(kc as usize).and_then(|c| c.column(col)) else {
                        continue;
                    };
                    if c.samples.iter().all(|&s| s == 0) {
                        continue;
                    }
                    let (e, s) = acc
                        .chunks
                        .entry(kc)
                        .or_insert_with(|| (vec![0; levels_per_chunk], vec![0; levels_per_chunk]));
                    for ((e, s), (q, k)) in e
                        .iter_mut()
                        .zip(s.iter_mut())
                        .zip(c.sum_q.iter().zip(c.samples))
                    {
                        *e = e.saturating_add(*q);
                        *s = s.saturating_add(*k);
                    }
                }
                if !p.remaining.contains_key(&key) {
                    let count = p.tiles_over(key, grid, unread);
                    p.remaining.insert(key, count);
                }
            }
        }
    }
}

/// The cell values in per-raster-tile grids.
struct Outputs {
    chm_cell: f64,
    profile_cell: f64,
    chm: BTreeMap<(i64, i64), CellGrid>,
    profile: BTreeMap<(i64, i64), Vec<CellGrid>>,
}

impl Outputs {
    fn new(chm_cell: f64, profile_cell: f64) -> Outputs {
        Outputs {
            chm_cell,
            profile_cell,
            chm: BTreeMap::new(),
            profile: BTreeMap::new(),
        }
    }

    /// Places the metrics of cell `key` of product `pi` (0: CHM, and the profile when both
    /// cells are the same; 1: profile).
    #[allow(clippy::too_many_arguments)]
    fn place(
        &mut self,
        pi: usize,
        same: bool,
        key: (i64, i64),
        cell: f64,
        m: &Option<WaveformMetrics>,
        pulses: u64,
        report: &mut StoreMetricsReport,
    ) -> Result<(), RasterError> {
        let x = (key.0 as f64 + 0.5) * cell;
        let y = (key.1 as f64 + 0.5) * cell;
        let chm = pi == 0;
        let profile = pi == 1 || same;
        if chm {
            report.cells[0] += 1;
        }
        if profile {
            report.cells[1] += 1;
        }
        let Some(m) = m else {
            return Ok(());
        };
        if chm {
            report.cells_ok[0] += 1;
            let n = RASTER_TILE_CELLS;
            let k = CellGrid::tile_of(x, y, n, self.chm_cell);
            let g = match self.chm.entry(k) {
                std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
                std::collections::btree_map::Entry::Vacant(e) => {
                    e.insert(CellGrid::for_tile(k.0, k.1, n, self.chm_cell)?)
                }
            };
            g.add(x, y, m.rh[100]);
        }
        if profile {
            report.cells_ok[1] += 1;
            let n = RASTER_TILE_CELLS;
            let k = CellGrid::tile_of(x, y, n, self.profile_cell);
            let grids = match self.profile.entry(k) {
                std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
                std::collections::btree_map::Entry::Vacant(e) => {
                    let mut v = Vec::with_capacity(STORE_BAND_COUNT);
                    for _ in 0..STORE_BAND_COUNT {
                        v.push(CellGrid::for_tile(k.0, k.1, n, self.profile_cell)?);
                    }
                    e.insert(v)
                }
            };
            let density = (pulses as f64 / (cell * cell)) as f32;
            let values = profile_values(m)
                .into_iter()
                .chain([m.ground_xyz[2] as f32, density]);
            for (g, v) in grids.iter_mut().zip(values) {
                g.add(x, y, v);
            }
        }
        Ok(())
    }
}

/// Turns a cell's accumulated profile into metrics.
struct Measurer {
    computer: MetricsComputer,
    config: MetricsConfig,
    smoothing_ns: f64,
    min_pulses: u64,
    noise_floor: f64,
    grid: Grid,
    samples: Vec<f32>,
    sorted: Vec<f32>,
}

impl Measurer {
    /// The metrics of one cell, `None` (counted in `report`) when it has none.
    fn measure(
        &mut self,
        acc: &CellAcc,
        key: (i64, i64),
        cell: f64,
        report: &mut StoreMetricsReport,
    ) -> Option<WaveformMetrics> {
        if acc.pulses < self.min_pulses {
            report.cells_few_pulses += 1;
            return None;
        }
        let m = self.profile_metrics(acc, key, cell);
        if m.status != MetricsStatus::Ok {
            *report
                .cells_without
                .entry(m.status.as_str().to_string())
                .or_default() += 1;
            return None;
        }
        Some(m)
    }

    /// Builds the profile (top first, energy per pulse) and measures it.
    fn profile_metrics(&mut self, acc: &CellAcc, key: (i64, i64), cell: f64) -> WaveformMetrics {
        let h = self.grid.chunk_levels() as u64;
        let q = self.grid.intensity_quantum;
        // Lowest and highest level that received a bin.
        let mut lo = u64::MAX;
        let mut hi = 0u64;
        for (&kc, (_, s)) in &acc.chunks {
            for (kk, &n) in s.iter().enumerate() {
                if n > 0 {
                    let k = u64::from(kc) * h + kk as u64;
                    lo = lo.min(k);
                    hi = hi.max(k);
                }
            }
        }
        if lo > hi || (hi - lo + 1) as usize > MAX_METRIC_SAMPLES {
            return WaveformMetrics::default();
        }
        let per_pulse = q / acc.pulses.max(1) as f64;
        self.samples.clear();
        for k in (lo..=hi).rev() {
            let (kc, kk) = ((k / h) as u32, (k % h) as usize);
            let v = acc
                .chunks
                .get(&kc)
                .map(|(e, _)| e[kk] as f64 * per_pulse)
                .unwrap_or(0.0);
            self.samples.push(v as f32);
        }
        let (mean, sd) = robust_noise(&self.samples, &mut self.sorted);
        let peak = self.samples.iter().fold(0.0f32, |a, &b| a.max(b));
        let sd = sd.max(self.noise_floor * (f64::from(peak) - mean).max(0.0));
        let dz = self.grid.voxel_size_m[2];
        let input = WaveformInput {
            pulse_sigma_ns: 0.0,
            samples: &self.samples,
            start_ns: 0.0,
            sample_ns: dz / HALF_C_M_PER_NS,
            noise_mean: mean,
            noise_sd: sd,
            smoothing_ns: self.smoothing_ns,
            geometry: None,
            geographic: false,
        };
        let mut m = self.computer.compute(&self.config, &input);
        if m.status == MetricsStatus::Ok {
            let z_top = self.grid.z_bottom_m + (hi as f64 + 0.5) * dz;
            m.ground_xyz = [
                (key.0 as f64 + 0.5) * cell,
                (key.1 as f64 + 0.5) * cell,
                z_top - m.ground_ns * HALF_C_M_PER_NS,
            ];
        }
        m
    }
}

/// Median and normalised MAD (× 1.4826) of `v`.
fn robust_noise(v: &[f32], sorted: &mut Vec<f32>) -> (f64, f64) {
    sorted.clear();
    sorted.extend_from_slice(v);
    let n = sorted.len();
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let mid = n / 2;
    let (_, med, _) = sorted.select_nth_unstable_by(mid, f32::total_cmp);
    let med = *med;
    for x in sorted.iter_mut() {
        *x = (*x - med).abs();
    }
    let (_, mad, _) = sorted.select_nth_unstable_by(mid, f32::total_cmp);
    (f64::from(med), 1.4826 * f64::from(*mad))
}

/// Checks the options that were given (before the store is read).
pub fn check_options(opts: &StoreMetricsOptions) -> Result<(), StoreMetricsError> {
    for (option, v) in [
        ("--cell", opts.cell_m),
        ("--profile-cell", opts.profile_cell_m),
    ] {
        if let Some(v) = v
            && !(v.is_finite() && v > 0.0 && v <= 10_000.0)
        {
            return Err(StoreMetricsError::Option {
                option,
                what: format!("must be a cell side in (0, 10000] m, got {v}"),
            });
        }
    }
    if !(opts.smoothing_ns.is_finite() && (0.0..=100.0).contains(&opts.smoothing_ns)) {
        return Err(StoreMetricsError::Option {
            option: "--smoothing-ns",
            what: format!("must be in 0..=100 ns, got {}", opts.smoothing_ns),
        });
    }
    if !(opts.noise_floor.is_finite() && (0.0..1.0).contains(&opts.noise_floor)) {
        return Err(StoreMetricsError::Option {
            option: "--noise-floor",
            what: format!("must be in [0, 1), got {}", opts.noise_floor),
        });
    }
    Ok(())
}

/// The files `fwlidar metrics` writes in its output folder (what `--force` replaces).
pub fn product_paths(out_dir: &Path) -> Vec<PathBuf> {
    vec![
        out_dir.join("chm.vrt"),
        out_dir.join("metrics.vrt"),
        out_dir.join("chm"),
        out_dir.join("metrics"),
        out_dir.join("metrics.json"),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_metrics_settings_of_a_recorded_configuration_are_found() {
        let text = "[pipeline]\nworkers = 0\n\n[[pipeline.stages]]\ntype = \"denoise\"\n\n\
                    [[pipeline.stages]]\ntype = \"metrics\"\nrho_ratio = 2.0\nfhd_bin_m = 0.5\n";
        let c = metrics_config_of(text).unwrap();
        assert_eq!(c.rho_ratio, 2.0);
        assert_eq!(c.fhd_bin_m, 0.5);
        assert_eq!(c.profile_bin_m, MetricsConfig::default().profile_bin_m);
        assert!(metrics_config_of("[pipeline]\nstages = []\n").is_none());
        assert!(metrics_config_of("not toml [").is_none());
        // A key this version does not know: the defaults, not a half-read setting.
        assert!(
            metrics_config_of("[[pipeline.stages]]\ntype = \"metrics\"\nnew_key = 1\n").is_none()
        );
    }

    #[test]
    fn robust_noise_ignores_the_echoes() {
        let mut v = vec![1.0f32; 100];
        v[10] = 50.0;
        v[11] = 80.0;
        v[20] = 1.5;
        v[21] = 0.5;
        let (mean, sd) = robust_noise(&v, &mut Vec::new());
        assert_eq!(mean, 1.0);
        assert_eq!(sd, 0.0);
        let alt: Vec<f32> = (0..100)
            .map(|i| if i % 2 == 0 { 1.0 } else { 3.0 })
            .collect();
        let (mean, sd) = robust_noise(&alt, &mut Vec::new());
        assert_eq!(mean, 3.0);
        assert!((sd - 0.0).abs() < 1e-9 || (sd - 2.0 * 1.4826).abs() < 1e-6);
    }

    #[test]
    fn bad_options_are_named() {
        let mut o = StoreMetricsOptions {
            cell_m: Some(0.0),
            ..Default::default()
        };
        assert!(
            check_options(&o)
                .unwrap_err()
                .to_string()
                .starts_with("--cell")
        );
        o.cell_m = None;
        o.noise_floor = 1.5;
        assert!(
            check_options(&o)
                .unwrap_err()
                .to_string()
                .starts_with("--noise-floor")
        );
        assert!(check_options(&StoreMetricsOptions::default()).is_ok());
    }
}
