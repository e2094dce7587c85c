//! The forest products, defined once: the bands of the metrics rasters and their writer (COG
//! tiles under VRT mosaics), and the columns of `pulse_metrics.csv`. The run's sinks
//! (`sink::metrics_rasters`, `sink::pulse_metrics_csv`), `fwlidar metrics` (from a voxel store,
//! [`super::store_metrics`]) and `fwlidar process --metrics` ([`super::table_metrics`]) all write
//! through these.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::core::fixed_text::push_fixed;
use crate::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
use crate::raster::cog::{CogOptions, write_cog};
use crate::raster::grid::{CellGrid, CellStat};
use crate::raster::vrt::{VrtTile, write_vrt};
use crate::raster::{Raster, RasterError};

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

/// The bands of the profile-resolution raster: [`PROFILE_BANDS`] then `extra`, each the mean
/// of its own grid (grid `i` for band `i`).
pub fn profile_bands(extra: &[(&'static str, &'static str)]) -> Vec<ProfileBand> {
    PROFILE_BANDS
        .iter()
        .chain(extra)
        .enumerate()
        .map(|(i, &(name, unit))| ProfileBand {
            name,
            unit,
            grid: i,
            stat: CellStat::Mean,
        })
        .collect()
}

/// The band of the pulse density, pulses per m², counted in the first grid.
pub const PULSE_DENSITY_BAND: ProfileBand = ProfileBand {
    name: "pulse_density",
    unit: "1/m2",
    grid: 0,
    stat: CellStat::Density,
};

/// The COG options of the rasters: DEFLATE level 1 (the run's pace; the predictor does most of
/// the work).
pub fn cog_options() -> CogOptions {
    CogOptions {
        deflate_level: 1,
        ..CogOptions::default()
    }
}

/// `dir/<product>/<product>_<ix>_<iy>.tif`.
pub fn tile_path(dir: &Path, product: &str, key: (i64, i64)) -> PathBuf {
    dir.join(product)
        .join(format!("{product}_{}_{}.tif", key.0, key.1))
}

/// The CHM tile of a grid: band `canopy_height` (m), the per-cell maximum.
pub fn chm_raster(g: &CellGrid, epsg: u32) -> Raster {
    let mut r = g.to_raster(epsg, NODATA, &[CellStat::Max]);
    r.band_names[0] = "canopy_height".into();
    r.band_units[0] = "m".into();
    r
}

/// The metrics tile of a tile's grids: one band per [`ProfileBand`] (`vrt` names errors).
pub fn metrics_raster(
    grids: &[CellGrid],
    bands: &[ProfileBand],
    epsg: u32,
    vrt: &Path,
) -> Result<Raster, RasterError> {
    let g0 = grids
        .first()
        .ok_or_else(|| RasterError::invalid(vrt, "a tile without grids"))?;
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
                vrt,
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
    Ok(r)
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
    let opt = cog_options();
    for sub in ["chm", "metrics"] {
        let d = dir.join(sub);
        std::fs::create_dir_all(&d).map_err(|e| RasterError::io(&d, e))?;
    }
    let mut chm_tiles = Vec::new();
    for (&key, g) in chm {
        let r = chm_raster(g, epsg);
        let path = tile_path(dir, "chm", key);
        write_cog(&path, &r, &opt)?;
        chm_tiles.push(VrtTile::of(&path, &r));
    }
    if !chm_tiles.is_empty() {
        write_vrt(&dir.join("chm.vrt"), &chm_tiles)?;
    }
    let mut tiles = Vec::new();
    let vrt = dir.join("metrics.vrt");
    for (&key, grids) in profile {
        let r = metrics_raster(grids, bands, epsg, &vrt)?;
        let path = tile_path(dir, "metrics", key);
        write_cog(&path, &r, &opt)?;
        tiles.push(VrtTile::of(&path, &r));
    }
    if !tiles.is_empty() {
        write_vrt(&vrt, &tiles)?;
    }
    Ok((chm_tiles.len(), tiles.len()))
}

