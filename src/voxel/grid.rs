//! The voxel grid (`[voxels]` of a run configuration): CRS, origin, voxel size, height range,
//! the tiles it is cut into and the extent it covers; and the mapping of a map position to a
//! voxel.
//!
//! Units: metres in the output CRS (x, y: easting, northing; z: ellipsoidal height, or height
//! above the DEM with `height = "above_dem"`).
//!
//! Tiles are numbered on a grid anchored at `origin_m` (default the CRS origin, so stores from
//! different flights with the same voxel size and tile size line up and merge): tile `(tx, ty)`
//! covers `origin + (tx·S, ty·S)` to `origin + ((tx+1)·S, (ty+1)·S)` with `S = tile_columns ·
//! voxel size`. Inside a tile a voxel is `(k, j, i)`: level `k` from `z_range_m[0]` upwards,
//! row `j` northwards, column `i` eastwards; its offset is `(j·T + i)·L + k` (`L` levels).
//!
//! The height axis is cut into chunks of `chunk_levels` (`H`) levels, and only the chunks that
//! hold data exist (in memory and in the store): the default height range is therefore every
//! height on Earth (`[-1000, 9000]` m, anchored at fixed levels so that stores line up and
//! merge), at no cost for the air. In memory a chunk's accumulators sit at `(j·T + i)·H + kk`
//! (a column contiguous, so the bins of a near-vertical beam land in neighbouring cache lines);
//! the store's chunks are in the `[z, y, x]` order of the arrays (`(kk·T + j)·T + i`); `zarr`
//! transposes when it writes and reads.

use serde::{Deserialize, Serialize};

use crate::core::validate::{Validate, Validator, field};

/// How voxel heights are measured.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HeightMode {
    /// The z of the output CRS (ellipsoidal height, metres). Default.
    #[default]
    Absolute,
    /// Height above the DEM of `[georeference] dem` (metres): z − DEM(x, y).
    AboveDem,
}

impl HeightMode {
    /// Name as written in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            HeightMode::Absolute => "absolute",
            HeightMode::AboveDem => "above_dem",
        }
    }
}

