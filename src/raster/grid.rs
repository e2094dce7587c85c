//! [`CellGrid`]: per-cell statistics of georeferenced values over a fixed north-up grid — the
//! maximum (canopy height model), the mean (RH percentiles, cover, PAI …), the number of
//! values (pulse density) — turned into a [`Raster`] for [`super::write_cog`].
//!
//! Grids of the same cell size whose origins are multiples of the cell size line up, so the
//! tiles of [`CellGrid::for_tile`] mosaic without gaps or overlaps in a VRT
//! ([`super::write_vrt`]).

use std::path::Path;

use super::{MAX_DIMENSION, Raster, RasterError};

/// A per-cell statistic of [`CellGrid`], one raster band each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CellStat {
    /// The largest finite value in the cell (e.g. canopy height, m). Band name `max`.
    Max,
    /// The mean of the finite values in the cell. Band name `mean`.
    Mean,
    /// How many values fell in the cell, finite or not (e.g. pulses). Band name `count`.
    Count,
    /// `Count` per square CRS unit (pulses/m² in a projected CRS). Band name `density`.
    Density,
}

impl CellStat {
    /// The band name this statistic gets in [`CellGrid::to_raster`].
    pub fn name(self) -> &'static str {
        match self {
            CellStat::Max => "max",
            CellStat::Mean => "mean",
            CellStat::Count => "count",
            CellStat::Density => "density",
        }
    }
}

/// Accumulates (x, y, value) into the cells of a fixed grid.
///
/// Cell (col, row) covers x ∈ [origin_x + col·cell, origin_x + (col+1)·cell) and
/// y ∈ [origin_y − (row+1)·cell, origin_y − row·cell) (rows run south from the upper-left
/// corner, as in [`Raster`]; every cell holds its lower-left edges). Values outside the grid are not accumulated ([`CellGrid::add`]
/// says so). Memory: 20 bytes per cell.
#[derive(Clone, Debug)]
pub struct CellGrid {
    origin_x: f64,
    origin_y: f64,
    cell_size: f64,
    width: usize,
    height: usize,
    max: Vec<f32>,
    sum: Vec<f64>,
    /// Finite values per cell (the mean's divisor).
    valid: Vec<u32>,
    /// All values per cell.
    count: Vec<u32>,
}

impl CellGrid {
    /// A grid of `width × height` cells of `cell_size` CRS units (m) whose upper-left corner
    /// is (`origin_x`, `origin_y`). Errors on an empty or oversized grid or a cell size that is
    /// not positive.
    pub fn new(
        origin_x: f64,
        origin_y: f64,
        cell_size: f64,
        width: usize,
        height: usize,
    ) -> Result<CellGrid, RasterError> {
        let here = Path::new("<cell grid>");
        if !(cell_size.is_finite() && cell_size > 0.0) {
            return Err(RasterError::invalid(
                here,
                format!("cell_size {cell_size} is not a positive number"),
            ));
        }
        if !(origin_x.is_finite() && origin_y.is_finite()) {
            return Err(RasterError::invalid(
                here,
                format!("origin ({origin_x}, {origin_y}) is not finite"),
            ));
        }
        if width == 0 || height == 0 || width > MAX_DIMENSION || height > MAX_DIMENSION {
            return Err(RasterError::invalid(
                here,
                format!("{width} × {height} cells: each side must be 1..={MAX_DIMENSION}"),
            ));
        }
        let n = width * height;
        Ok(CellGrid {
            origin_x,
            origin_y,
            cell_size,
            width,
            height,
            max: vec![f32::NEG_INFINITY; n],
            sum: vec![0.0; n],
            valid: vec![0; n],
            count: vec![0; n],
        })
    }