/// The header line for `profile_bins` PAVD bins of `profile_bin_m` metres.
pub fn header(shot_number: bool, profile_bins: usize, profile_bin_m: f64) -> String {
    use std::fmt::Write as _;
    let mut h = String::from("pulse_id,gps_time");
    if shot_number {
        h.push_str(",shot_number");
    }
    h.push_str(",x,y,z,status,canopy_height");
    for p in 0..=100 {
        let _ = write!(h, ",rh{p}");
    }
    h.push_str(
        ",energy_10_90_ns,modes,crown_thickness_m,energy_total,energy_ground,energy_canopy,\
         cover,pgap,pai,fhd",
    );
    for b in 0..profile_bins {
        let lo = b as f64 * profile_bin_m;
        let _ = write!(h, ",pavd_{}_{}", fmt_m(lo), fmt_m(lo + profile_bin_m));
    }
    h.push_str(
        ",ground_sigma_m,ground_skew,energy_lowest_m,ground_above_dem_m,zenith_deg,noise_mean,\
         noise_sd,smoothing_ns,top_ns,ground_ns,bottom_ns,mode_ns,ground_from,top_x,top_y,top_z",
    );
    h
}

fn fmt_m(v: f64) -> String {
    if v.fract() == 0.0 {
        format!("{}", v as i64)
    } else {
        format!("{v}").replace('.', "p")
    }
}

/// Writes one row of `pulse_metrics.csv` (with its newline) into `l`, cleared first: the
/// columns of [`header`] for `profile_bins` PAVD bins. `gps_time` `None` leaves its cell empty
/// (inputs without time, `fwlidar process`); `shot_number` repeats `pulse_id` in the GEDI
/// column; `above_dem` is `ground_above_dem_m` (NaN: empty).
pub fn format_row(
    l: &mut String,
    pulse_id: u64,
    gps_time: Option<f64>,
    shot_number: bool,
    m: &WaveformMetrics,
    profile_bins: usize,
    above_dem: f32,
) {
    use std::fmt::Write as _;
    l.clear();
    let _ = write!(l, "{pulse_id},");
    if let Some(t) = gps_time {
        push_fixed(l, t, 9);
    }
    if shot_number {
        let _ = write!(l, ",{pulse_id}");
    }
    let xyz = |l: &mut String, p: [f64; 3]| {
        for v in p {
            l.push(',');
            push_fixed(l, v, 3);
        }
    };
    if m.ground_xyz.iter().all(|v| v.is_finite()) {
        xyz(l, m.ground_xyz);
    } else {
        l.push_str(",,,");
    }
    let _ = write!(l, ",{}", m.status.as_str());
    let ok = m.status == MetricsStatus::Ok;
    let f = |l: &mut String, v: f32, digits: usize| {
        l.push(',');
        if ok && v.is_finite() {
            push_fixed(l, f64::from(v), digits);
        }
    };
    f(l, m.canopy_height, 3);
    for v in m.rh {
        f(l, v, 3);
    }
    f(l, m.energy_10_90_ns, 3);
    if ok {
        let _ = write!(l, ",{}", m.modes);
    } else {
        l.push(',');
    }
    f(l, m.crown_thickness_m, 3);
    f(l, m.energy_total, 2);
    f(l, m.energy_ground, 2);
    f(l, m.energy_canopy, 2);
    f(l, m.cover, 5);
    f(l, m.pgap, 5);
    f(l, m.pai, 5);
    f(l, m.fhd, 5);
    for b in 0..profile_bins {
        let v = if b < m.pavd_bins as usize {
            m.pavd[b]
        } else {
            f32::NAN
        };
        f(l, v, 6);
    }
    f(l, m.ground_sigma_m, 4);
    f(l, m.ground_skew, 4);
    f(l, m.energy_lowest_m, 5);
    f(l, above_dem, 4);
    f(l, m.zenith_deg, 3);
    f(l, m.noise_mean, 4);
    f(l, m.noise_sd, 4);
    f(l, m.smoothing_ns, 3);
    for v in [m.top_ns, m.ground_ns, m.bottom_ns, m.mode_ns] {
        l.push(',');
        if ok && v.is_finite() {
            push_fixed(l, v, 3);
        }
    }
    if ok {
        let _ = write!(l, ",{}", m.ground_from.as_str());
    } else {
        l.push(',');
    }
    if ok && m.top_xyz.iter().all(|v| v.is_finite()) {
        xyz(l, m.top_xyz);
    } else {
        l.push_str(",,,");
    }
    l.push('\n');
}