/// `[voxels]`: the voxel grid and the tile lifecycle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VoxelConfig {
    /// Write voxel tiles (`voxels.zarr`). Default false.
    #[serde(default)]
    pub enabled: bool,
    /// Voxel size `[x, y, z]`, metres. Default `[0.5, 0.5, 0.15]` (the seed's grid).
    #[serde(default = "default_voxel_size")]
    pub voxel_size_m: [f64; 3],
    /// Anchor of the tile grid `[x, y]` in the output CRS, metres. Default `[0, 0]`.
    #[serde(default)]
    pub origin_m: [f64; 2],
    /// Height range `[bottom, top]` of the grid, metres (see `height`): an optional limit.
    /// Default `[-1000, 9000]`, every height on Earth (only the height chunks that hold data
    /// cost memory or disk, so a tall range is free).
    #[serde(default = "default_z_range")]
    pub z_range_m: [f64; 2],
    /// Levels per height chunk of the store (a power of two, 1..=4096); a chunk is
    /// `tile_columns² × chunk_levels` voxels. Default 64 (9.6 m at 0.15 m).
    #[serde(default = "default_chunk_levels")]
    pub chunk_levels: u32,
    /// Heights absolute or above the DEM. Default absolute.
    #[serde(default)]
    pub height: HeightMode,
    /// Columns along each side of a tile (a tile is `tile_columns²` columns over the height
    /// range). Default 32 (16 m at 0.5 m).
    #[serde(default = "default_tile_columns")]
    pub tile_columns: u32,
    /// Horizontal extent `[xmin, ymin, xmax, ymax]` of the store, metres; bins outside it are
    /// counted and not deposited. Default: a square of `auto_extent_m` centred on the first
    /// deposit, snapped to tiles.
    #[serde(default)]
    pub extent_m: Option<[f64; 4]>,
    /// Side of the automatic extent, metres. Default 1 000 000 (1000 km: any survey flown from
    /// its first pulse; the extent costs nothing until a tile holds data, and a finished
    /// store's arrays span only the tiles written).
    #[serde(default = "default_auto_extent")]
    pub auto_extent_m: f64,
    /// Tiles held in memory at most; beyond, the tile deposited least recently is closed early
    /// (and merged again if touched later). Default 64. The metrics rasters' tiles follow this
    /// and `close_after_s` too (`src/sink/metrics_rasters.rs`).
    #[serde(default = "default_max_open")]
    pub max_open_tiles: usize,
    /// Memory the open tiles may take, MiB (2^20 bytes): a tile costs the columns deposited
    /// in (4 arrays × the height chunk's levels per column written), so a sparse line's tile
    /// of a few pulses costs a few pulses' columns. Past it (checked when a tile opens and every
    /// 256 pulses), the tiles deposited least recently are closed early until the rest fit.
    /// Default 1024.
    #[serde(
        default = "default_max_open_mib",
        skip_serializing_if = "is_default_max_open_mib"
    )]
    pub max_open_mib: u64,
    /// A tile closes when no bin has been deposited in it for this long (pulse time, seconds)
    /// and it lies outside the current swath. Default 2.
    #[serde(default = "default_close_after")]
    pub close_after_s: f64,
    /// Spread each bin over the columns its footprint covers (beam divergence of the sensor
    /// profile), instead of the column of the beam axis. Default false.
    #[serde(default)]
    pub footprint: bool,
    /// Full-angle beam divergence for `footprint`, milliradians; default the sensor profile's.
    #[serde(default)]
    pub beam_divergence_mrad: Option<f64>,
    /// Quantum of the intensity sums (units of the deposited intensity): sums are integers of
    /// this quantum so that merging partial results is exact in any order. Default 1e-6.
    #[serde(default = "default_quantum")]
    pub intensity_quantum: f64,
    /// Also write each closed tile's occupied voxels as a LAS point cloud
    /// (`voxels_las/tile_<tx>_<ty>.las`). Default false.
    #[serde(default)]
    pub las: bool,
    /// Threads writing closed tiles (compression, sync, commit), each tile always on the same
    /// one. Default: one per four cores, at least one.
    #[serde(default)]
    pub writer_threads: Option<usize>,
    /// Tiles along each side of a shard file (`G`): the height chunks of `G × G` tiles over
    /// `shard_height_chunks` height chunks are one file per array, written when the flight has
    /// left them, with one journal line per batch (`src/voxel/shard_group.rs`). Default 16;
    /// 0: a file per tile, height chunk and array, committed tile by tile (the layout before
    /// issue 36).
    #[serde(
        default = "default_shard_tiles",
        skip_serializing_if = "is_default_shard_tiles"
    )]
    pub shard_tiles: u32,
    /// Height chunks of a shard file (`K`) when `shard_tiles` > 0. Default 8.
    #[serde(
        default = "default_shard_height_chunks",
        skip_serializing_if = "is_default_shard_height"
    )]
    pub shard_height_chunks: u32,
}

fn default_shard_tiles() -> u32 {
    16
}

fn default_shard_height_chunks() -> u32 {
    8
}

// The grouping keys are left out of the recorded configuration at their defaults, so that a
// store's metadata (and run key) is what versions before them wrote.
fn is_default_shard_tiles(v: &u32) -> bool {
    *v == default_shard_tiles()
}

fn is_default_shard_height(v: &u32) -> bool {
    *v == default_shard_height_chunks()
}

impl VoxelConfig {
    /// How a new store is laid out: tiles grouped into shard files (`shard_tiles` > 0) or
    /// not; inner chunks of `INNER_COLUMNS` (narrower ones were measured: on the sparse 7.2 km
    /// line 4 columns a side doubled the store for no speed, 1 column multiplied it by 20 —
    /// each inner chunk costs an index entry and a zstd frame; docs/performance.md).
    pub fn layout_choice(&self) -> crate::voxel::shard_group::LayoutChoice {
        crate::voxel::shard_group::LayoutChoice {
            group: (self.shard_tiles > 0).then_some(crate::voxel::shard_group::ShardGroup {
                tiles: self.shard_tiles,
                height_chunks: self.shard_height_chunks,
            }),
            inner_columns: crate::voxel::shard_group::INNER_COLUMNS,
        }
    }
}