    /// The grid snapped to multiples of `cell_size` that covers the box
    /// [`min_x`, `max_x`] × [`min_y`, `max_y`] (CRS units).
    pub fn covering(
        min_x: f64,
        min_y: f64,
        max_x: f64,
        max_y: f64,
        cell_size: f64,
    ) -> Result<CellGrid, RasterError> {
        let c0 = (min_x / cell_size).floor();
        let r0 = (max_y / cell_size).floor() + 1.0; // upper edge strictly above max_y
        let c1 = (max_x / cell_size).floor() + 1.0;
        let r1 = (min_y / cell_size).floor();
        let w = c1 - c0;
        let h = r0 - r1;
        if !(w.is_finite() && h.is_finite() && w >= 1.0 && h >= 1.0) {
            return Err(RasterError::invalid(
                Path::new("<cell grid>"),
                format!("box [{min_x}, {max_x}] × [{min_y}, {max_y}] is empty or not finite"),
            ));
        }
        let side = |v: f64| {
            if v > MAX_DIMENSION as f64 {
                MAX_DIMENSION + 1 // rejected by `new`
            } else {
                v as usize
            }
        };
        CellGrid::new(c0 * cell_size, r0 * cell_size, cell_size, side(w), side(h))
    }

    /// Tile (`ix`, `iy`) of a tiling of the plane into squares of `cells × cells` cells of
    /// `cell_size`: x ∈ [ix·cells·cell_size, (ix+1)·cells·cell_size), likewise y with `iy`.
    /// [`CellGrid::tile_of`] gives the tile a point falls in.
    pub fn for_tile(
        ix: i64,
        iy: i64,
        cells: usize,
        cell_size: f64,
    ) -> Result<CellGrid, RasterError> {
        let side = cells as f64 * cell_size;
        CellGrid::new(
            ix as f64 * side,
            (iy + 1) as f64 * side,
            cell_size,
            cells,
            cells,
        )
    }

