//! Rasters that GDAL, QGIS and rasterio open: Cloud-Optimized GeoTIFFs ([`write_cog`]), a GDAL
//! VRT mosaic of several of them ([`write_vrt`]), and a per-cell accumulator over a fixed grid
//! ([`CellGrid`]) that turns georeferenced values (x, y, value) into a [`Raster`].
//!
//! Pure Rust (no libgdal): the TIFF encoding is written here against TIFF 6.0, BigTIFF,
//! GeoTIFF 1.1 and the COG layout (see `docs/formats.md`, "Rasters (COG + VRT)", and
//! `docs/architecture.md` for why the `tiff` crate's encoder does not serve).
//!
//! A sink that writes products tile by tile calls, per closed tile:
//! ```no_run
//! use fwlidar::raster::{CellGrid, CellStat, CogOptions, write_cog, write_vrt_files};
//! # fn main() -> Result<(), fwlidar::raster::RasterError> {
//! let mut grid = CellGrid::for_tile(12, -4, 1000, 1.0)?; // 1000 × 1000 cells of 1 m
//! grid.add(12_345.2, -3_210.7, 23.5); // (x, y in CRS units, canopy height in m)
//! let raster = grid.to_raster(32618, -9999.0, &[CellStat::Max, CellStat::Count]);
//! write_cog("chm_12_-4.tif".as_ref(), &raster, &CogOptions::default())?;
//! write_vrt_files("chm.vrt".as_ref(), &["chm_12_-4.tif".into()])?;
//! # Ok(()) }
//! ```

pub mod cog;
pub mod grid;
pub mod vrt;

pub use cog::{CogOptions, Predictor, write_cog};
pub use grid::{CellGrid, CellStat};
pub use vrt::{VrtTile, write_vrt, write_vrt_files};

use std::path::Path;

/// The largest width or height accepted, in cells (2²⁴ = 16 777 216): beyond it a single
/// in-memory raster is not what this module is for (write tiles and a VRT).
pub const MAX_DIMENSION: usize = 1 << 24;

/// Errors writing or describing rasters; every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    /// Creating, writing, syncing or renaming the file failed.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: String,
        /// The operating-system error.
        source: std::io::Error,
    },
    /// The raster's description is not one that can be written.
    #[error("{file}: {what}")]
    Invalid {
        /// The file.
        file: String,
        /// What is wrong, naming the field.
        what: String,
    },
    /// Reading an existing raster (for a VRT) failed.
    #[error("{file}: cannot read as a GeoTIFF: {what}")]
    Read {
        /// The file.
        file: String,
        /// What went wrong.
        what: String,
    },
}

impl RasterError {
    pub(crate) fn invalid(file: &Path, what: impl Into<String>) -> Self {
        RasterError::Invalid {
            file: file.display().to_string(),
            what: what.into(),
        }
    }

    pub(crate) fn io(file: &Path, source: std::io::Error) -> Self {
        RasterError::Io {
            file: file.display().to_string(),
            source,
        }
    }
}

/// A north-up raster of Float32 bands on a square grid, in memory.
///
/// Cell (col, row) covers x ∈ [origin_x + col·cell_size, origin_x + (col+1)·cell_size) and
/// y ∈ [origin_y − (row+1)·cell_size, origin_y − row·cell_size): rows run south (GeoTIFF
/// `PixelIsArea`, GDAL geotransform `[origin_x, cell_size, 0, origin_y, 0, −cell_size]`).
#[derive(Clone, Debug, PartialEq)]
pub struct Raster {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// x of the upper-left corner of cell (0, 0), CRS units (m for a projected CRS).
    pub origin_x: f64,
    /// y of the upper-left corner of cell (0, 0), CRS units.
    pub origin_y: f64,
    /// Cell side, CRS units (m for a projected CRS, degrees for a geographic one).
    pub cell_size: f64,
    /// EPSG code of the CRS (a projected one such as 32618, or a geographic one such as 4326).
    pub epsg: u32,
    /// The value of cells without data (NaN allowed). NaN values in a band are also treated as
    /// missing by the overviews.
    pub nodata: f32,
    /// The bands, each `width × height` values in row-major order (row 0 is the north edge).
    pub bands: Vec<Vec<f32>>,
    /// One name per band (GDAL's band description), e.g. `canopy_height`; may be empty.
    pub band_names: Vec<String>,
    /// One unit per band (GDAL's unit type), e.g. `m`, `1/m2`; may be empty.
    pub band_units: Vec<String>,
}

impl Raster {
    /// A raster with no bands yet ([`Raster::push_band`] adds them).
    pub fn new(
        width: usize,
        height: usize,
        origin_x: f64,
        origin_y: f64,
        cell_size: f64,
        epsg: u32,
        nodata: f32,
    ) -> Raster {
        Raster {
            width,
            height,
            origin_x,
            origin_y,
            cell_size,
            epsg,
            nodata,
            bands: Vec::new(),
            band_names: Vec::new(),
            band_units: Vec::new(),
        }
    }