fn default_voxel_size() -> [f64; 3] {
    [0.5, 0.5, 0.15]
}
fn default_z_range() -> [f64; 2] {
    [-1000.0, 9000.0]
}
fn default_chunk_levels() -> u32 {
    64
}
fn default_tile_columns() -> u32 {
    32
}
fn default_auto_extent() -> f64 {
    1.0e6
}
fn default_max_open() -> usize {
    64
}
fn default_max_open_mib() -> u64 {
    1024
}
// Left out of the recorded configuration at its default, so that a store's run key is what
// versions before it wrote.
fn is_default_max_open_mib(v: &u64) -> bool {
    *v == default_max_open_mib()
}
fn default_close_after() -> f64 {
    2.0
}
fn default_quantum() -> f64 {
    1e-6
}

impl Default for VoxelConfig {
    fn default() -> Self {
        VoxelConfig {
            enabled: false,
            voxel_size_m: default_voxel_size(),
            origin_m: [0.0, 0.0],
            z_range_m: default_z_range(),
            chunk_levels: default_chunk_levels(),
            height: HeightMode::Absolute,
            tile_columns: default_tile_columns(),
            extent_m: None,
            auto_extent_m: default_auto_extent(),
            max_open_tiles: default_max_open(),
            max_open_mib: default_max_open_mib(),
            close_after_s: default_close_after(),
            footprint: false,
            beam_divergence_mrad: None,
            intensity_quantum: default_quantum(),
            las: false,
            writer_threads: None,
            shard_tiles: default_shard_tiles(),
            shard_height_chunks: default_shard_height_chunks(),
        }
    }
}

/// Most voxels a height chunk may hold (memory of one chunk: 20 bytes per voxel).
pub const MAX_TILE_VOXELS: u64 = 1 << 26;

/// Most voxels a tile may span over the whole height range (offsets inside a tile are `u32`).
pub const MAX_TILE_SPAN: u64 = u32::MAX as u64;