    /// The tile (ix, iy) of [`CellGrid::for_tile`] that holds (x, y).
    pub fn tile_of(x: f64, y: f64, cells: usize, cell_size: f64) -> (i64, i64) {
        let side = cells as f64 * cell_size;
        ((x / side).floor() as i64, (y / side).floor() as i64)
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Upper-left corner (x, y), CRS units.
    pub fn origin(&self) -> (f64, f64) {
        (self.origin_x, self.origin_y)
    }

    /// Cell side, CRS units.
    pub fn cell_size(&self) -> f64 {
        self.cell_size
    }

    /// The cell (col, row) holding (x, y), if inside the grid.
    pub fn cell_of(&self, x: f64, y: f64) -> Option<(usize, usize)> {
        let c = ((x - self.origin_x) / self.cell_size).floor();
        let r = ((self.origin_y - y) / self.cell_size).ceil() - 1.0;
        // y exactly on a row's lower edge belongs to that row: ceil − 1 does this.
        if c >= 0.0 && r >= 0.0 && (c as usize) < self.width && (r as usize) < self.height {
            Some((c as usize, r as usize))
        } else {
            None
        }
    }

    /// Adds `value` at (x, y): the cell's count always grows; its max and mean take `value`
    /// only if it is finite (a NaN metric still counts as a pulse). Returns false, changing
    /// nothing, when (x, y) is outside the grid or not finite.
    pub fn add(&mut self, x: f64, y: f64, value: f32) -> bool {
        let Some((c, r)) = self.cell_of(x, y) else {
            return false;
        };
        let i = r * self.width + c;
        self.count[i] += 1;
        if value.is_finite() {
            self.valid[i] += 1;
            self.sum[i] += f64::from(value);
            if value > self.max[i] {
                self.max[i] = value;
            }
        }
        true
    }

    /// Number of values added to cell (col, row).
    pub fn count(&self, col: usize, row: usize) -> u32 {
        self.count[row * self.width + col]
    }

    /// One statistic as a band (row-major), `nodata` in cells it is undefined for (no finite
    /// value for `Max`/`Mean`; `Count` and `Density` are 0, never nodata, in empty cells).
    pub fn band(&self, stat: CellStat, nodata: f32) -> Vec<f32> {
        let area = self.cell_size * self.cell_size;
        (0..self.width * self.height)
            .map(|i| match stat {
                CellStat::Max if self.valid[i] > 0 => self.max[i],
                CellStat::Mean if self.valid[i] > 0 => {
                    (self.sum[i] / f64::from(self.valid[i])) as f32
                }
                CellStat::Max | CellStat::Mean => nodata,
                CellStat::Count => self.count[i] as f32,
                CellStat::Density => (f64::from(self.count[i]) / area) as f32,
            })
            .collect()
    }

    /// A raster of the grid with one band per statistic (named by [`CellStat::name`]; rename
    /// through `Raster::band_names` as needed, e.g. `canopy_height`), in CRS `epsg`.
    pub fn to_raster(&self, epsg: u32, nodata: f32, stats: &[CellStat]) -> Raster {
        let mut r = Raster::new(
            self.width,
            self.height,
            self.origin_x,
            self.origin_y,
            self.cell_size,
            epsg,
            nodata,
        );
        for &s in stats {
            let unit = match s {
                CellStat::Count => "count",
                CellStat::Density => "1/unit2",
                _ => "",
            };
            r.push_band(s.name(), unit, self.band(s, nodata));
        }
        r
    }

    /// Appends the accumulators of the cells holding a value to `out` (a tile closed behind
    /// the flight keeps them in a file to be read back if it reopens, `src/sink/metrics_rasters.rs`):
    /// `FWCG`, width, height, the number of such cells (u32 each), then per cell its index
    /// (row-major), count, finite values (u32), maximum (f32) and sum (f64), little-endian:
    /// 16 + 24 bytes per cell with a value.
    pub fn save_cells(&self, out: &mut Vec<u8>) {
        let used = self.count.iter().filter(|&&c| c > 0).count();
        out.reserve(16 + 24 * used);
        out.extend_from_slice(CELLS_MAGIC);
        for v in [self.width as u32, self.height as u32, used as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for (i, &c) in self.count.iter().enumerate() {
            if c == 0 {
                continue;
            }
            out.extend_from_slice(&(i as u32).to_le_bytes());
            out.extend_from_slice(&c.to_le_bytes());
            out.extend_from_slice(&self.valid[i].to_le_bytes());
            out.extend_from_slice(&self.max[i].to_le_bytes());
            out.extend_from_slice(&self.sum[i].to_le_bytes());
        }
    }

    /// Sets the cells [`CellGrid::save_cells`] wrote at the start of `bytes` (read from `file`,
    /// named in errors) into this grid, which must have the same size; cells not in `bytes`
    /// keep their values (an empty grid becomes the one saved, exactly). Returns the bytes after
    /// them. Errors on anything malformed, changing no cell.
    pub fn load_cells<'a>(
        &mut self,
        bytes: &'a [u8],
        file: &Path,
    ) -> Result<&'a [u8], RasterError> {
        let bad = |what: &str| RasterError::invalid(file, format!("cell accumulators: {what}"));
        let u32_at = |b: &[u8], at: usize| -> Option<u32> {
            Some(u32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?))
        };
        if bytes.get(..4) != Some(CELLS_MAGIC.as_slice()) {
            return Err(bad("no FWCG header"));
        }
        let (Some(w), Some(h), Some(used)) =
            (u32_at(bytes, 4), u32_at(bytes, 8), u32_at(bytes, 12))
        else {
            return Err(bad("truncated header"));
        };
        if (w as usize, h as usize) != (self.width, self.height) {
            return Err(bad(&format!(
                "{w} × {h} cells, the grid has {} × {}",
                self.width, self.height
            )));
        }
        let end = 16usize.saturating_add((used as usize).saturating_mul(24));
        let Some(cells) = bytes.get(16..end) else {
            return Err(bad("truncated cells"));
        };
        let n = self.count.len();
        let index = |rec: &[u8]| u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]) as usize;
        if let Some(i) = cells.chunks_exact(24).map(index).find(|&i| i >= n) {
            return Err(bad(&format!("cell {i} outside the {n} cells")));
        }
        for rec in cells.chunks_exact(24) {
            let field = |a: usize| -> [u8; 4] { [rec[a], rec[a + 1], rec[a + 2], rec[a + 3]] };
            let i = index(rec);
            self.count[i] = u32::from_le_bytes(field(4));
            self.valid[i] = u32::from_le_bytes(field(8));
            self.max[i] = f32::from_le_bytes(field(12));
            let mut sum = [0u8; 8];
            sum.copy_from_slice(&rec[16..24]);
            self.sum[i] = f64::from_le_bytes(sum);
        }
        Ok(&bytes[end..])
    }
}