    /// Adds a band of `width × height` values with its name and unit (either may be empty).
    pub fn push_band(&mut self, name: &str, unit: &str, values: Vec<f32>) {
        self.bands.push(values);
        self.band_names.push(name.to_string());
        self.band_units.push(unit.to_string());
    }

    /// The GDAL geotransform `[origin_x, cell_size, 0, origin_y, 0, −cell_size]`.
    pub fn geotransform(&self) -> [f64; 6] {
        [
            self.origin_x,
            self.cell_size,
            0.0,
            self.origin_y,
            0.0,
            -self.cell_size,
        ]
    }

    /// Whether `v` is missing: equal to `nodata`, or NaN.
    pub fn is_nodata(&self, v: f32) -> bool {
        is_nodata(v, self.nodata)
    }

    /// Checks what the writers rely on; `file` names the output in the error.
    pub(crate) fn validate(&self, file: &Path) -> Result<(), RasterError> {
        let bad = |w: String| Err(RasterError::invalid(file, w));
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "empty raster ({} × {} cells)",
                self.width, self.height
            ));
        }
        if self.width > MAX_DIMENSION || self.height > MAX_DIMENSION {
            return bad(format!(
                "{} × {} cells is too large: at most {MAX_DIMENSION} cells a side; write tiles \
                 and a VRT mosaic instead",
                self.width, self.height
            ));
        }
        if !(self.cell_size.is_finite() && self.cell_size > 0.0) {
            return bad(format!(
                "cell_size {} is not a positive number",
                self.cell_size
            ));
        }
        if !(self.origin_x.is_finite() && self.origin_y.is_finite()) {
            return bad(format!(
                "origin ({}, {}) is not finite",
                self.origin_x, self.origin_y
            ));
        }
        // GeoKey values are 16-bit and 32767 means "user-defined".
        if self.epsg == 0 || self.epsg > 65535 || self.epsg == 32767 {
            return bad(format!(
                "EPSG:{} cannot be stated as a GeoTIFF key (1..65535, not 32767)",
                self.epsg
            ));
        }
        if self.bands.is_empty() {
            return bad("no bands".into());
        }
        if self.bands.len() > 1024 {
            return bad(format!("{} bands: at most 1024", self.bands.len()));
        }
        let cells = self.width * self.height;
        for (i, b) in self.bands.iter().enumerate() {
            if b.len() != cells {
                return bad(format!(
                    "band {} holds {} values, {} × {} = {cells} expected",
                    i + 1,
                    b.len(),
                    self.width,
                    self.height
                ));
            }
        }
        for (what, v) in [
            ("band_names", &self.band_names),
            ("band_units", &self.band_units),
        ] {
            if !v.is_empty() && v.len() != self.bands.len() {
                return bad(format!("{} {what} for {} bands", v.len(), self.bands.len()));
            }
        }
        Ok(())
    }
}

/// Whether `v` is missing for a raster whose nodata value is `nodata`.
pub(crate) fn is_nodata(v: f32, nodata: f32) -> bool {
    v.is_nan() || v == nodata
}

/// Whether an EPSG code names a geographic (latitude/longitude) CRS, by the EPSG code ranges
/// of geographic 2D CRSs (4000–4999) that GeoTIFF's `GeographicTypeGeoKey` takes; everything
/// else is treated as projected (`ProjectedCSTypeGeoKey`).
pub fn is_geographic_epsg(epsg: u32) -> bool {
    (4000..5000).contains(&epsg)
}

/// The nodata value as GDAL writes it in `GDAL_NODATA` and a VRT's `NoDataValue`.
pub(crate) fn nodata_text(v: f32) -> String {
    if v.is_nan() {
        "nan".into()
    } else if v.is_infinite() {
        if v > 0.0 { "inf".into() } else { "-inf".into() }
    } else {
        // Rust prints the shortest text that reads back to the same f32.
        format!("{v}")
    }
}

/// Escapes text for XML element content and attribute values.
pub(crate) fn xml_escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&apos;"),
            c => o.push(c),
        }
    }
    o
}

/// Writes `path` atomically: under `path.partial`, flushed and synced, then renamed over `path`.
/// On any error the partial file is removed, so a failed write leaves nothing behind (and a
/// previous `path` intact).
pub(crate) fn write_atomic(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
) -> Result<(), RasterError> {
    use std::io::Write;
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = std::path::PathBuf::from(tmp);
    let file = std::fs::File::create(&tmp).map_err(|e| RasterError::io(path, e))?;
    let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
    let result = fill(&mut w)
        .and_then(|()| w.flush())
        .and_then(|()| w.get_ref().sync_all())
        .and_then(|()| {
            drop(w);
            std::fs::rename(&tmp, path)
        });
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(RasterError::io(path, e));
    }
    Ok(())
}