impl Validate for VoxelConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        for (i, s) in self.voxel_size_m.iter().enumerate() {
            v.require(
                s.is_finite() && (0.01..=100.0).contains(s),
                format!("{}[{i}]", field(path, "voxel_size_m")),
                format!("must be in 0.01..=100 m, got {s}"),
            );
        }
        v.require(
            self.origin_m.iter().all(|o| o.is_finite()),
            field(path, "origin_m"),
            "must be finite",
        );
        let [lo, hi] = self.z_range_m;
        v.require(
            lo.is_finite() && hi.is_finite() && lo < hi,
            field(path, "z_range_m"),
            format!("must be [bottom, top] with bottom < top, got [{lo}, {hi}]"),
        );
        v.require(
            (1..=4096).contains(&self.tile_columns),
            field(path, "tile_columns"),
            format!("must be in 1..=4096, got {}", self.tile_columns),
        );
        if let Some(e) = self.extent_m {
            v.require(
                e.iter().all(|x| x.is_finite()) && e[0] < e[2] && e[1] < e[3],
                field(path, "extent_m"),
                format!("must be [xmin, ymin, xmax, ymax] with min < max, got {e:?}"),
            );
        }
        v.require(
            self.auto_extent_m.is_finite() && (1.0..=1.0e6).contains(&self.auto_extent_m),
            field(path, "auto_extent_m"),
            format!("must be in 1..=1e6 m, got {}", self.auto_extent_m),
        );
        v.require(
            self.shard_tiles <= 256,
            field(path, "shard_tiles"),
            format!("must be in 0..=256, got {}", self.shard_tiles),
        );
        v.require(
            (1..=256).contains(&self.shard_height_chunks),
            field(path, "shard_height_chunks"),
            format!("must be in 1..=256, got {}", self.shard_height_chunks),
        );

        v.require(
            (1..=1 << 20).contains(&self.max_open_tiles),
            field(path, "max_open_tiles"),
            format!("must be in 1..=1048576, got {}", self.max_open_tiles),
        );
        v.require(
            (1..=1 << 24).contains(&self.max_open_mib),
            field(path, "max_open_mib"),
            format!("must be in 1..=16777216 (MiB), got {}", self.max_open_mib),
        );
        v.require(
            self.close_after_s.is_finite() && (0.0..=3600.0).contains(&self.close_after_s),
            field(path, "close_after_s"),
            format!("must be in 0..=3600 s, got {}", self.close_after_s),
        );
        if let Some(n) = self.writer_threads {
            v.require(
                (1..=64).contains(&n),
                field(path, "writer_threads"),
                format!("must be in 1..=64, got {n}"),
            );
        }
        if let Some(d) = self.beam_divergence_mrad {
            v.require(
                d.is_finite() && d > 0.0 && d < 100.0,
                field(path, "beam_divergence_mrad"),
                format!("must be in (0, 100) mrad, got {d}"),
            );
        }
        v.require(
            self.intensity_quantum.is_finite() && self.intensity_quantum > 0.0,
            field(path, "intensity_quantum"),
            format!("must be > 0, got {}", self.intensity_quantum),
        );
        v.require(
            self.chunk_levels.is_power_of_two() && self.chunk_levels <= 4096,
            field(path, "chunk_levels"),
            format!(
                "must be a power of two in 1..=4096, got {}",
                self.chunk_levels
            ),
        );
        if let Some(levels) = self.levels_checked() {
            let cols = self.tile_columns as u64 * self.tile_columns as u64;
            let voxels = cols * self.chunk_levels.min(levels) as u64;
            v.require(
                voxels <= MAX_TILE_VOXELS,
                field(path, "tile_columns"),
                format!(
                    "a height chunk of {0}×{0} columns × {1} levels is {voxels} voxels, more \
                     than {MAX_TILE_VOXELS}: use smaller tiles or fewer chunk_levels",
                    self.tile_columns,
                    self.chunk_levels.min(levels)
                ),
            );
            let span = cols * levels as u64;
            v.require(
                span <= MAX_TILE_SPAN,
                field(path, "z_range_m"),
                format!(
                    "a tile of {0}×{0} columns × {levels} levels spans {span} voxels, more than \
                     {MAX_TILE_SPAN}: use smaller tiles, a shorter z_range_m or taller voxels",
                    self.tile_columns
                ),
            );
        }
    }
}

impl VoxelConfig {
    /// Tile writer threads: the configured number, or one per four cores, at least two (a
    /// writer idles until a tile closes; on two cores a second one ran the sparse 7.2 km line
    /// ~15 % faster and the dense survey line ~5 %, docs/performance.md).
    pub fn writer_threads(&self) -> usize {
        self.writer_threads.unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get() / 4)
                .unwrap_or(1)
                .max(2)
        })
    }

    fn levels_checked(&self) -> Option<u32> {
        let [lo, hi] = self.z_range_m;
        let dz = self.voxel_size_m[2];
        let n = ((hi - lo) / dz - 1e-9).ceil();
        (n.is_finite() && n >= 1.0 && n <= u32::MAX as f64).then_some(n as u32)
    }
}

/// The grid a store is written on: everything needed to place a voxel, fixed for the store's
/// life (two stores merge only when their grids agree, apart from their extents).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    /// Voxel size `[x, y, z]`, metres.
    pub voxel_size_m: [f64; 3],
    /// Anchor of the tile grid `[x, y]`, metres.
    pub origin_m: [f64; 2],
    /// Bottom of level 0, metres.
    pub z_bottom_m: f64,
    /// Height levels.
    pub levels: u32,
    /// Levels per height chunk (a power of two; 0 in stores of older versions, which are not
    /// read).
    #[serde(default)]
    pub chunk_levels: u32,
    /// Columns along each side of a tile.
    pub tile_columns: u32,
    /// Heights absolute or above the DEM.
    pub height: HeightMode,
    /// Tiles covered: `[tx_min, ty_min]` inclusive.
    pub tile_min: [i64; 2],
    /// Number of tiles `[east, north]`.
    pub tiles: [u32; 2],
    /// Quantum of the intensity sums.
    pub intensity_quantum: f64,
}