/// First bytes of [`CellGrid::save_cells`].
const CELLS_MAGIC: &[u8; 4] = b"FWCG";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_max_mean_count_and_edges() {
        let mut g = CellGrid::new(100.0, 200.0, 2.0, 3, 2).unwrap();
        // Cell (0, 0): x ∈ [100, 102), y ∈ [198, 200).
        assert!(g.add(100.0, 199.9, 5.0));
        assert!(g.add(101.9, 198.0, 7.0));
        assert!(g.add(101.0, 199.0, f32::NAN));
        // Cell (2, 1).
        assert!(g.add(105.5, 196.0, 1.5));
        // Outside: right edge, below, above.
        assert!(!g.add(106.0, 199.0, 1.0));
        assert!(!g.add(101.0, 195.9, 1.0));
        assert!(!g.add(101.0, 200.0, 1.0));
        assert_eq!(g.cell_of(102.0, 198.0), Some((1, 0)));
        assert_eq!(g.cell_of(102.0, 197.9), Some((1, 1)));
        let max = g.band(CellStat::Max, -1.0);
        let mean = g.band(CellStat::Mean, -1.0);
        let count = g.band(CellStat::Count, -1.0);
        assert_eq!(max, vec![7.0, -1.0, -1.0, -1.0, -1.0, 1.5]);
        assert_eq!(mean, vec![6.0, -1.0, -1.0, -1.0, -1.0, 1.5]);
        assert_eq!(count, vec![3.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        assert_eq!(g.band(CellStat::Density, -1.0)[0], 0.75);
        let r = g.to_raster(32618, -1.0, &[CellStat::Max, CellStat::Count]);
        assert_eq!(r.band_names, ["max", "count"]);
        assert_eq!(r.geotransform(), [100.0, 2.0, 0.0, 200.0, 0.0, -2.0]);
    }

    #[test]
    fn saved_cells_load_back_exactly_and_malformed_ones_are_refused() {
        let mut g = CellGrid::new(0.0, 10.0, 1.0, 4, 3).unwrap();
        g.add(0.5, 9.5, 0.1);
        g.add(0.7, 9.2, 0.2);
        g.add(3.5, 7.5, f32::NAN);
        let mut bytes = Vec::new();
        g.save_cells(&mut bytes);
        assert_eq!(bytes.len(), 16 + 2 * 24, "only the cells with a value");
        bytes.extend_from_slice(b"rest");
        let mut back = CellGrid::new(0.0, 10.0, 1.0, 4, 3).unwrap();
        let rest = back.load_cells(&bytes, Path::new("t")).unwrap();
        assert_eq!(rest, b"rest");
        // Adding the same value to both keeps them equal, bit for bit.
        g.add(0.5, 9.5, 0.3);
        back.add(0.5, 9.5, 0.3);
        for stat in [CellStat::Max, CellStat::Mean, CellStat::Count] {
            let (a, b) = (g.band(stat, -1.0), back.band(stat, -1.0));
            assert!(
                a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{stat:?}"
            );
        }
        assert_eq!(back.sum, g.sum);
        let mut other = CellGrid::new(0.0, 10.0, 1.0, 3, 4).unwrap();
        assert!(
            other.load_cells(&bytes, Path::new("t")).is_err(),
            "size differs"
        );
        assert!(
            back.load_cells(&bytes[..30], Path::new("t")).is_err(),
            "truncated"
        );
        assert!(back.load_cells(b"FWC", Path::new("t")).is_err());
        let mut outside = bytes[..16 + 24].to_vec();
        outside[16..20].copy_from_slice(&99u32.to_le_bytes());
        assert!(
            back.load_cells(&outside, Path::new("t")).is_err(),
            "index outside"
        );
    }

    #[test]
    fn tiles_line_up_and_covering_snaps() {
        let (ix, iy) = CellGrid::tile_of(-0.5, 1234.0, 100, 1.0);
        assert_eq!((ix, iy), (-1, 12));
        let t = CellGrid::for_tile(ix, iy, 100, 1.0).unwrap();
        assert_eq!(t.origin(), (-100.0, 1300.0));
        assert_eq!(t.cell_of(-0.5, 1234.0), Some((99, 65)));
        let g = CellGrid::covering(10.2, 20.7, 13.0, 22.0, 0.5).unwrap();
        assert_eq!(g.origin(), (10.0, 22.5));
        assert_eq!((g.width(), g.height()), (7, 4));
        assert!(g.cell_of(13.0, 20.7).is_some());
        assert!(CellGrid::new(0.0, 0.0, 0.0, 1, 1).is_err());
        assert!(CellGrid::new(0.0, 0.0, 1.0, MAX_DIMENSION + 1, 1).is_err());
    }
}