impl Grid {
    /// The grid of `cfg` with its extent (configured, or automatic around `first`, a position
    /// in the output CRS).
    pub fn new(cfg: &VoxelConfig, first: [f64; 2]) -> Grid {
        let levels = cfg.levels_checked().unwrap_or(1);
        let side = cfg.tile_columns as f64;
        let tile_m = [side * cfg.voxel_size_m[0], side * cfg.voxel_size_m[1]];
        let extent = cfg.extent_m.unwrap_or_else(|| {
            let h = cfg.auto_extent_m / 2.0;
            [first[0] - h, first[1] - h, first[0] + h, first[1] + h]
        });
        let t0 = [
            ((extent[0] - cfg.origin_m[0]) / tile_m[0]).floor() as i64,
            ((extent[1] - cfg.origin_m[1]) / tile_m[1]).floor() as i64,
        ];
        let t1 = [
            ((extent[2] - cfg.origin_m[0]) / tile_m[0]).ceil() as i64,
            ((extent[3] - cfg.origin_m[1]) / tile_m[1]).ceil() as i64,
        ];
        Grid {
            voxel_size_m: cfg.voxel_size_m,
            origin_m: cfg.origin_m,
            z_bottom_m: cfg.z_range_m[0],
            levels,
            // No taller than the grid needs (a small grid is one chunk).
            chunk_levels: cfg
                .chunk_levels
                .max(1)
                .min(levels.next_power_of_two())
                .next_power_of_two(),
            tile_columns: cfg.tile_columns,
            height: cfg.height,
            tile_min: t0,
            tiles: [
                (t1[0] - t0[0]).clamp(1, u32::MAX as i64) as u32,
                (t1[1] - t0[1]).clamp(1, u32::MAX as i64) as u32,
            ],
            intensity_quantum: cfg.intensity_quantum,
        }
    }

    /// Voxels in one tile over the whole height range (most are never allocated).
    pub fn tile_voxels(&self) -> usize {
        self.levels as usize * self.tile_columns as usize * self.tile_columns as usize
    }

    /// Levels per height chunk, `H`.
    pub fn chunk_levels(&self) -> u32 {
        self.chunk_levels.max(1)
    }

    /// Voxels in one height chunk of a tile, `T² · H`.
    pub fn chunk_voxels(&self) -> usize {
        self.chunk_levels() as usize * self.tile_columns as usize * self.tile_columns as usize
    }

    /// Height chunks over the grid's levels.
    pub fn height_chunks(&self) -> u32 {
        self.levels.div_ceil(self.chunk_levels())
    }

    /// Tile side `[x, y]`, metres.
    pub fn tile_m(&self) -> [f64; 2] {
        let s = self.tile_columns as f64;
        [s * self.voxel_size_m[0], s * self.voxel_size_m[1]]
    }

    /// Shape `[levels, rows (y), columns (x)]` of voxels over the whole extent (the store's
    /// arrays while a run writes; `zarr::Span` says what they span).
    pub fn shape(&self) -> [u64; 3] {
        let t = self.tile_columns as u64;
        [
            self.levels as u64,
            self.tiles[1] as u64 * t,
            self.tiles[0] as u64 * t,
        ]
    }

    /// West and south edges of the extent, metres.
    pub fn extent_origin(&self) -> [f64; 2] {
        let tm = self.tile_m();
        [
            self.origin_m[0] + self.tile_min[0] as f64 * tm[0],
            self.origin_m[1] + self.tile_min[1] as f64 * tm[1],
        ]
    }

    /// Whether tile `(tx, ty)` (global numbering) is inside the store's extent.
    pub fn contains_tile(&self, tile: [i64; 2]) -> bool {
        (0..2).all(|a| {
            tile[a] >= self.tile_min[a] && tile[a] < self.tile_min[a] + self.tiles[a] as i64
        })
    }

    /// Whether `other` places every voxel where this grid does (extents may differ).
    pub fn compatible(&self, other: &Grid) -> Result<(), String> {
        let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(1.0);
        if !(0..3).all(|i| same(self.voxel_size_m[i], other.voxel_size_m[i])) {
            return Err(format!(
                "voxel sizes differ: {:?} m and {:?} m",
                self.voxel_size_m, other.voxel_size_m
            ));
        }
        if !(0..2).all(|i| same(self.origin_m[i], other.origin_m[i])) {
            return Err(format!(
                "tile grid origins differ: {:?} m and {:?} m",
                self.origin_m, other.origin_m
            ));
        }
        if !same(self.z_bottom_m, other.z_bottom_m) || self.levels != other.levels {
            return Err(format!(
                "height ranges differ: {} m + {} levels and {} m + {} levels",
                self.z_bottom_m, self.levels, other.z_bottom_m, other.levels
            ));
        }
        if self.chunk_levels != other.chunk_levels {
            return Err(format!(
                "height chunks differ: {} and {} levels",
                self.chunk_levels, other.chunk_levels
            ));
        }
        if self.tile_columns != other.tile_columns {
            return Err(format!(
                "tile sizes differ: {} and {} columns",
                self.tile_columns, other.tile_columns
            ));
        }
        if self.height != other.height {
            return Err(format!(
                "height modes differ: {} and {}",
                self.height.name(),
                other.height.name()
            ));
        }
        if !same(self.intensity_quantum, other.intensity_quantum) {
            return Err(format!(
                "intensity quanta differ: {} and {}",
                self.intensity_quantum, other.intensity_quantum
            ));
        }
        Ok(())
    }

    /// The grid covering the tiles of both (same grid otherwise).
    pub fn union(&self, other: &Grid) -> Grid {
        let mut g = self.clone();
        for a in 0..2 {
            let lo = self.tile_min[a].min(other.tile_min[a]);
            let hi = (self.tile_min[a] + self.tiles[a] as i64)
                .max(other.tile_min[a] + other.tiles[a] as i64);
            g.tile_min[a] = lo;
            g.tiles[a] = (hi - lo) as u32;
        }
        g
    }
}

/// A position on the grid: the tile and the voxel inside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VoxelIndex {
    /// Tile `[tx, ty]`, global numbering.
    pub tile: [i64; 2],
    /// Offset of the voxel's accumulators inside the tile.
    pub offset: u32,
}

/// Precomputed reciprocals for placing positions on a [`Grid`] quickly.
#[derive(Clone, Copy, Debug)]
pub struct Placer {
    inv: [f64; 3],
    origin: [f64; 2],
    z_bottom: f64,
    levels: i64,
    side: i64,
    col_min: [i64; 2],
    col_end: [i64; 2],
}

impl Placer {
    /// Placer of `grid`.
    pub fn new(grid: &Grid) -> Placer {
        let side = grid.tile_columns as i64;
        Placer {
            inv: [
                1.0 / grid.voxel_size_m[0],
                1.0 / grid.voxel_size_m[1],
                1.0 / grid.voxel_size_m[2],
            ],
            origin: grid.origin_m,
            z_bottom: grid.z_bottom_m,
            levels: grid.levels as i64,
            side,
            col_min: [grid.tile_min[0] * side, grid.tile_min[1] * side],
            col_end: [
                (grid.tile_min[0] + grid.tiles[0] as i64) * side,
                (grid.tile_min[1] + grid.tiles[1] as i64) * side,
            ],
        }
    }

    /// Global column `[cx, cy]` of a horizontal position, if inside the extent.
    #[inline]
    pub fn column(&self, x: f64, y: f64) -> Option<[i64; 2]> {
        let [gx, gy] = self.grid_xy(x, y);
        let (cx, cy) = (fast_floor(gx), fast_floor(gy));
        // NaN fails both comparisons.
        if !(cx >= self.col_min[0] as f64 && cx < self.col_end[0] as f64) {
            return None;
        }
        if !(cy >= self.col_min[1] as f64 && cy < self.col_end[1] as f64) {
            return None;
        }
        Some([cx as i64, cy as i64])
    }

    /// Level of a height (absolute or above ground, as the grid measures), if inside the range.
    #[inline]
    pub fn level(&self, z: f64) -> Option<i64> {
        let k = fast_floor((z - self.z_bottom) * self.inv[2]);
        (k >= 0.0 && k < self.levels as f64).then_some(k as i64)
    }

    /// The voxel of global column `c` at level `k`.
    #[inline]
    pub fn voxel(&self, c: [i64; 2], k: i64) -> VoxelIndex {
        let tile = self.tile_of(c);
        VoxelIndex {
            tile,
            offset: self.offset(c[0] - tile[0] * self.side, c[1] - tile[1] * self.side, k),
        }
    }

    /// The tile of global column `c`.
    #[inline]
    pub fn tile_of(&self, c: [i64; 2]) -> [i64; 2] {
        if self.side.count_ones() == 1 {
            // A power of two: the arithmetic shift is the floor division, negatives included.
            let s = self.side.trailing_zeros();
            [c[0] >> s, c[1] >> s]
        } else {
            [c[0].div_euclid(self.side), c[1].div_euclid(self.side)]
        }
    }

    /// Columns along a tile's side.
    #[inline]
    pub fn side(&self) -> i64 {
        self.side
    }

    /// Offset in a tile's accumulators of column `i` (east), row `j` (north), level `k`.
    #[inline]
    pub fn offset(&self, i: i64, j: i64, k: i64) -> u32 {
        ((j * self.side + i) * self.levels + k) as u32
    }

    /// Fractional grid coordinates `[gx, gy]` of a horizontal position: the column is their
    /// floor (what [`Placer::column`] computes before its range checks).
    #[inline]
    pub fn grid_xy(&self, x: f64, y: f64) -> [f64; 2] {
        [
            (x - self.origin[0]) * self.inv[0],
            (y - self.origin[1]) * self.inv[1],
        ]
    }

    /// Bottom of level 0, metres.
    #[inline]
    pub fn z_bottom(&self) -> f64 {
        self.z_bottom
    }

    /// Levels of the grid.
    #[inline]
    pub fn levels(&self) -> i64 {
        self.levels
    }

    /// 1 / voxel size along `axis` (0 x, 1 y, 2 z), per metre.
    pub fn inv(&self, axis: usize) -> f64 {
        self.inv[axis]
    }

    /// Centre `[x, y]` of global column `c`, metres.
    pub fn column_centre(&self, c: [i64; 2]) -> [f64; 2] {
        [
            self.origin[0] + (c[0] as f64 + 0.5) / self.inv[0],
            self.origin[1] + (c[1] as f64 + 0.5) / self.inv[1],
        ]
    }
}

/// `v.floor()` for the values a grid meets, without the library call baseline x86-64 makes for
/// `floor` (no SSE4.1 rounding instruction): truncation, corrected for negatives. Values beyond
/// ±2⁶³ and NaN come out as whatever lies outside every grid (they are refused by the caller's
/// range check).
#[inline]
pub fn fast_floor(v: f64) -> f64 {
    // NaN, infinities and huge values come back as they are: refused by the range checks.
    if v.is_nan() || v.abs() >= 9.0e18 {
        return v;
    }
    let t = v as i64 as f64;
    if t > v { t - 1.0 } else { t }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> VoxelConfig {
        VoxelConfig {
            enabled: true,
            extent_m: Some([100.0, 200.0, 164.0, 232.0]),
            z_range_m: [0.0, 3.0],
            tile_columns: 16,
            ..VoxelConfig::default()
        }
    }

    #[test]
    fn grid_snaps_the_extent_to_tiles_on_the_anchor() {
        let g = Grid::new(&cfg(), [0.0, 0.0]);
        assert_eq!(g.levels, 20, "3 m / 0.15 m");
        assert_eq!(g.tile_m(), [8.0, 8.0]);
        assert_eq!(g.tile_min, [12, 25]);
        assert_eq!(g.tiles, [9, 4], "x 96..168, y 200..232");
        assert_eq!(g.shape(), [20, 64, 144]);
        assert_eq!(g.extent_origin(), [96.0, 200.0]);
    }

    #[test]
    fn placer_maps_positions_to_tiles_and_offsets() {
        let g = Grid::new(&cfg(), [0.0, 0.0]);
        let p = Placer::new(&g);
        let c = p.column(100.26, 200.74).unwrap();
        assert_eq!(c, [200, 401]);
        let k = p.level(0.31).unwrap();
        assert_eq!(k, 2);
        let v = p.voxel(c, k);
        assert_eq!(v.tile, [12, 25]);
        assert_eq!(v.offset, (16 + 8) * 20 + 2, "(j·T + i)·L + k");
        assert_eq!(p.column_centre(c), [100.25, 200.75]);
        assert!(
            p.column(95.9, 210.0).is_none(),
            "west of the snapped extent"
        );
        assert!(p.column(f64::NAN, 210.0).is_none());
        assert!(p.level(3.0).is_none() && p.level(-0.01).is_none());
        assert!(p.level(f64::INFINITY).is_none());
    }

    #[test]
    fn negative_coordinates_use_floor_division() {
        let c = VoxelConfig {
            extent_m: Some([-20.0, -20.0, 20.0, 20.0]),
            ..cfg()
        };
        let g = Grid::new(&c, [0.0, 0.0]);
        let p = Placer::new(&g);
        let col = p.column(-0.1, -8.1).unwrap();
        assert_eq!(col, [-1, -17]);
        let v = p.voxel(col, 0);
        assert_eq!(v.tile, [-1, -2]);
        assert_eq!(v.offset, (15 * 16 + 15) * 20);
        for v in [-2.5, -2.0, -0.0, 0.0, 0.3, 7.0, 1e12 + 0.5, -1e12 - 0.5] {
            assert_eq!(fast_floor(v), v.floor(), "{v}");
        }
    }

    #[test]
    fn union_and_compatibility() {
        let a = Grid::new(&cfg(), [0.0, 0.0]);
        let b = Grid::new(
            &VoxelConfig {
                extent_m: Some([300.0, 100.0, 310.0, 110.0]),
                ..cfg()
            },
            [0.0, 0.0],
        );
        a.compatible(&b).unwrap();
        let u = a.union(&b);
        assert_eq!(u.tile_min, [12, 12]);
        assert_eq!(u.tiles, [39 - 12, 29 - 12]);
        let c = Grid::new(
            &VoxelConfig {
                voxel_size_m: [1.0, 1.0, 0.15],
                ..cfg()
            },
            [0.0, 0.0],
        );
        assert!(a.compatible(&c).unwrap_err().contains("voxel sizes"));
    }

    #[test]
    fn validation_names_the_fields() {
        let bad = VoxelConfig {
            voxel_size_m: [0.5, 0.0, 0.15],
            z_range_m: [5.0, 1.0],
            tile_columns: 4096,
            max_open_mib: 0,
            shard_tiles: 300,
            ..VoxelConfig::default()
        };
        let mut v = Validator::default();
        bad.validate("voxels", &mut v);
        let text = format!("{v:?}");
        assert!(text.contains("voxels.voxel_size_m[1]"), "{text}");
        assert!(text.contains("voxels.z_range_m"), "{text}");
        assert!(text.contains("voxels.max_open_mib"), "{text}");
        assert!(text.contains("voxels.shard_tiles"), "{text}");
        let mut v = Validator::default();
        VoxelConfig::default().validate("voxels", &mut v);
        assert!(!format!("{v:?}").contains("max_open_mib"));
    }
}
