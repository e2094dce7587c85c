//! Voxel tiles as a Zarr v3 store (`voxels.zarr`): per tile one chunk per height chunk that
//! holds data, written atomically.
//!
//! Layout (Zarr v3 core specification; CF conventions so that `xarray.open_zarr` gives named
//! dimensions, coordinates and the CRS; the root's `consolidated_metadata` as zarr-python 3
//! writes it, so that readers find every array in one document):
//!
//! ```text
//! voxels.zarr/zarr.json                 group: CRS (crs_wkt, epsg), origin, voxel size, units,
//!                                       the processing configuration, the grid (attributes);
//!                                       consolidated metadata of every node below
//! voxels.zarr/intensity_sum/            int64 [z, y, x], CF scale_factor = intensity quantum
//! voxels.zarr/sample_count/             uint32: bins deposited
//! voxels.zarr/intensity_max/            float32: largest bin (NaN: none)
//! voxels.zarr/pulse_count/              uint32: pulses whose beam passed through
//! voxels.zarr/{x,y,z}/                  float64 voxel centres, metres
//! voxels.zarr/spatial_ref/              0-d CF grid mapping holding the WKT
//! voxels.zarr/fwlidar_state/tiles/TX_TY the tile's watermark record (resume; see below)
//! ```
//!
//! Every data array has chunk shape `[H, T, T]` (`H` = the grid's `chunk_levels`): a chunk is
//! the `T × T` columns of one tile over `H` levels, chunk key `c/LEV/ROW/COL`. Only chunks that
//! hold a deposit exist; a missing chunk is all fill value (Zarr's rule, which zarr-python and
//! xarray follow), so empty air is neither held in memory nor compressed nor written.
//!
//! **Sharding** ([`Layout`]). Each chunk file is a shard (Zarr v3 `sharding_indexed`): inner
//! chunks of `[H, B, B]` voxels (`B` = [`INNER_COLUMNS`], 8, or the largest divisor of `T`
//! below it), each `bytes` (little endian) then `zstd` level 1, back to back, then the index:
//! per inner chunk in C order `(offset, nbytes)` as little-endian `u64`, `2^64 − 1` twice for
//! an inner chunk not stored (`index_codecs [bytes]`, stated in the metadata; no checksum,
//! which zarr-python 3 accepts; a `crc32c` index is read too). An inner chunk is stored when a
//! sample or a pass landed in it, decided for the four arrays together, so a sparse flight line
//! compresses and writes the few blocks of columns its pulses touched, not the whole tile.
//! Stores of earlier versions — one `bytes` + `zstd` (or `gzip`) chunk per file — are read,
//! merged and resumed in their own layout (the array metadata says which).
//!
//! **The arrays' span** ([`Span`]): chunk `(LEV, ROW, COL)` is height chunk
//! `span.level_chunk_min + LEV` of tile `span.tile_min + (COL, ROW)`.
//! While a run writes, the span is the grid's whole extent (fixed, so a tile's chunk key never
//! changes under the writer); when the run ends, [`ZarrStore::fit`] shrinks it to the bounding
//! box of the tiles and height chunks written, which is what a reader sees of a finished store. Reopening a store
//! to write puts it back on the extent. A change of span moves every tile's chunks: first into
//! `fwlidar_state/staging/` (named by tile and height chunk, so nothing is ambiguous), then the metadata is
//! rewritten, then the chunks go to their new keys; a journal (`fwlidar_state/relayout`, the
//! target span) written before the first move lets the next open finish a move cut short.
//!
//! **Crash safety.** A tile's chunks (four arrays × its height chunks; each a whole shard) are written under
//! `KEY.pending` and synced (one `syncfs` on Linux); then its record `fwlidar_state/tiles/TX_TY`
//! is replaced atomically by `{watermark, chunks, pending: true}` (the commit point; `chunks`
//! lists the height chunks the tile holds, ascending); then the pending chunks are renamed into
//! place and the record rewritten with `pending: false`. A tile written again holds every
//! height chunk it held before (it is read back and merged), so no chunk is left behind. Opening a store completes any committed tile whose renames were cut
//! short and deletes pending chunks that were never committed, so every tile is either its old
//! or its new content, never a mix. The **watermark** is the sequence number of the first pulse
//! not yet in the tile: a tile holds exactly the deposits of pulses numbered below it (pulses
//! reach the voxeliser in order), so a rerun of the same input skips, tile by tile, what is
//! already there, and ends with the same bits as an uninterrupted run.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::{self, File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use flate2::Compression;
use flate2::read::GzDecoder;
use flate2::write::GzEncoder;
use serde_json::{Value, json};

use super::grid::Grid;
use super::shard_group::{Batch, Journal, JournalTile, ShardGroup};
pub use super::shard_group::{INNER_COLUMNS, LayoutChoice};
use super::tile::TileData;

/// Names of the data arrays, in the order their chunks are written.
pub const ARRAYS: [&str; 4] = [
    "intensity_sum",
    "sample_count",
    "intensity_max",
    "pulse_count",
];

/// Errors of the tile store; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A file of the store is not what this program writes.
    #[error("{path}: {what}")]
    Invalid {
        /// The file.
        path: String,
        /// What is wrong, naming the field.
        what: String,
    },
    /// The store holds another grid or another run's tiles; nothing was changed.
    #[error(
        "{path}: {what}; nothing was changed (choose another output, or combine stores with `fwlidar merge`)"
    )]
    Mismatch {
        /// The store.
        path: String,
        /// What differs.
        what: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.display().to_string(),
        source,
    }
}

fn invalid(path: &Path, what: impl Into<String>) -> StoreError {
    StoreError::Invalid {
        path: path.display().to_string(),
        what: what.into(),
    }
}

/// What the store records about its contents besides the grid.
#[derive(Clone, Debug, PartialEq)]
pub struct StoreInfo {
    /// The output CRS as OGC WKT, when known.
    pub crs_wkt: Option<String>,
    /// Its EPSG code, when known.
    pub epsg: Option<u32>,
    /// Units of the deposited intensity (`V`, or the calibrated backscatter's).
    pub intensity_units: String,
    /// Identifies the run that writes the store (input and configuration); a rerun resumes only
    /// a store with the same identity. Empty for merged stores.
    pub run_key: String,
    /// The processing configuration (TOML text), recorded as an attribute.
    pub configuration: String,
}

/// The tiles the data arrays span: chunk `(row, col)` of every data array holds tile
/// `(tile_min[0] + col, tile_min[1] + row)`; the arrays are `tiles[1]·T` rows (y) by
/// `tiles[0]·T` columns (x) of voxels. Recorded in the root's attributes as `fwlidar.arrays`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Span {
    /// The tile `[tx, ty]` (global numbering) in chunk `(0, 0)`.
    pub tile_min: [i64; 2],
    /// Tiles along `[x, y]` (0 when the store holds none).
    pub tiles: [u32; 2],
    /// The height chunk (of the grid's, counted from its bottom) in chunk level 0.
    #[serde(default)]
    pub level_chunk_min: u32,
    /// Height chunks spanned (0 when the store holds none).
    #[serde(default = "one")]
    pub level_chunks: u32,
    /// The span is the bounding box of the tiles written (a run or a merge ended), not the
    /// grid's whole extent (a run is writing, or was killed).
    pub fitted: bool,
}

impl Span {
    /// The grid's whole extent: the span while a run writes.
    pub fn extent(grid: &Grid) -> Span {
        Span {
            tile_min: grid.tile_min,
            tiles: grid.tiles,
            level_chunk_min: 0,
            level_chunks: grid.height_chunks(),
            fitted: false,
        }
    }

    /// The bounding box of `tiles`, each with the height chunks it holds (none: an empty span
    /// at the extent's corner).
    pub fn around<'a>(grid: &Grid, tiles: impl IntoIterator<Item = ([i64; 2], &'a [u32])>) -> Span {
        let mut b = [i64::MAX, i64::MAX, i64::MIN, i64::MIN];
        let (mut klo, mut khi) = (u32::MAX, 0u32);
        for (t, chunks) in tiles {
            b = [
                b[0].min(t[0]),
                b[1].min(t[1]),
                b[2].max(t[0]),
                b[3].max(t[1]),
            ];
            for &k in chunks {
                klo = klo.min(k);
                khi = khi.max(k);
            }
        }
        if b[0] > b[2] {
            return Span {
                tile_min: grid.tile_min,
                tiles: [0, 0],
                level_chunk_min: 0,
                level_chunks: 0,
                fitted: true,
            };
        }
        if klo > khi {
            // Tiles without any chunk (nothing deposited): one height chunk at the bottom.
            (klo, khi) = (0, 0);
        }
        let n = |lo: i64, hi: i64| (hi as i128 - lo as i128 + 1).clamp(0, u32::MAX as i128) as u32;
        Span {
            tile_min: [b[0], b[1]],
            tiles: [n(b[0], b[2]), n(b[1], b[3])],
            level_chunk_min: klo,
            level_chunks: khi - klo + 1,
            fitted: true,
        }
    }

    /// Whether the arrays cover the same tiles and height chunks (fitted or not).
    pub fn same_tiles(&self, other: &Span) -> bool {
        self.tile_min == other.tile_min
            && self.tiles == other.tiles
            && self.level_chunk_min == other.level_chunk_min
            && self.level_chunks == other.level_chunks
    }

    /// Chunk level (of the arrays) of the grid's height chunk `kc`, if the span holds it.
    pub fn level_of(&self, kc: u32) -> Option<u32> {
        kc.checked_sub(self.level_chunk_min)
            .filter(|l| *l < self.level_chunks)
    }

    /// Chunk indices `[row, column]` of a tile, if the span holds it.
    pub fn chunk_of(&self, tile: [i64; 2]) -> Option<[u64; 2]> {
        let off = |a: usize| {
            let d = tile[a] as i128 - self.tile_min[a] as i128;
            (0..self.tiles[a] as i128).contains(&d).then_some(d as u64)
        };
        Some([off(1)?, off(0)?])
    }

    /// Whether the span holds `tile`.
    pub fn contains(&self, tile: [i64; 2]) -> bool {
        self.chunk_of(tile).is_some()
    }

    /// The data arrays' shape `[levels, rows (y), columns (x)]` (levels from the bottom of
    /// height chunk `level_chunk_min`, to the grid's top at most).
    pub fn shape(&self, grid: &Grid) -> [u64; 3] {
        let t = grid.tile_columns as u64;
        let h = grid.chunk_levels() as u64;
        let below = self.level_chunk_min as u64 * h;
        [
            (self.level_chunks as u64 * h).min((grid.levels as u64).saturating_sub(below)),
            self.tiles[1] as u64 * t,
            self.tiles[0] as u64 * t,
        ]
    }

    /// Bottom of the arrays' first level, metres.
    pub fn z_bottom_m(&self, grid: &Grid) -> f64 {
        grid.z_bottom_m
            + (self.level_chunk_min as u64 * grid.chunk_levels() as u64) as f64
                * grid.voxel_size_m[2]
    }

    /// West and south edges of the arrays (of chunk `(0, 0)`), metres.
    pub fn origin_m(&self, grid: &Grid) -> [f64; 2] {
        let tm = grid.tile_m();
        [
            grid.origin_m[0] + self.tile_min[0] as f64 * tm[0],
            grid.origin_m[1] + self.tile_min[1] as f64 * tm[1],
        ]
    }
}

fn one() -> u32 {
    1
}

/// Per tile: the watermark, its height chunks, and whether a commit is incomplete.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileRecord {
    /// First pulse sequence number not in the tile.
    pub watermark: u64,
    /// Height chunks the tile holds (grid numbering, ascending).
    pub chunks: Vec<u32>,
    /// The tile's chunks are being renamed into place.
    pub pending: bool,
}

impl TileRecord {
    fn json(&self) -> Vec<u8> {
        json!({"watermark": self.watermark, "chunks": self.chunks, "pending": self.pending})
            .to_string()
            .into_bytes()
    }
}

/// How chunks are compressed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Codec {
    /// Zarr's `zstd` codec at this level (what this version writes).
    Zstd(i32),
    /// Zarr's `gzip` codec at this level (stores of earlier versions).
    Gzip(u32),
}

impl Codec {
    /// The codec this version writes: zstd level 1 (see docs/architecture.md for the measured
    /// reason).
    pub const WRITE: Codec = Codec::Zstd(1);

    fn meta(self) -> Value {
        match self {
            Codec::Zstd(level) => {
                json!({"name": "zstd", "configuration": {"level": level, "checksum": false}})
            }
            Codec::Gzip(level) => json!({"name": "gzip", "configuration": {"level": level}}),
        }
    }

    fn of_meta(v: &Value) -> Option<Codec> {
        let codecs = v.get("codecs")?.as_array()?;
        codecs.iter().find_map(|c| {
            let level = c.get("configuration").and_then(|x| x.get("level"));
            match c.get("name")?.as_str()? {
                "zstd" => Some(Codec::Zstd(
                    level.and_then(Value::as_i64).unwrap_or(1) as i32
                )),
                "gzip" => Some(Codec::Gzip(
                    level.and_then(Value::as_u64).unwrap_or(1) as u32
                )),
                _ => None,
            }
        })
    }

    fn encode(self, raw: &[u8], out: &mut Vec<u8>) -> std::io::Result<()> {
        out.clear();
        match self {
            Codec::Zstd(level) => {
                let mut enc = zstd::stream::Encoder::new(std::mem::take(out), level)?;
                enc.include_contentsize(true)?;
                enc.set_pledged_src_size(Some(raw.len() as u64))?;
                enc.write_all(raw)?;
                *out = enc.finish()?;
            }
            Codec::Gzip(level) => {
                let mut enc = GzEncoder::new(std::mem::take(out), Compression::new(level));
                enc.write_all(raw)?;
                *out = enc.finish()?;
            }
        }
        Ok(())
    }

    /// Compresses `raw` into `out` (cleared), zstd with a context of `zc` (made on first use
    /// and reused: an inner chunk is small, a fresh context each would cost more than the
    /// data). A block of at most [`SPARSE_BLOCK_COLUMNS`] written columns (`written`) is
    /// compressed with its literals stored raw (see [`BlockCompressors`]).
    fn encode_block(
        self,
        zc: &mut BlockCompressors,
        written: u32,
        raw: &[u8],
        out: &mut Vec<u8>,
    ) -> std::io::Result<()> {
        match self {
            Codec::Zstd(level) => {
                let (slot, level) = if written <= SPARSE_BLOCK_COLUMNS {
                    (&mut zc.raw_literals, RAW_LITERALS_LEVEL)
                } else {
                    (&mut zc.entropy, level)
                };
                let c = match slot {
                    Some(c) => c,
                    None => slot.insert(zstd::bulk::Compressor::new(level)?),
                };
                out.clear();
                out.reserve(zstd::zstd_safe::compress_bound(raw.len()));
                c.compress_to_buffer(raw, out)?;
                Ok(())
            }
            Codec::Gzip(_) => self.encode(raw, out),
        }
    }

    /// Decompresses `packed` into `out` (cleared), which must come to `expect` bytes (more is
    /// an error, and never allocated).
    fn decode_block(
        self,
        zd: &mut Option<zstd::bulk::Decompressor<'static>>,
        packed: &[u8],
        expect: usize,
        out: &mut Vec<u8>,
    ) -> std::io::Result<()> {
        out.clear();
        out.reserve(expect);
        match self {
            Codec::Zstd(_) => {
                let d = match zd {
                    Some(d) => d,
                    None => zd.insert(zstd::bulk::Decompressor::new()?),
                };
                d.decompress_to_buffer(packed, out)?;
            }
            Codec::Gzip(_) => {
                GzDecoder::new(packed)
                    .take(expect as u64 + 1)
                    .read_to_end(out)?;
            }
        }
        if out.len() != expect {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("{} bytes, an inner chunk needs {expect}", out.len()),
            ));
        }
        Ok(())
    }

    fn decode(self, file: File, out: &mut Vec<u8>) -> std::io::Result<()> {
        out.clear();
        match self {
            Codec::Zstd(_) => {
                zstd::stream::Decoder::new(file)?.read_to_end(out)?;
            }
            Codec::Gzip(_) => {
                GzDecoder::new(file).read_to_end(out)?;
            }
        }
        Ok(())
    }
}

/// How the data arrays' chunks are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// Each chunk one compressed block (stores of earlier versions).
    Plain(Codec),
    /// Each chunk a shard (Zarr's `sharding_indexed` codec, what this version writes): inner
    /// chunks of `[H, inner, inner]` voxels in C order, each `bytes` (little endian) then
    /// `codec`, absent when none of the voxel's four arrays holds anything in it; then the index,
    /// `(offset, nbytes)` as little-endian `u64` per inner chunk (`2^64 − 1` twice: absent),
    /// followed by its CRC-32C when `index_crc`.
    Sharded {
        /// Columns along each side of an inner chunk (divides `T`).
        inner: u32,
        /// Compression of each inner chunk.
        codec: Codec,
        /// The index ends with its CRC-32C (Zarr's `crc32c` index codec).
        index_crc: bool,
        /// Tiles grouped into one shard per array, each tile's height chunk an inner shard of
        /// it (`shard_group`); `None`: a shard per tile and height chunk.
        group: Option<ShardGroup>,
        /// Each inner chunk is stored column by column (Zarr's `transpose` codec, order
        /// `[1, 2, 0]`: `[y, x, z]`, a column's levels contiguous) rather than in `[z, y, x]`
        /// order. What this version writes: a beam fills a column, so its levels stay
        /// together — on the sparse 7.2 km line the store is 25 % smaller and zstd's work 11 %
        /// less (docs/performance.md).
        transposed: bool,
    },
}

/// A chunk shape from metadata (empty when absent or not a list of integers).
fn shape_of(v: Option<&Value>) -> Vec<u64> {
    v.and_then(Value::as_array)
        .map(|a| a.iter().filter_map(Value::as_u64).collect())
        .unwrap_or_default()
}

/// The names of a `sharding_indexed` configuration's index codecs, if it lists them.
fn index_codec_names(cfg: &Value) -> Option<Vec<&str>> {
    cfg.get("index_codecs").and_then(Value::as_array).map(|a| {
        a.iter()
            .filter_map(|c| c.get("name").and_then(Value::as_str))
            .collect()
    })
}

/// Greatest common divisor (both positive).
fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 { a } else { gcd(b, a % b) }
}

impl Layout {
    /// The layout this version writes on `grid`: shards of `INNER_COLUMNS`-wide inner chunks,
    /// zstd level 1, the index without a checksum (zarr-python 3 reads `[bytes]` alone).
    pub fn for_grid(grid: &Grid) -> Layout {
        Layout::Sharded {
            inner: gcd(grid.tile_columns.max(1), INNER_COLUMNS),
            codec: Codec::WRITE,
            index_crc: false,
            group: None,
            transposed: true,
        }
    }

    /// The layout this version writes on `grid` as `choice` says: tiles grouped or not, inner
    /// chunks of `gcd(T, choice.inner_columns)` columns a side (as [`for_grid`](Self::for_grid)
    /// with the default choice).
    pub fn chosen(grid: &Grid, choice: LayoutChoice) -> Layout {
        let group = choice.group.filter(|g| g.tiles > 0 && g.height_chunks > 0);
        let inner = gcd(grid.tile_columns.max(1), choice.inner_columns.max(1));
        match Layout::for_grid(grid) {
            Layout::Sharded {
                codec,
                index_crc,
                transposed,
                ..
            } => Layout::Sharded {
                inner,
                codec,
                index_crc,
                group,
                transposed,
            },
            plain => plain,
        }
    }

    /// The grouping of tiles into shards, if any.
    pub fn group(self) -> Option<ShardGroup> {
        match self {
            Layout::Sharded { group, .. } => group,
            Layout::Plain(_) => None,
        }
    }

    /// The layout of one tile's height chunk (the grouping left out).
    fn tile_shard(self) -> Layout {
        match self {
            Layout::Sharded {
                inner,
                codec,
                index_crc,
                transposed,
                ..
            } => Layout::Sharded {
                inner,
                codec,
                index_crc,
                group: None,
                transposed,
            },
            plain => plain,
        }
    }

    /// The data arrays' chunk shape `[z, y, x]` (a shard's).
    fn chunk_shape(self, grid: &Grid) -> [u64; 3] {
        let (h, t) = (grid.chunk_levels() as u64, grid.tile_columns as u64);
        match self.group() {
            Some(g) => [
                h * g.height_chunks as u64,
                t * g.tiles as u64,
                t * g.tiles as u64,
            ],
            None => [h, t, t],
        }
    }

    /// The compression of the data (of each inner chunk when sharded); the coordinates use it.
    pub fn codec(self) -> Codec {
        match self {
            Layout::Plain(c) | Layout::Sharded { codec: c, .. } => c,
        }
    }

    /// Columns along each side of the blocks a chunk is encoded in (`T` when not sharded).
    fn block(self, grid: &Grid) -> usize {
        match self {
            Layout::Plain(_) => grid.tile_columns as usize,
            Layout::Sharded { inner, .. } => inner as usize,
        }
    }

    /// The data arrays' `codecs` metadata.
    fn meta(self, grid: &Grid) -> Value {
        let bytes = json!({"name": "bytes", "configuration": {"endian": "little"}});
        match self {
            Layout::Plain(c) => json!([bytes, c.meta()]),
            Layout::Sharded {
                inner,
                codec,
                index_crc,
                group,
                transposed,
            } => {
                let mut index = vec![bytes.clone()];
                let mut codecs = Vec::new();
                if transposed {
                    codecs
                        .push(json!({"name": "transpose", "configuration": {"order": [1, 2, 0]}}));
                }
                codecs.extend([bytes.clone(), codec.meta()]);
                if index_crc {
                    index.push(json!({"name": "crc32c"}));
                }
                let tile_shard = json!({
                    "name": "sharding_indexed",
                    "configuration": {
                        "chunk_shape": [grid.chunk_levels(), inner, inner],
                        "codecs": codecs,
                        "index_codecs": index,
                        "index_location": "end",
                    }
                });
                if group.is_none() {
                    return json!([tile_shard]);
                }
                let t = grid.tile_columns;
                json!([{
                    "name": "sharding_indexed",
                    "configuration": {
                        "chunk_shape": [grid.chunk_levels(), t, t],
                        "codecs": [tile_shard],
                        "index_codecs": [bytes],
                        "index_location": "end",
                    }
                }])
            }
        }
    }

    /// The layout an array's metadata `v` states, for chunks of `grid`; what is not understood
    /// is named.
    fn of_meta(v: &Value, grid: &Grid) -> Result<Layout, String> {
        let codecs = v
            .get("codecs")
            .and_then(Value::as_array)
            .ok_or("no `codecs` list")?;
        let Some(shard) = codecs
            .iter()
            .find(|c| c.get("name").and_then(Value::as_str) == Some("sharding_indexed"))
        else {
            return Codec::of_meta(v)
                .map(Layout::Plain)
                .ok_or_else(|| "codecs: neither zstd nor gzip nor sharding_indexed".into());
        };
        let cfg = shard
            .get("configuration")
            .ok_or("sharding_indexed: no `configuration`")?;
        let nested = cfg.get("codecs").and_then(Value::as_array).and_then(|c| {
            c.iter()
                .find(|c| c.get("name").and_then(Value::as_str) == Some("sharding_indexed"))
        });
        let Some(tile_shard) = nested else {
            let (inner, codec, index_crc, transposed) = Self::of_shard(cfg, grid)?;
            return Ok(Layout::Sharded {
                inner,
                codec,
                index_crc,
                group: None,
                transposed,
            });
        };
        // Tiles grouped: the array's chunk is the group, the outer shard's inner chunk a tile's
        // height chunk, itself a shard.
        let (h, t) = (grid.chunk_levels() as u64, grid.tile_columns as u64);
        let outer = shape_of(cfg.get("chunk_shape"));
        if outer != [h, t, t] {
            return Err(format!(
                "sharding_indexed.chunk_shape {outer:?}: not a tile's height chunk [{h}, {t}, {t}]"
            ));
        }
        let names = index_codec_names(cfg).unwrap_or_default();
        if names != ["bytes"] || cfg.get("index_location").and_then(Value::as_str) != Some("end") {
            return Err(format!(
                "sharding_indexed.index_codecs {names:?}: the grouped layout's index is `bytes` at \
                 the end"
            ));
        }
        let grid_shape = shape_of(
            v.get("chunk_grid")
                .and_then(|g| g.get("configuration"))
                .and_then(|c| c.get("chunk_shape")),
        );
        let group = match grid_shape[..] {
            [z, y, x] if y == x && z > 0 && y > 0 && z % h == 0 && y % t == 0 => ShardGroup {
                tiles: u32::try_from(y / t).map_err(|_| "chunk_grid too large")?,
                height_chunks: u32::try_from(z / h).map_err(|_| "chunk_grid too large")?,
            },
            _ => {
                return Err(format!(
                    "chunk_grid.chunk_shape {grid_shape:?}: not whole tiles' height chunks"
                ));
            }
        };
        let inner_cfg = tile_shard
            .get("configuration")
            .ok_or("sharding_indexed.codecs.sharding_indexed: no `configuration`")?;
        let (inner, codec, index_crc, transposed) = Self::of_shard(inner_cfg, grid)?;
        Ok(Layout::Sharded {
            inner,
            codec,
            index_crc,
            group: Some(group),
            transposed,
        })
    }

    /// The inner chunk width, codec, index checksum and column order (`transpose`) of a tile's
    /// height-chunk shard, from its `sharding_indexed` configuration `cfg`.
    fn of_shard(cfg: &Value, grid: &Grid) -> Result<(u32, Codec, bool, bool), String> {
        let shape = shape_of(cfg.get("chunk_shape"));
        let t = grid.tile_columns as u64;
        let inner = match shape[..] {
            [h, a, b]
                if h == grid.chunk_levels() as u64 && a == b && a > 0 && t.is_multiple_of(a) =>
            {
                a
            }
            _ => {
                return Err(format!(
                    "sharding_indexed.chunk_shape {shape:?}: not [{}, b, b] with b dividing {t}",
                    grid.chunk_levels()
                ));
            }
        };
        let codec = Codec::of_meta(cfg)
            .ok_or("sharding_indexed.codecs: neither zstd nor gzip".to_string())?;
        let names = index_codec_names(cfg).unwrap_or_else(|| vec!["bytes", "crc32c"]);
        let endian = cfg
            .get("index_codecs")
            .and_then(Value::as_array)
            .and_then(|a| a.first())
            .and_then(|c| c.get("configuration"))
            .and_then(|c| c.get("endian"))
            .and_then(Value::as_str)
            .unwrap_or("little");
        let index_crc = match (&names[..], endian) {
            (["bytes"], "little") => false,
            (["bytes", "crc32c"], "little") => true,
            _ => {
                return Err(format!(
                    "sharding_indexed.index_codecs {names:?} ({endian} endian): not bytes \
                     (little endian) with an optional crc32c"
                ));
            }
        };
        let location = cfg
            .get("index_location")
            .and_then(Value::as_str)
            .unwrap_or("end");
        if location != "end" {
            return Err(format!(
                "sharding_indexed.index_location {location:?}: only \"end\" is read"
            ));
        }
        let transposed = match cfg.get("codecs").and_then(Value::as_array).and_then(|c| {
            c.iter()
                .find(|c| c.get("name").and_then(Value::as_str) == Some("transpose"))
        }) {
            None => false,
            Some(t) => {
                let order = shape_of(t.get("configuration").and_then(|c| c.get("order")));
                if order != [1, 2, 0] {
                    return Err(format!(
                        "sharding_indexed.codecs.transpose.order {order:?}: only [1, 2, 0] (a \
                         column's levels contiguous) is read"
                    ));
                }
                true
            }
        };
        Ok((inner as u32, codec, index_crc, transposed))
    }
}

/// Inner chunks of at most this many written columns (of 64) are compressed with their
/// literals stored raw: building a Huffman table per chunk costs the same whatever the chunk
/// holds, and a few columns' values gain a few bytes from it. Measured on the sparse 7.2 km
/// line and the dense survey line (docs/performance.md, "Raw literals for sparse inner
/// chunks").
const SPARSE_BLOCK_COLUMNS: u32 = 8;

/// zstd's level −1: level 1's fast match finder with literals left uncompressed (zstd turns
/// literal compression off at negative levels), a standard zstd frame any reader decodes.
const RAW_LITERALS_LEVEL: i32 = -1;

/// The store's reused zstd compression contexts: one at the codec's level, one for sparse
/// inner chunks at [`RAW_LITERALS_LEVEL`].
#[derive(Default)]
struct BlockCompressors {
    entropy: Option<zstd::bulk::Compressor<'static>>,
    raw_literals: Option<zstd::bulk::Compressor<'static>>,
    /// A sparse block's frame made from its runs of values, without the library (see
    /// [`super::fill_frame`]).
    fill: super::fill_frame::FillFrame,
}

/// Coordinate arrays of more values than this (together) are compressed and written on a
/// thread of their own: a new store spans the whole extent (2 000 032 columns each way at the
/// default 1 000 km and 0.5 m), whose x and y coordinates took ~95 ms of the sink thread
/// through zstd — most of the replay of a 64-shot GEDI granule. A store killed before they
/// land has its coordinate metadata without the chunk; opening it writes them again.
const COORDINATES_IN_BACKGROUND: usize = 1 << 20;

/// An open store.
pub struct ZarrStore {
    root: PathBuf,
    grid: Grid,
    info: StoreInfo,
    /// Reused encode/decode buffers.
    raw: Vec<u8>,
    packed: Vec<u8>,
    /// One shard as it is assembled or read.
    shard: Vec<u8>,
    /// Per block of a height chunk: its written columns (0: nothing to store; the four
    /// arrays together).
    blocks: Vec<u32>,
    /// Reused zstd contexts.
    zc: BlockCompressors,
    /// Coordinate chunks being written on a thread of their own (see
    /// [`COORDINATES_IN_BACKGROUND`]); joined before the metadata is written again and when
    /// the store is dropped.
    coordinates: Option<std::thread::JoinHandle<Result<(), StoreError>>>,
    zd: Option<zstd::bulk::Decompressor<'static>>,
    /// Other stores' shard files open while their tiles are copied in (a merge's inputs).
    sources: super::shard_group::OpenShards,
    /// The tiles the data arrays span.
    span: Span,
    /// How chunks are laid out and compressed.
    layout: Layout,
    /// Committed tiles: watermark and height chunks.
    records: HashMap<[i64; 2], (u64, Vec<u32>)>,
    /// Tiles written (for the summary).
    pub tiles_written: u64,
    /// Chunk (shard) files written (all four arrays).
    pub chunks_written: u64,
    /// Inner chunks encoded (all four arrays; equal to `chunks_written` when not sharded).
    pub inner_chunks_written: u64,
    /// Bytes of uncompressed chunk data written (what went through the compressor).
    pub bytes_written: u64,
    /// Bytes of compressed chunk data written (on disk).
    pub bytes_stored: u64,
    /// Committed tiles whose renames a previous run left unfinished, completed on open.
    pub recovered_commits: u64,
    /// Uncommitted pending chunks of a previous run, deleted on open.
    pub discarded_pending: u64,
    /// Each tile made durable when written (the commit protocol); off for a store that is
    /// written whole and renamed into place when complete ([`ZarrStore::unsynced`]).
    durable: bool,
    /// Tiles grouped into shards: per group `[gx, gy]`, the shards being assembled.
    groups: HashMap<[i64; 2], GroupBuffer>,
    /// Bytes the groups being assembled hold.
    buffered_bytes: usize,
    /// Past this many buffered bytes every group is written.
    pub buffer_budget: usize,
    /// The journal of the grouped layout, shared with the [`tile_writer`](Self::tile_writer)
    /// handles.
    journal: Option<Journal>,
    /// Keep what each group write committed for [`take_committed`](Self::take_committed) (a
    /// writer thread's handle).
    reports: bool,
    /// Tiles made durable since [`take_committed`](Self::take_committed).
    committed: Vec<Committed>,
}

/// A group of tiles being assembled into its shards (the grouped layout).
#[derive(Default)]
struct GroupBuffer {
    /// Each tile's height-chunk shard by `(array, group height, place)`.
    places: BTreeMap<(usize, u32, usize), Vec<u8>>,
    /// The tiles written into it: watermark, height chunks, the encoding's cost.
    tiles: BTreeMap<[i64; 2], (u64, Vec<u32>, WriteCost)>,
    /// Bytes of `places`.
    bytes: usize,
}

/// A tile made durable by a writer handle, as [`ZarrStore::note_committed`] takes it.
#[derive(Clone, Debug)]
pub struct Committed {
    /// The tile.
    pub tile: [i64; 2],
    /// Its watermark.
    pub watermark: u64,
    /// Its height chunks.
    pub chunks: Vec<u32>,
    /// What writing it cost (a group's files and stored bytes on its first tile).
    pub cost: WriteCost,
}

/// Bytes of tiles buffered before every group is written, when nothing else says (256 MiB).
const BUFFER_BUDGET: usize = 256 << 20;

fn dtype(name: &str) -> (&'static str, Value) {
    match name {
        "intensity_sum" => ("int64", json!(0)),
        "sample_count" | "pulse_count" => ("uint32", json!(0)),
        _ => ("float32", json!("NaN")),
    }
}

/// Bytes of one value of data array `name`.
fn value_bytes(name: &str) -> usize {
    if name == "intensity_sum" { 8 } else { 4 }
}

fn write_file_synced(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut f = OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .open(path)
        .map_err(io(path))?;
    f.write_all(bytes).map_err(io(path))?;
    f.sync_all().map_err(io(path))
}

/// Writes `path` atomically: `path.partial`, sync, rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    write_file_synced(&tmp, bytes)?;
    fs::rename(&tmp, path).map_err(io(path))
}

fn sync_dir(path: &Path) {
    // Makes the renames durable; not every platform can open a directory, so best effort.
    if let Ok(d) = File::open(path) {
        let _ = d.sync_all();
    }
}

/// Makes the renames in `dirs` (folders of the store at `root`) durable. On Linux one
/// `syncfs` of the store's file system does it for all of them at once (a directory fsync costs
/// milliseconds however little changed, and a change of span touches a folder per row of tiles
/// per array); elsewhere, or if that fails, each folder is synced.
fn sync_dirs(root: &Path, dirs: &BTreeSet<PathBuf>) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        if let Ok(d) = File::open(root) {
            // SAFETY: `syncfs` only reads the descriptor, which `d` keeps open for the call.
            if unsafe { libc::syncfs(d.as_raw_fd()) } == 0 {
                return;
            }
        }
    }
    let _ = root;
    for d in dirs {
        sync_dir(d);
    }
}

impl ZarrStore {
    /// The store's folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The grid.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// What the store records.
    pub fn info(&self) -> &StoreInfo {
        &self.info
    }

    /// The tiles the data arrays span now.
    pub fn span(&self) -> &Span {
        &self.span
    }

    /// A store at `root` with nothing read or written yet, its arrays spanning `span`.
    fn at(root: &Path, grid: Grid, info: StoreInfo, span: Span) -> Self {
        let layout = Layout::for_grid(&grid);
        ZarrStore {
            root: root.to_path_buf(),
            grid,
            info,
            layout,
            span,
            raw: Vec::new(),
            packed: Vec::new(),
            shard: Vec::new(),
            blocks: Vec::new(),
            zc: BlockCompressors::default(),
            coordinates: None,
            zd: None,
            sources: Default::default(),
            records: Default::default(),
            tiles_written: 0,
            chunks_written: 0,
            inner_chunks_written: 0,
            bytes_written: 0,
            bytes_stored: 0,
            recovered_commits: 0,
            discarded_pending: 0,
            durable: true,
            groups: HashMap::new(),
            buffered_bytes: 0,
            buffer_budget: BUFFER_BUDGET,
            journal: None,
            reports: false,
            committed: Vec::new(),
        }
    }

    /// Writes tiles without making each durable (no sync per tile; the record written once):
    /// for a store that is written whole and then put in place (a merge into
    /// `mosaic.zarr.partial`), where a crash means starting again, not resuming. The files are
    /// the same bytes; call [`sync`](Self::sync) when done. Four syncs a tile cost ~4 ms each on
    /// this machine's disk, more than copying the tile (docs/performance.md).
    pub fn unsynced(mut self) -> Self {
        self.durable = false;
        self
    }

    /// Makes everything written so far durable: one `syncfs` of the store's file system on
    /// Linux, else a sync of the store's root folder.
    pub fn sync(&self) {
        if !syncfs(&self.root) {
            sync_dir(&self.root);
        }
    }

    /// Every tile of the store with its accumulators, in tile order (tests, small stores: one
    /// tile's memory each).
    pub fn read_all(&mut self) -> Result<Vec<([i64; 2], TileData)>, StoreError> {
        let mut out = Vec::new();
        for t in self.tiles() {
            let mut d = TileData::for_grid(&self.grid);
            self.read_tile(t, &mut d)?;
            out.push((t, d));
        }
        Ok(out)
    }

    /// Creates the store at `root`, or opens the one there when it was written by the same run
    /// on the same grid (a resumed run): committed but unfinished tiles are completed and
    /// uncommitted chunks removed. Another grid or run is refused without changing anything.
    /// Either way the arrays span the grid's whole extent until [`fit`](Self::fit).
    pub fn create_or_open(root: &Path, grid: Grid, info: StoreInfo) -> Result<Self, StoreError> {
        Self::create_or_open_grouped(root, grid, info, None)
    }

    /// [`create_or_open`](Self::create_or_open), a new store laid out as `choice` says (tiles
    /// grouped into shards, `shard_group`; the inner chunks' width); a store reopened keeps its
    /// own layout.
    pub fn create_or_open_grouped(
        root: &Path,
        grid: Grid,
        info: StoreInfo,
        choice: impl Into<LayoutChoice>,
    ) -> Result<Self, StoreError> {
        let choice = choice.into();
        let meta = root.join("zarr.json");
        if meta.exists() {
            let mut s = ZarrStore::open(root)?;
            if let Err(what) = s.grid.compatible(&grid) {
                return Err(StoreError::Mismatch {
                    path: root.display().to_string(),
                    what: format!("the store's grid differs from this run's: {what}"),
                });
            }
            if s.grid.tile_min != grid.tile_min || s.grid.tiles != grid.tiles {
                return Err(StoreError::Mismatch {
                    path: root.display().to_string(),
                    what: format!(
                        "the store covers tiles {:?} + {:?}, this run {:?} + {:?}",
                        s.grid.tile_min, s.grid.tiles, grid.tile_min, grid.tiles
                    ),
                });
            }
            if s.info.run_key != info.run_key {
                return Err(StoreError::Mismatch {
                    path: root.display().to_string(),
                    what: format!(
                        "the store was written by another run ({}), not this one ({})",
                        s.info.run_key, info.run_key
                    ),
                });
            }
            s.info = info;
            s.relayout(Span::extent(&grid))?;
            return Ok(s);
        }
        if root.exists() && fs::read_dir(root).map_err(io(root))?.next().is_some() {
            return Err(StoreError::Mismatch {
                path: root.display().to_string(),
                what: "the folder exists, is not empty and is not a voxel store".into(),
            });
        }
        ZarrStore::create_new(root, grid, info, choice, None)
    }

    /// Creates a store whose arrays span, from the start, the bounding box of `tiles` (each
    /// with its height chunks; aligned to shard groups as [`fit`](Self::fit) would): a merge
    /// knows every tile it will write before it writes one, so its `fit` at the end moves
    /// nothing and a new store's extent-wide coordinates are never written. `root` must not
    /// exist or be empty. Writing a tile outside the span is refused.
    pub fn create_on_tiles<'a>(
        root: &Path,
        grid: Grid,
        info: StoreInfo,
        choice: impl Into<LayoutChoice>,
        tiles: impl IntoIterator<Item = ([i64; 2], &'a [u32])>,
    ) -> Result<Self, StoreError> {
        if fs::read_dir(root).is_ok_and(|mut d| d.next().is_some()) {
            return Err(StoreError::Mismatch {
                path: root.display().to_string(),
                what: "the folder exists and is not empty".into(),
            });
        }
        let span = Span::around(&grid, tiles);
        ZarrStore::create_new(root, grid, info, choice.into(), Some(span))
    }

    /// Creates a new store in `root` (checked to be absent or empty) on `span` (aligned to
    /// the layout's groups), or on the whole extent.
    fn create_new(
        root: &Path,
        grid: Grid,
        info: StoreInfo,
        choice: LayoutChoice,
        span: Option<Span>,
    ) -> Result<Self, StoreError> {
        let extent = Span::extent(&grid);
        let mut s = ZarrStore::at(root, grid, info, extent);
        s.layout = Layout::chosen(&s.grid, choice);
        if let Some(span) = span {
            s.span = s.aligned(span);
        }
        s.write_metadata()?;
        if s.layout.group().is_some() {
            s.journal = Some(Journal::new(s.group_journal_path(), 1));
        }
        Ok(s)
    }

    /// Opens an existing store (for `merge`, reading, resuming), finishing interrupted commits
    /// and an interrupted change of span. Its arrays keep their span.
    pub fn open(root: &Path) -> Result<Self, StoreError> {
        let meta = root.join("zarr.json");
        let text = fs::read(&meta).map_err(io(&meta))?;
        let v: Value =
            serde_json::from_slice(&text).map_err(|e| invalid(&meta, format!("not JSON: {e}")))?;
        let attrs = v
            .get("attributes")
            .ok_or_else(|| invalid(&meta, "no `attributes`"))?;
        let fw = attrs
            .get("fwlidar")
            .ok_or_else(|| invalid(&meta, "no `attributes.fwlidar`: not a fwlidar voxel store"))?;
        let grid: Grid = serde_json::from_value(fw.get("grid").cloned().unwrap_or(Value::Null))
            .map_err(|e| invalid(&meta, format!("attributes.fwlidar.grid: {e}")))?;
        if !grid.chunk_levels.is_power_of_two() {
            return Err(invalid(
                &meta,
                "attributes.fwlidar.grid.chunk_levels: missing or not a power of two (a store of \
                 an fwlidar version with one chunk per tile: process its input again)",
            ));
        }
        let s = |k: &str| attrs.get(k).and_then(|x| x.as_str()).map(str::to_string);
        let info = StoreInfo {
            crs_wkt: s("crs_wkt"),
            epsg: attrs
                .get("epsg")
                .and_then(|x| x.as_u64())
                .and_then(|x| u32::try_from(x).ok()),
            intensity_units: s("intensity_units").unwrap_or_default(),
            run_key: fw
                .get("run_key")
                .and_then(|x| x.as_str())
                .unwrap_or_default()
                .to_string(),
            configuration: s("configuration").unwrap_or_default(),
        };
        // Stores written before the span was recorded span the extent.
        let span = match fw.get("arrays") {
            None => Span::extent(&grid),
            Some(a) => serde_json::from_value::<Span>(a.clone())
                .map_err(|e| invalid(&meta, format!("attributes.fwlidar.arrays: {e}")))?,
        };
        if !within(&span, &grid) {
            return Err(invalid(
                &meta,
                format!(
                    "attributes.fwlidar.arrays: tiles {:?} + {:?} lie outside the grid's extent",
                    span.tile_min, span.tiles
                ),
            ));
        }
        let mut store = ZarrStore::at(root, grid, info, span);
        let array_meta = root.join(ARRAYS[1]).join("zarr.json");
        if let Ok(text) = fs::read(&array_meta) {
            let v: Value = serde_json::from_slice(&text)
                .map_err(|e| invalid(&array_meta, format!("not JSON: {e}")))?;
            store.layout =
                Layout::of_meta(&v, &store.grid).map_err(|what| invalid(&array_meta, what))?;
        }
        store.recover()?;
        Ok(store)
    }

    fn state_dir(&self) -> PathBuf {
        self.root.join("fwlidar_state").join("tiles")
    }

    /// Where a change of span keeps the chunks it is moving, named `<array>.<tx>_<ty>`.
    fn staging_dir(&self) -> PathBuf {
        self.root.join("fwlidar_state").join("staging")
    }

    /// The journal of a change of span: the target span, present while the chunks move.
    fn journal_path(&self) -> PathBuf {
        self.root.join("fwlidar_state").join("relayout")
    }

    /// The journal of the grouped layout (`shard_group`).
    fn group_journal_path(&self) -> PathBuf {
        self.root.join("fwlidar_state").join("journal")
    }

    fn record_path(&self, tile: [i64; 2]) -> PathBuf {
        self.state_dir().join(format!("{}_{}", tile[0], tile[1]))
    }

    /// Path of height chunk `kc` of a tile's chunks of `array` under the current span; an
    /// error naming the store when the span does not hold it.
    pub fn chunk_path(&self, array: &str, tile: [i64; 2], kc: u32) -> Result<PathBuf, StoreError> {
        if let Some(g) = self.layout.group() {
            let p = g.place(self.grid.tile_min, tile, kc);
            return self.shard_path(array, p.group, p.gz);
        }
        let place = self
            .span
            .chunk_of(tile)
            .and_then(|rc| Some((self.span.level_of(kc)?, rc)));
        let (lev, [row, col]) = place.ok_or_else(|| {
            invalid(
                &self.root,
                format!(
                    "tile {tile:?}, height chunk {kc} lies outside the arrays (tiles {:?} + {:?}, \
                     height chunks {} + {})",
                    self.span.tile_min,
                    self.span.tiles,
                    self.span.level_chunk_min,
                    self.span.level_chunks
                ),
            )
        })?;
        Ok(self
            .root
            .join(array)
            .join("c")
            .join(lev.to_string())
            .join(row.to_string())
            .join(col.to_string()))
    }

    /// Path of the shard of `array` holding group `group` at group height `gz` (the grouped
    /// layout) under the current span, whose tiles and height chunks start at a group's.
    fn shard_path(&self, array: &str, group: [i64; 2], gz: u32) -> Result<PathBuf, StoreError> {
        let g = self.layout.group().unwrap_or(ShardGroup {
            tiles: 1,
            height_chunks: 1,
        });
        let (n, k) = (g.tiles.max(1) as i64, g.height_chunks.max(1));
        let sp = &self.span;
        let first = |a: usize| (sp.tile_min[a] - self.grid.tile_min[a]).div_euclid(n);
        let count = |a: usize| (sp.tiles[a] as i64 + n - 1) / n;
        let (z0, z1) = (
            sp.level_chunk_min / k,
            (sp.level_chunk_min + sp.level_chunks).div_ceil(k),
        );
        let (col, row) = (group[0] - first(0), group[1] - first(1));
        if !(0..count(0)).contains(&col) || !(0..count(1)).contains(&row) || !(z0..z1).contains(&gz)
        {
            return Err(invalid(
                &self.root,
                format!(
                    "shard group {group:?} at height {gz} lies outside the arrays (tiles {:?} + \
                     {:?}, height chunks {} + {})",
                    sp.tile_min, sp.tiles, sp.level_chunk_min, sp.level_chunks
                ),
            ));
        }
        Ok(self
            .root
            .join(array)
            .join("c")
            .join((gz - z0).to_string())
            .join(row.to_string())
            .join(col.to_string()))
    }

    /// The chunk files the tiles in the store occupy, each `([x, y], z)`: a tile and a height
    /// chunk, or (grouped) a group and a group height.
    fn units(&self) -> BTreeSet<([i64; 2], u32)> {
        let g = self.layout.group();
        self.records
            .iter()
            .flat_map(|(t, (_, c))| c.iter().map(move |k| (*t, *k)))
            .map(|(t, k)| match g {
                Some(g) => {
                    let p = g.place(self.grid.tile_min, t, k);
                    (p.group, p.gz)
                }
                None => (t, k),
            })
            .collect()
    }

    /// Path of a unit of [`units`](Self::units) of `array` under the current span.
    fn unit_path(&self, array: &str, xy: [i64; 2], z: u32) -> Result<PathBuf, StoreError> {
        match self.layout.group() {
            Some(_) => self.shard_path(array, xy, z),
            None => self.chunk_path(array, xy, z),
        }
    }

    /// `span` widened down to whole groups (the grouped layout), so that each shard of the
    /// arrays is one group.
    fn aligned(&self, mut span: Span) -> Span {
        let Some(g) = self.layout.group() else {
            return span;
        };
        if span.tiles.contains(&0) {
            return span;
        }
        for a in 0..2 {
            let off = (span.tile_min[a] - self.grid.tile_min[a]).rem_euclid(g.tiles.max(1) as i64);
            span.tile_min[a] -= off;
            span.tiles[a] += off as u32;
        }
        let off = span.level_chunk_min % g.height_chunks.max(1);
        span.level_chunk_min -= off;
        span.level_chunks += off;
        span
    }

    fn pending_path(&self, array: &str, tile: [i64; 2], kc: u32) -> Result<PathBuf, StoreError> {
        let mut p = self.chunk_path(array, tile, kc)?.into_os_string();
        p.push(".pending");
        Ok(PathBuf::from(p))
    }

    fn read_record(path: &Path) -> Result<TileRecord, StoreError> {
        let text = fs::read(path).map_err(io(path))?;
        let v: Value = serde_json::from_slice(&text)
            .map_err(|e| invalid(path, format!("tile record is not JSON: {e}")))?;
        let chunks = match v.get("chunks") {
            None => vec![0],
            Some(c) => c
                .as_array()
                .and_then(|a| {
                    a.iter()
                        .map(|x| x.as_u64().and_then(|k| u32::try_from(k).ok()))
                        .collect::<Option<Vec<u32>>>()
                })
                .ok_or_else(|| invalid(path, "tile record: `chunks` is not a list of levels"))?,
        };
        Ok(TileRecord {
            watermark: v
                .get("watermark")
                .and_then(|x| x.as_u64())
                .ok_or_else(|| invalid(path, "tile record has no `watermark`"))?,
            chunks,
            pending: v.get("pending").and_then(|x| x.as_bool()).unwrap_or(false),
        })
    }

    fn parse_tile_name(name: &str) -> Option<[i64; 2]> {
        let (a, b) = name.split_once('_')?;
        Some([a.parse().ok()?, b.parse().ok()?])
    }

    /// `TX_TY_KC` (a staged chunk's name after its array).
    fn parse_staged_name(name: &str) -> Option<([i64; 2], u32)> {
        let (t, k) = name.rsplit_once('_')?;
        Some((Self::parse_tile_name(t)?, k.parse().ok()?))
    }

    /// Completes committed tiles, discards uncommitted chunks, loads the watermarks.
    fn recover(&mut self) -> Result<(), StoreError> {
        let dir = self.state_dir();
        if dir.exists() {
            for entry in fs::read_dir(&dir).map_err(io(&dir))? {
                let entry = entry.map_err(io(&dir))?;
                let name = entry.file_name().to_string_lossy().to_string();
                if name.ends_with(".partial") {
                    let _ = fs::remove_file(entry.path());
                    continue;
                }
                let Some(tile) = Self::parse_tile_name(&name) else {
                    continue;
                };
                let mut rec = Self::read_record(&entry.path())?;
                if rec.pending {
                    for &kc in &rec.chunks {
                        for a in ARRAYS {
                            let p = self.pending_path(a, tile, kc)?;
                            if p.exists() {
                                let c = self.chunk_path(a, tile, kc)?;
                                fs::rename(&p, &c).map_err(io(&c))?;
                            }
                        }
                    }
                    rec.pending = false;
                    write_atomic(&entry.path(), &rec.json())?;
                    self.recovered_commits += 1;
                }
                self.records.insert(tile, (rec.watermark, rec.chunks));
            }
        }
        if self.layout.group().is_some() {
            self.recover_journal()?;
        }
        // Pending chunks no record committed: an interrupted first step; the old chunk stays.
        for a in ARRAYS {
            let base = self.root.join(a).join("c");
            if base.exists() {
                self.discarded_pending += remove_pending(&base)?;
            }
        }
        // A change of span cut short: finish it (the journal names the target).
        let journal = self.journal_path();
        if journal.exists() {
            let text = fs::read(&journal).map_err(io(&journal))?;
            let target: Span = serde_json::from_slice(&text)
                .map_err(|e| invalid(&journal, format!("not a span: {e}")))?;
            if !within(&target, &self.grid) {
                return Err(invalid(&journal, "the span lies outside the grid's extent"));
            }
            self.finish_relayout(target)?;
        }
        Ok(())
    }

    /// The grouped layout's part of opening: the tiles from the journal (a torn last line cut
    /// off), the renames of committed batches that were cut short completed.
    fn recover_journal(&mut self) -> Result<(), StoreError> {
        let path = self.group_journal_path();
        let (batches, torn) =
            Journal::read(&path).map_err(|what| invalid(&path, format!("journal: {what}")))?;
        if let Some(len) = torn {
            let f = OpenOptions::new()
                .write(true)
                .open(&path)
                .map_err(io(&path))?;
            f.set_len(len).map_err(io(&path))?;
            f.sync_all().map_err(io(&path))?;
        }
        for b in &batches {
            for shard in &b.shards {
                let to = self.root.join(shard);
                let mut from = to.clone().into_os_string();
                from.push(format!(".pending.{}", b.seq));
                let from = PathBuf::from(from);
                if from.exists() {
                    fs::rename(&from, &to).map_err(io(&to))?;
                    self.recovered_commits += 1;
                }
            }
        }
        self.records = super::shard_group::latest_tiles(&batches)
            .into_iter()
            .collect();
        let next = batches.iter().map(|b| b.seq + 1).max().unwrap_or(1);
        self.journal = Some(Journal::new(path, next));
        Ok(())
    }

    /// Rewrites the journal as one batch holding every tile (nothing pending: after
    /// [`flush_all`](Self::flush_all)).
    fn compact_journal(&mut self) -> Result<(), StoreError> {
        let path = self.group_journal_path();
        // Numbered 0 (real batches count from 1): a finished store's journal does not depend on
        // how many batches wrote it, so a run resumed after kill -9 ends with the same bytes.
        let batch = Batch {
            seq: 0,
            shards: Vec::new(),
            tiles: self
                .tiles()
                .into_iter()
                .map(|t| {
                    let (watermark, chunks) = self.records[&t].clone();
                    JournalTile {
                        tile: t,
                        watermark,
                        chunks,
                    }
                })
                .collect(),
        };
        if self.durable {
            write_atomic(&path, &batch.line())
        } else {
            fs::write(&path, batch.line()).map_err(io(&path))
        }
    }

    /// Shrinks the arrays to the bounding box of the tiles in the store (the end of a run or a
    /// merge): what a reader sees of a finished store. Writing again needs
    /// [`create_or_open`](Self::create_or_open), which puts the arrays back on the extent.
    pub fn fit(&mut self) -> Result<(), StoreError> {
        if self.layout.group().is_some() {
            self.flush_all()?;
            self.compact_journal()?;
        }
        let span = self.aligned(Span::around(
            &self.grid,
            self.records.iter().map(|(t, (_, c))| (*t, c.as_slice())),
        ));
        self.relayout(span)
    }

    /// Puts the data arrays on `span`, moving every tile's chunks to its key there (through the
    /// staging folder, under a journal: see the module documentation) and rewriting the
    /// metadata. Only between tile writes (no tile is pending).
    fn relayout(&mut self, span: Span) -> Result<(), StoreError> {
        if let Some(t) = self.records.iter().find(|(t, (_, c))| {
            !span.contains(**t) || c.iter().any(|k| span.level_of(*k).is_none())
        }) {
            return Err(invalid(
                &self.root,
                format!(
                    "tile {:?} lies outside the span {:?} + {:?} the arrays are to take",
                    t.0, span.tile_min, span.tiles
                ),
            ));
        }
        if self.span.same_tiles(&span) {
            self.span = span;
            return self.write_metadata();
        }
        let state = self.root.join("fwlidar_state");
        fs::create_dir_all(&state).map_err(io(&state))?;
        let journal = self.journal_path();
        let text = serde_json::to_vec(&span).map_err(|e| invalid(&journal, e.to_string()))?;
        write_atomic(&journal, &text)?;
        sync_dir(&state);
        self.finish_relayout(span)
    }

    /// Moves the chunks to `target` (the journal's span) from wherever the last attempt left
    /// them, rewrites the metadata, removes the journal. Idempotent.
    fn finish_relayout(&mut self, target: Span) -> Result<(), StoreError> {
        let staging = self.staging_dir();
        let mut touched = BTreeSet::new();
        if !self.span.same_tiles(&target) {
            // The metadata still names the old span: every chunk still at its old key goes to
            // staging, then the old chunk trees (nothing else is in them) are removed.
            fs::create_dir_all(&staging).map_err(io(&staging))?;
            for (t, kc) in self.units() {
                for a in ARRAYS {
                    let from = self.unit_path(a, t, kc)?;
                    let to = staging.join(format!("{a}.{}_{}_{kc}", t[0], t[1]));
                    match fs::rename(&from, &to) {
                        Ok(()) => {
                            if let Some(d) = from.parent() {
                                touched.insert(d.to_path_buf());
                            }
                        }
                        // Already staged by an attempt cut short, or an all-fill chunk.
                        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                        Err(e) => return Err(io(&from)(e)),
                    }
                }
            }
            touched.insert(staging.clone());
            sync_dirs(&self.root, &std::mem::take(&mut touched));
            for a in ARRAYS {
                let c = self.root.join(a).join("c");
                if c.exists() {
                    fs::remove_dir_all(&c).map_err(io(&c))?;
                }
            }
        }
        // The new span's metadata (the root document last) is the point after which the
        // chunks belong at their new keys.
        self.span = target;
        self.write_metadata()?;
        if staging.exists() {
            let units = self.units();
            for entry in fs::read_dir(&staging).map_err(io(&staging))? {
                let entry = entry.map_err(io(&staging))?;
                let from = entry.path();
                let name = entry.file_name().to_string_lossy().to_string();
                let place = name.split_once('.').and_then(|(a, t)| {
                    let (xy, z) = Self::parse_staged_name(t)?;
                    let a = ARRAYS.iter().find(|x| **x == a)?;
                    let to = self.unit_path(a, xy, z).ok()?;
                    units.contains(&(xy, z)).then_some(to)
                });
                let Some(to) = place else {
                    fs::remove_file(&from).map_err(io(&from))?;
                    continue;
                };
                let dir = to.parent().unwrap_or(&self.root).to_path_buf();
                if !touched.contains(&dir) {
                    fs::create_dir_all(&dir).map_err(io(&dir))?;
                    touched.insert(dir);
                }
                fs::rename(&from, &to).map_err(io(&to))?;
            }
            sync_dirs(&self.root, &touched);
            fs::remove_dir(&staging).map_err(io(&staging))?;
        }
        let journal = self.journal_path();
        if journal.exists() {
            fs::remove_file(&journal).map_err(io(&journal))?;
        }
        sync_dir(&self.root.join("fwlidar_state"));
        Ok(())
    }

    /// Watermark of a tile already in the store.
    pub fn watermark(&self, tile: [i64; 2]) -> Option<u64> {
        self.records.get(&tile).map(|r| r.0)
    }

    /// Height chunks a tile of the store holds (ascending).
    pub fn tile_chunks(&self, tile: [i64; 2]) -> Option<&[u32]> {
        self.records.get(&tile).map(|r| r.1.as_slice())
    }

    /// Tiles in the store.
    pub fn tiles(&self) -> Vec<[i64; 2]> {
        let mut t: Vec<_> = self.records.keys().copied().collect();
        t.sort();
        t
    }

    /// Reads a tile into `into` (which must have the grid's tile shape); false when the store
    /// has no such tile (`into` is then cleared).
    pub fn read_tile(&mut self, tile: [i64; 2], into: &mut TileData) -> Result<bool, StoreError> {
        into.clear();
        if let Some(g) = self.layout.group() {
            // A tile of a group still being assembled: its shards written first.
            let key = g.group_of(self.grid.tile_min, tile);
            if self.groups.contains_key(&key) {
                self.flush_groups(vec![key])?;
            }
        }
        let Some((_, chunks)) = self.records.get(&tile) else {
            return Ok(false);
        };
        let chunks = chunks.clone();
        let order = DiskOrder::of(&self.grid, self.layout);
        for kc in chunks {
            if kc as usize >= into.chunk_count() {
                return Err(invalid(
                    &self.record_path(tile),
                    format!("height chunk {kc} lies above the grid"),
                ));
            }
            for a in ARRAYS {
                let path = self.chunk_path(a, tile, kc)?;
                if let Some(g) = self.layout.group() {
                    let slot = g.place(self.grid.tile_min, tile, kc).slot;
                    let mut shard = std::mem::take(&mut self.shard);
                    let found = super::shard_group::read_place(&path, g.slots(), slot, &mut shard)
                        .map_err(|what| invalid(&path, what));
                    self.shard = shard;
                    if !found? {
                        continue; // all fill value
                    }
                } else if !path.exists() {
                    continue; // all fill value
                }
                self.read_chunk(&path, a, order, into.chunk_mut(kc as usize))?;
            }
        }
        Ok(true)
    }

    /// Reads the chunk file `path` of array `a` into `c`, by the store's layout: a shard's
    /// inner chunks (absent ones stay fill value), or one compressed chunk; grouped, the tile's
    /// height-chunk shard already read into `self.shard`.
    fn read_chunk(
        &mut self,
        path: &Path,
        a: &str,
        order: DiskOrder,
        c: &mut super::tile::Chunk,
    ) -> Result<(), StoreError> {
        let width = if a == "intensity_sum" { 8 } else { 4 };
        let expect = order.block_voxels() * width;
        let blocks = order.blocks() * order.blocks();
        let bad = |what: String| invalid(path, what);
        let mut fill = |raw: &[u8], blk: usize| match a {
            "intensity_sum" => order.read(raw, blk, c, |v| v.sum_q, i64::from_le_bytes),
            "sample_count" => order.read(raw, blk, c, |v| v.samples, u32::from_le_bytes),
            "pulse_count" => order.read(raw, blk, c, |v| v.pulses, u32::from_le_bytes),
            _ => order.read(raw, blk, c, |v| v.max, f32::from_le_bytes),
        };
        match self.layout {
            Layout::Plain(codec) => {
                let f = File::open(path).map_err(io(path))?;
                codec
                    .decode(f, &mut self.raw)
                    .map_err(|e| bad(format!("chunk does not decompress: {e}")))?;
                if self.raw.len() != expect {
                    return Err(bad(format!(
                        "chunk holds {} bytes, a chunk of {} voxels needs {expect}",
                        self.raw.len(),
                        order.block_voxels()
                    )));
                }
                fill(&self.raw, 0);
            }
            Layout::Sharded {
                codec,
                index_crc,
                group,
                ..
            } => {
                if group.is_none() {
                    let mut f = File::open(path).map_err(io(path))?;
                    self.shard.clear();
                    f.read_to_end(&mut self.shard).map_err(io(path))?;
                }
                let index_len = blocks * 16 + if index_crc { 4 } else { 0 };
                let Some(data_len) = self.shard.len().checked_sub(index_len) else {
                    return Err(bad(format!(
                        "shard of {} bytes is shorter than its index ({index_len} bytes)",
                        self.shard.len()
                    )));
                };
                let (data, index) = self.shard.split_at(data_len);
                let entries = &index[..blocks * 16];
                if index_crc {
                    let stored =
                        u32::from_le_bytes(index[blocks * 16..].try_into().unwrap_or_default());
                    if crc32c::crc32c(entries) != stored {
                        return Err(bad("shard index: CRC-32C does not match".into()));
                    }
                }
                for (blk, e) in entries.chunks_exact(16).enumerate() {
                    let word =
                        |i: usize| u64::from_le_bytes(e[i..i + 8].try_into().unwrap_or_default());
                    let (off, n) = (word(0), word(8));
                    if off == u64::MAX && n == u64::MAX {
                        continue; // all fill value
                    }
                    let range = usize::try_from(off)
                        .ok()
                        .zip(usize::try_from(n).ok())
                        .and_then(|(o, n)| Some(o..o.checked_add(n)?))
                        .filter(|r| r.end <= data.len())
                        .ok_or_else(|| {
                            bad(format!(
                                "shard index: inner chunk {blk} at {off} + {n} bytes lies \
                                 outside the shard's {} bytes of data",
                                data.len()
                            ))
                        })?;
                    codec
                        .decode_block(&mut self.zd, &data[range], expect, &mut self.raw)
                        .map_err(|e| {
                            bad(format!("inner chunk {blk}: chunk does not decompress: {e}"))
                        })?;
                    fill(&self.raw, blk);
                }
            }
        }
        Ok(())
    }

    /// A second handle on the same store for a writer thread: it writes tiles with
    /// [`write_tile`](Self::write_tile) exactly as this one would; this one learns of each commit
    /// through [`note_committed`](Self::note_committed). Its own records are not consulted.
    /// The span must not change while it writes (it does not: a run's span is the extent).
    pub fn tile_writer(&mut self) -> ZarrStore {
        let mut w = ZarrStore::at(&self.root, self.grid.clone(), self.info.clone(), self.span);
        w.layout = self.layout;
        w.durable = self.durable;
        w.buffer_budget = self.buffer_budget;
        if self.layout.group().is_some() {
            // Grouped: the writer merges a group's shards with what the store holds, so it knows
            // the tiles; a group is only ever written by one writer.
            w.records = self.records.clone();
            let path = self.group_journal_path();
            w.journal = Some(
                self.journal
                    .get_or_insert_with(|| Journal::new(path, 1))
                    .clone(),
            );
            w.reports = true;
        }
        w
    }

    /// Adds a tile this handle wrote to what [`take_committed`](Self::take_committed) returns.
    pub fn note_written(&mut self, c: Committed) {
        self.committed.push(c);
    }

    /// How the store is laid out, as a new store would be asked to be (`merge` writes its
    /// result as its first input is).
    pub fn layout_choice(&self) -> LayoutChoice {
        LayoutChoice {
            group: self.layout.group(),
            inner_columns: match self.layout {
                Layout::Sharded { inner, .. } => inner,
                Layout::Plain(_) => INNER_COLUMNS,
            },
        }
    }

    /// The tiles this (writer) handle made durable since the last call, with their costs.
    pub fn take_committed(&mut self) -> Vec<Committed> {
        std::mem::take(&mut self.committed)
    }

    /// The group of tiles `tile` is written with (the grouped layout), if any.
    pub fn group_of(&self, tile: [i64; 2]) -> Option<[i64; 2]> {
        self.layout
            .group()
            .map(|g| g.group_of(self.grid.tile_min, tile))
    }

    /// The tiles of group `group`, `[tx0, ty0, tx1, ty1]` inclusive (the grouped layout).
    pub fn group_tiles(&self, group: [i64; 2]) -> Option<[i64; 4]> {
        self.layout
            .group()
            .map(|g| g.tiles_of(self.grid.tile_min, group))
    }

    /// The groups being assembled (the grouped layout; written by
    /// [`flush_groups`](Self::flush_groups)).
    pub fn buffered_groups(&self) -> Vec<[i64; 2]> {
        let mut g: Vec<_> = self.groups.keys().copied().collect();
        g.sort_unstable();
        g
    }

    /// Writes every group being assembled (the grouped layout; nothing otherwise).
    pub fn flush_all(&mut self) -> Result<(), StoreError> {
        let all = self.buffered_groups();
        self.flush_groups(all)
    }

    /// Writes the shards of `groups` (those being assembled) as one batch: each shard the
    /// group's new tiles over what the store holds, written pending and synced, the batch's
    /// journal line appended and synced (the commit point), the shards renamed into place
    /// (`shard_group`).
    pub fn flush_groups(&mut self, mut groups: Vec<[i64; 2]>) -> Result<(), StoreError> {
        let Some(g) = self.layout.group() else {
            return Ok(());
        };
        groups.sort_unstable();
        groups.dedup();
        groups.retain(|k| self.groups.contains_key(k));
        if groups.is_empty() {
            return Ok(());
        }
        let path = self.group_journal_path();
        let journal = self
            .journal
            .get_or_insert_with(|| Journal::new(path, 1))
            .clone();
        let seq = journal.next_seq();
        let (mut pending, mut batch) = (
            Vec::new(),
            Batch {
                seq,
                shards: Vec::new(),
                tiles: Vec::new(),
            },
        );
        let mut reports = Vec::new();
        let mut dirs = BTreeSet::new();
        let mut out = Vec::new();
        for key in groups {
            let Some(buf) = self.groups.remove(&key) else {
                continue;
            };
            self.buffered_bytes = self.buffered_bytes.saturating_sub(buf.bytes);
            let heights: BTreeSet<u32> = buf.places.keys().map(|k| k.1).collect();
            let (mut files, mut stored) = (0u64, 0u64);
            for (ai, a) in ARRAYS.iter().enumerate() {
                for &gz in &heights {
                    let path = self.shard_path(a, key, gz)?;
                    let old = match fs::read(&path) {
                        Ok(b) => Some(b),
                        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
                        Err(e) => return Err(io(&path)(e)),
                    };
                    super::shard_group::assemble(
                        old.as_deref(),
                        g.slots(),
                        |slot| buf.places.get(&(ai, gz, slot)).map(Vec::as_slice),
                        &mut out,
                    )
                    .map_err(|what| invalid(&path, what))?;
                    let mut p = path.clone().into_os_string();
                    p.push(format!(".pending.{seq}"));
                    let p = PathBuf::from(p);
                    let dir = path.parent().unwrap_or(&self.root).to_path_buf();
                    if dirs.insert(dir.clone()) {
                        fs::create_dir_all(&dir).map_err(io(&dir))?;
                    }
                    let mut f = File::create(&p).map_err(io(&p))?;
                    f.write_all(&out).map_err(io(&p))?;
                    files += 1;
                    stored += out.len() as u64;
                    let rel = path.strip_prefix(&self.root).unwrap_or(&path);
                    batch.shards.push(rel.to_string_lossy().replace('\\', "/"));
                    pending.push((f, p, path));
                }
            }
            for (i, (tile, (watermark, chunks, mut cost))) in buf.tiles.into_iter().enumerate() {
                if i == 0 {
                    (cost.chunks, cost.stored_bytes) = (files, stored);
                }
                batch.tiles.push(JournalTile {
                    tile,
                    watermark,
                    chunks: chunks.clone(),
                });
                reports.push(Committed {
                    tile,
                    watermark,
                    chunks,
                    cost,
                });
            }
        }
        if self.durable && !syncfs(&self.root) {
            for (f, path, _) in &pending {
                f.sync_all().map_err(io(path))?;
            }
        }
        journal
            .append(&batch, self.durable)
            .map_err(io(journal.path()))?;
        for (f, p, c) in pending {
            drop(f);
            fs::rename(&p, &c).map_err(io(&c))?;
        }
        for r in reports {
            self.tiles_written += 1;
            self.chunks_written += r.cost.chunks;
            self.inner_chunks_written += r.cost.inner_chunks;
            self.bytes_written += r.cost.raw_bytes;
            self.bytes_stored += r.cost.stored_bytes;
            if self.reports {
                self.committed.push(r);
            }
        }
        Ok(())
    }

    /// Puts a tile's height-chunk shard of array `ai` into its group's buffer.
    fn buffer_place(&mut self, tile: [i64; 2], kc: u32, ai: usize, bytes: Vec<u8>) {
        let Some(g) = self.layout.group() else {
            return;
        };
        let p = g.place(self.grid.tile_min, tile, kc);
        let buf = self.groups.entry(p.group).or_default();
        buf.bytes += bytes.len();
        self.buffered_bytes += bytes.len();
        if let Some(old) = buf.places.insert((ai, p.gz, p.slot), bytes) {
            buf.bytes -= old.len();
            self.buffered_bytes -= old.len();
        }
    }

    /// Records a tile put into its group's buffer; past the budget, every group is written.
    fn buffer_tile(
        &mut self,
        tile: [i64; 2],
        watermark: u64,
        chunks: Vec<u32>,
        cost: WriteCost,
    ) -> Result<(), StoreError> {
        let Some(key) = self.group_of(tile) else {
            return Ok(());
        };
        self.groups
            .entry(key)
            .or_default()
            .tiles
            .insert(tile, (watermark, chunks.clone(), cost));
        self.records.insert(tile, (watermark, chunks));
        if self.buffered_bytes > self.buffer_budget {
            self.flush_all()?;
        }
        Ok(())
    }

    /// Records a tile committed by a [`tile_writer`](Self::tile_writer) handle, with what its
    /// write cost.
    pub fn note_committed(
        &mut self,
        tile: [i64; 2],
        watermark: u64,
        chunks: Vec<u32>,
        cost: WriteCost,
    ) {
        self.records.insert(tile, (watermark, chunks));
        self.tiles_written += 1;
        self.chunks_written += cost.chunks;
        self.inner_chunks_written += cost.inner_chunks;
        self.bytes_written += cost.raw_bytes;
        self.bytes_stored += cost.stored_bytes;
    }

    /// Writes a tile with its watermark (see the module documentation for the protocol): the
    /// height chunks it holds, nothing for empty air. The arrays' span must hold the tile (a
    /// run's span is the whole extent). Returns the tile's height chunks and the write's cost.
    pub fn write_tile(
        &mut self,
        tile: [i64; 2],
        data: &TileData,
        watermark: u64,
    ) -> Result<(Vec<u32>, WriteCost), StoreError> {
        if !self.span.contains(tile) {
            return Err(invalid(
                &self.root,
                format!(
                    "tile {tile:?} lies outside the arrays (tiles {:?} + {:?})",
                    self.span.tile_min, self.span.tiles
                ),
            ));
        }
        // Chunks that an earlier write of the tile holds stay (a reopened tile was merged, so
        // its chunks are a superset; listed anyway so that the record never loses one).
        let mut chunks: Vec<u32> = data
            .present()
            .into_iter()
            .filter(|k| data.chunk(*k as usize).is_some_and(|c| !c.is_blank()))
            .collect();
        if let Some((_, old)) = self.records.get(&tile) {
            for k in old {
                if !chunks.contains(k) {
                    chunks.push(*k);
                }
            }
            chunks.sort_unstable();
        }
        let order = DiskOrder::of(&self.grid, self.layout);
        let mut cost = WriteCost::default();
        if self.layout.group().is_some() {
            for &kc in &chunks {
                let Some(c) = data.chunk(kc as usize) else {
                    continue; // held by the store already, not in memory: unchanged
                };
                order.occupied(c, &mut self.blocks);
                for (ai, a) in ARRAYS.iter().enumerate() {
                    self.encode_chunk(c, a, order, &mut cost)
                        .map_err(io(&self.root))?;
                    let bytes = self.shard.clone();
                    self.buffer_place(tile, kc, ai, bytes);
                }
            }
            cost.stored_bytes = 0; // counted when the group is written
            self.buffer_tile(tile, watermark, chunks.clone(), cost)?;
            return Ok((chunks, cost));
        }
        let mut dirs = BTreeSet::new();
        let mut pending = Vec::with_capacity(chunks.len() * ARRAYS.len());
        for &kc in &chunks {
            let Some(c) = data.chunk(kc as usize) else {
                continue; // held by the store already, not in memory: unchanged
            };
            match self.layout {
                Layout::Plain(_) => {
                    self.blocks.clear();
                    self.blocks.push(order.side as u32 * order.side as u32);
                }
                Layout::Sharded { .. } => order.occupied(c, &mut self.blocks),
            }
            for a in ARRAYS {
                let path = self.pending_path(a, tile, kc)?;
                self.encode_chunk(c, a, order, &mut cost)
                    .map_err(io(&path))?;
                cost.chunks += 1;
                let dir = path.parent().unwrap_or(&self.root).to_path_buf();
                if dirs.insert(dir.clone()) {
                    fs::create_dir_all(&dir).map_err(io(&dir))?;
                }
                let mut f = File::create(&path).map_err(io(&path))?;
                f.write_all(&self.shard).map_err(io(&path))?;
                pending.push((f, path, self.chunk_path(a, tile, kc)?));
            }
        }
        self.commit(tile, pending, chunks, watermark, cost)
    }

    /// Writes `tile` of `src` into this store as its chunk files are, without decoding them: a
    /// tile that only one input of a merge holds. The bytes are those [`write_tile`](Self::write_tile)
    /// would write for the decoded data (the encoding is deterministic: the same blocks, codec
    /// and level). `Ok(false)`, nothing written, when it cannot be copied — the stores' layouts
    /// or tile shapes differ, `src` lacks the tile, or this store holds it already — so the
    /// caller decodes and writes it instead.
    pub fn copy_tile(
        &mut self,
        src: &ZarrStore,
        tile: [i64; 2],
        watermark: u64,
    ) -> Result<bool, StoreError> {
        // A tile's height-chunk shard is the same bytes grouped or not; a grouped source is
        // copied only into a grouped store (its files are groups).
        let same_shape = src.layout.tile_shard() == self.layout.tile_shard()
            && (src.layout.group().is_none() || self.layout.group().is_some())
            && src.grid.tile_columns == self.grid.tile_columns
            && src.grid.chunk_levels == self.grid.chunk_levels
            && src.grid.levels == self.grid.levels;
        let Some((_, chunks)) = src.records.get(&tile) else {
            return Ok(false);
        };
        if !same_shape || self.records.contains_key(&tile) || !self.span.contains(tile) {
            return Ok(false);
        }
        let chunks = chunks.clone();
        if self.layout.group().is_some() {
            return self.copy_tile_grouped(src, tile, chunks, watermark);
        }
        let mut cost = WriteCost::default();
        let mut dirs = BTreeSet::new();
        let mut pending = Vec::with_capacity(chunks.len() * ARRAYS.len());
        for &kc in &chunks {
            for a in ARRAYS {
                let from = src.chunk_path(a, tile, kc)?;
                let bytes = match fs::read(&from) {
                    Ok(b) => b,
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                    Err(e) => return Err(io(&from)(e)),
                };
                let path = self.pending_path(a, tile, kc)?;
                let dir = path.parent().unwrap_or(&self.root).to_path_buf();
                if dirs.insert(dir.clone()) {
                    fs::create_dir_all(&dir).map_err(io(&dir))?;
                }
                let mut f = File::create(&path).map_err(io(&path))?;
                f.write_all(&bytes).map_err(io(&path))?;
                cost.chunks += 1;
                cost.stored_bytes += bytes.len() as u64;
                pending.push((f, path, self.chunk_path(a, tile, kc)?));
            }
        }
        self.commit(tile, pending, chunks, watermark, cost)?;
        Ok(true)
    }

    /// [`copy_tile`](Self::copy_tile) into a grouped store: each height chunk's shard, read
    /// where `src` keeps it (its own file, or its place in a group's shard), into the group.
    fn copy_tile_grouped(
        &mut self,
        src: &ZarrStore,
        tile: [i64; 2],
        chunks: Vec<u32>,
        watermark: u64,
    ) -> Result<bool, StoreError> {
        let mut cost = WriteCost::default();
        let mut bytes = Vec::new();
        for &kc in &chunks {
            for (ai, a) in ARRAYS.iter().enumerate() {
                let from = src.chunk_path(a, tile, kc)?;
                let found = match src.layout.group() {
                    Some(g) => {
                        let slot = g.place(src.grid.tile_min, tile, kc).slot;
                        self.sources
                            .read_place(&from, g.slots(), slot, &mut bytes)
                            .map_err(|what| invalid(&from, what))?
                    }
                    None => match fs::read(&from) {
                        Ok(b) => {
                            bytes = b;
                            true
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
                        Err(e) => return Err(io(&from)(e)),
                    },
                };
                if found {
                    self.buffer_place(tile, kc, ai, std::mem::take(&mut bytes));
                }
            }
        }
        cost.chunks = 0;
        self.buffer_tile(tile, watermark, chunks, cost)?;
        Ok(true)
    }

    /// The end of a tile's write: the pending chunk files `(file, pending path, final path)`
    /// made durable, the record committed, the chunks renamed into place, the record marked
    /// done (the module documentation's protocol).
    fn commit(
        &mut self,
        tile: [i64; 2],
        pending: Vec<(File, PathBuf, PathBuf)>,
        chunks: Vec<u32>,
        watermark: u64,
        cost: WriteCost,
    ) -> Result<(Vec<u32>, WriteCost), StoreError> {
        let state = self.state_dir();
        fs::create_dir_all(&state).map_err(io(&state))?;
        let record = self.record_path(tile);
        let mut rec = TileRecord {
            watermark,
            chunks: chunks.clone(),
            pending: true,
        };
        if self.durable {
            // The chunks' data durable before the commit record: one syncfs, else a sync each.
            if !pending.is_empty() && !syncfs(&self.root) {
                for (f, path, _) in &pending {
                    f.sync_all().map_err(io(path))?;
                }
            }
            write_atomic(&record, &rec.json())?;
        }
        for (f, p, c) in pending {
            drop(f);
            fs::rename(&p, &c).map_err(io(&c))?;
        }
        rec.pending = false;
        if self.durable {
            write_atomic(&record, &rec.json())?;
            sync_dir(&state);
        } else {
            fs::write(&record, rec.json()).map_err(io(&record))?;
        }
        self.records.insert(tile, (watermark, chunks.clone()));
        self.tiles_written += 1;
        self.chunks_written += cost.chunks;
        self.inner_chunks_written += cost.inner_chunks;
        self.bytes_written += cost.raw_bytes;
        self.bytes_stored += cost.stored_bytes;
        Ok((chunks, cost))
    }

    /// Encodes array `a` of height chunk `c` into `self.shard` by the store's layout: the blocks
    /// `self.blocks` marks, each compressed, then (sharded) the index; adds what it cost.
    fn encode_chunk(
        &mut self,
        c: &super::tile::Chunk,
        a: &str,
        order: DiskOrder,
        cost: &mut WriteCost,
    ) -> std::io::Result<()> {
        self.shard.clear();
        let mut index = Vec::new();
        for blk in 0..self.blocks.len() {
            let written = self.blocks[blk];
            if written == 0 {
                index.push((u64::MAX, u64::MAX));
                continue;
            }
            if self.fill_frame(c, a, order, blk, written) {
                index.push((self.shard.len() as u64, self.packed.len() as u64));
                self.shard.extend_from_slice(&self.packed);
                cost.raw_bytes += (order.block_voxels() * value_bytes(a)) as u64;
                cost.inner_chunks += 1;
                continue;
            }
            self.raw.clear();
            match a {
                "intensity_sum" => {
                    order.write(c, |v| v.sum_q, 0, blk, &mut self.raw, i64::to_le_bytes)
                }
                "sample_count" => {
                    order.write(c, |v| v.samples, 0, blk, &mut self.raw, u32::to_le_bytes)
                }
                "pulse_count" => {
                    order.write(c, |v| v.pulses, 0, blk, &mut self.raw, u32::to_le_bytes)
                }
                _ => order.write(c, |v| v.max, f32::NAN, blk, &mut self.raw, f32::to_le_bytes),
            }
            let codec = self.layout.codec();
            match self.layout {
                Layout::Plain(_) => codec.encode(&self.raw, &mut self.packed)?,
                Layout::Sharded { .. } => {
                    codec.encode_block(&mut self.zc, written, &self.raw, &mut self.packed)?
                }
            }
            index.push((self.shard.len() as u64, self.packed.len() as u64));
            self.shard.extend_from_slice(&self.packed);
            cost.raw_bytes += self.raw.len() as u64;
            cost.inner_chunks += 1;
        }
        if let Layout::Sharded { index_crc, .. } = self.layout {
            let at = self.shard.len();
            for (o, n) in index {
                self.shard.extend_from_slice(&o.to_le_bytes());
                self.shard.extend_from_slice(&n.to_le_bytes());
            }
            if index_crc {
                let crc = crc32c::crc32c(&self.shard[at..]);
                self.shard.extend_from_slice(&crc.to_le_bytes());
            }
        }
        cost.stored_bytes += self.shard.len() as u64;
        Ok(())
    }

    /// Encodes array `a` of block `blk` of height chunk `c` into `self.packed` as a frame made
    /// from its runs of values ([`super::fill_frame`]) when that applies: a sparse block
    /// (at most [`SPARSE_BLOCK_COLUMNS`] written columns) of the sharded, column-ordered
    /// layout under zstd. `false`: compress the arranged bytes instead.
    fn fill_frame(
        &mut self,
        c: &super::tile::Chunk,
        a: &str,
        order: DiskOrder,
        blk: usize,
        written: u32,
    ) -> bool {
        let sparse_zstd = matches!(
            self.layout,
            Layout::Sharded {
                codec: Codec::Zstd(_),
                ..
            }
        );
        if !sparse_zstd || !order.transposed || written > SPARSE_BLOCK_COLUMNS {
            return false;
        }
        let f = &mut self.zc.fill;
        match a {
            "intensity_sum" => order.runs(c, |v| v.sum_q, 0, blk, f, i64::to_le_bytes),
            "sample_count" => order.runs(c, |v| v.samples, 0, blk, f, u32::to_le_bytes),
            "pulse_count" => order.runs(c, |v| v.pulses, 0, blk, f, u32::to_le_bytes),
            _ => order.runs(c, |v| v.max, f32::NAN, blk, f, f32::to_le_bytes),
        }
        f.finish(&mut self.packed)
    }

    /// Rewrites the metadata documents (arrays, coordinates, then the root group with the
    /// consolidated metadata of them all) for the current span; the root document is synced.
    fn write_metadata(&mut self) -> Result<(), StoreError> {
        self.join_coordinates()?;
        let g = &self.grid;
        fs::create_dir_all(&self.root).map_err(io(&self.root))?;
        let shape = self.span.shape(g);
        // Every node below the root, as its own `zarr.json` says, for the consolidated metadata.
        let mut nodes = serde_json::Map::new();
        self.write_state_group(&mut nodes)?;
        self.write_data_arrays(shape, &mut nodes)?;
        self.write_coordinates(shape, &mut nodes)?;
        self.write_spatial_ref(&mut nodes)?;
        self.write_root_group(nodes)
    }

    /// Writes the group `fwlidar_state` (where the resume records live, so that Zarr readers
    /// see a node) and adds it to `nodes`.
    fn write_state_group(
        &self,
        nodes: &mut serde_json::Map<String, Value>,
    ) -> Result<(), StoreError> {
        // The resume records live in a group of their own so that Zarr readers see a node.
        let state = self.root.join("fwlidar_state");
        fs::create_dir_all(&state).map_err(io(&state))?;
        let state_meta = json!({
            "zarr_format": 3,
            "node_type": "group",
            "attributes": {"description": "fwlidar resume records: tiles/TX_TY holds the watermark of each tile (first pulse sequence number not in it)"},
        });
        write_atomic(&state.join("zarr.json"), state_meta.to_string().as_bytes())?;
        let mut consolidated_state = state_meta;
        consolidated_state["consolidated_metadata"] = json!({
            "kind": "inline",
            "must_understand": false,
            "metadata": {},
        });
        nodes.insert("fwlidar_state".into(), consolidated_state);
        Ok(())
    }

    /// Writes the metadata of the four data arrays (of `shape` voxels, z, y, x; chunked by a
    /// height chunk and a tile) and adds them to `nodes`.
    fn write_data_arrays(
        &self,
        shape: [u64; 3],
        nodes: &mut serde_json::Map<String, Value>,
    ) -> Result<(), StoreError> {
        let g = &self.grid;
        for a in ARRAYS {
            let (dt, fill) = dtype(a);
            let meta = self.write_array_meta(
                a,
                json!(shape),
                dt,
                fill,
                json!(self.layout.chunk_shape(g)),
                json!(["z", "y", "x"]),
                self.data_array_attrs(a),
            )?;
            nodes.insert(a.into(), meta);
        }
        Ok(())
    }

    /// The CF attributes of data array `a`: its long name, units (the intensity's for the
    /// intensities) and, for the intensity sum, the quantum as scale factor.
    fn data_array_attrs(&self, a: &str) -> Value {
        let g = &self.grid;
        let units = &self.info.intensity_units;
        let mut attrs = json!({
            "grid_mapping": "spatial_ref",
            "coordinates": "spatial_ref",
        });
        let m = attrs.as_object_mut().expect("object");
        match a {
            "intensity_sum" => {
                m.insert("long_name".into(), json!("sum of deposited intensity"));
                m.insert("units".into(), json!(units));
                m.insert("scale_factor".into(), json!(g.intensity_quantum));
            }
            "sample_count" => {
                m.insert("long_name".into(), json!("waveform bins deposited"));
                m.insert("units".into(), json!("1"));
            }
            "intensity_max" => {
                m.insert("long_name".into(), json!("largest deposited intensity"));
                m.insert("units".into(), json!(units));
            }
            _ => {
                m.insert(
                    "long_name".into(),
                    json!("pulses whose beam passed through the voxel"),
                );
                m.insert("units".into(), json!("1"));
            }
        }
        attrs
    }

    /// Writes the coordinate arrays `x`, `y`, `z` (voxel centres of the span's `shape`, metres)
    /// with their one chunk each, and adds them to `nodes`.
    fn write_coordinates(
        &mut self,
        shape: [u64; 3],
        nodes: &mut serde_json::Map<String, Value>,
    ) -> Result<(), StoreError> {
        let g = &self.grid;
        let corner = self.span.origin_m(g);
        let z0 = self.span.z_bottom_m(g);
        let (height_name, height_long) = match g.height {
            super::grid::HeightMode::Absolute => ("height", "height of the voxel centre (CRS z)"),
            super::grid::HeightMode::AboveDem => (
                "height_above_ground",
                "height of the voxel centre above the DEM",
            ),
        };
        // Coordinates: voxel centres, `first + (i + 0.5) · step` for `n` values.
        let mut chunks = Vec::with_capacity(3);
        let xs = Centres::new(corner[0], g.voxel_size_m[0], shape[2]);
        let ys = Centres::new(corner[1], g.voxel_size_m[1], shape[1]);
        let zs = Centres::new(z0, g.voxel_size_m[2], shape[0]);
        for (name, vals, attrs) in [
            (
                "x",
                xs,
                json!({"standard_name": "projection_x_coordinate", "long_name": "easting of the voxel centre", "units": "m", "axis": "X"}),
            ),
            (
                "y",
                ys,
                json!({"standard_name": "projection_y_coordinate", "long_name": "northing of the voxel centre", "units": "m", "axis": "Y"}),
            ),
            (
                "z",
                zs,
                json!({"standard_name": height_name, "long_name": height_long, "units": "m", "axis": "Z", "positive": "up"}),
            ),
        ] {
            let meta = self.write_array_meta(
                name,
                json!([vals.n]),
                "float64",
                json!("NaN"),
                json!([vals.n.max(1)]),
                json!([name]),
                attrs,
            )?;
            nodes.insert(name.into(), meta);
            chunks.push((name, vals));
        }
        let (root, codec) = (self.root.clone(), self.layout.codec());
        let write_all = move || {
            chunks
                .iter()
                .try_for_each(|(name, vals)| write_coordinate_chunk(&root, codec, name, *vals))
        };
        if (shape[0] + shape[1] + shape[2]) as usize > COORDINATES_IN_BACKGROUND {
            let spawned = std::thread::Builder::new()
                .name("voxel-coordinates".into())
                .spawn(write_all);
            match spawned {
                Ok(h) => self.coordinates = Some(h),
                Err(e) => return Err(io(&self.root)(e)),
            }
            return Ok(());
        }
        write_all()
    }

    /// Waits for coordinate chunks being written in the background, and returns their error.
    fn join_coordinates(&mut self) -> Result<(), StoreError> {
        let Some(h) = self.coordinates.take() else {
            return Ok(());
        };
        h.join().unwrap_or_else(|_| {
            Err(invalid(
                &self.root,
                "the thread writing the coordinate arrays panicked",
            ))
        })
    }

    /// Writes the CF grid mapping `spatial_ref` (a 0-d variable carrying the CRS as WKT and
    /// EPSG code, when known) and adds it to `nodes`.
    fn write_spatial_ref(
        &self,
        nodes: &mut serde_json::Map<String, Value>,
    ) -> Result<(), StoreError> {
        // CF grid mapping: a 0-d variable carrying the CRS.
        let mut sr = json!({"long_name": "coordinate reference system"});
        if let Some(w) = &self.info.crs_wkt {
            sr["crs_wkt"] = json!(w);
            sr["spatial_ref"] = json!(w);
        }
        if let Some(code) = self.info.epsg {
            sr["epsg_code"] = json!(format!("EPSG:{code}"));
        }
        let meta = self.write_array_meta(
            "spatial_ref",
            json!([]),
            "int32",
            json!(0),
            json!([]),
            json!([]),
            sr,
        )?;
        nodes.insert("spatial_ref".into(), meta);
        Ok(())
    }

    /// Writes the root group last, its attributes naming the span the chunks are keyed on
    /// (origin and extent in metres) and its consolidated metadata holding `nodes`; the root
    /// directory is synced.
    fn write_root_group(&self, nodes: serde_json::Map<String, Value>) -> Result<(), StoreError> {
        let g = &self.grid;
        let span = &self.span;
        let corner = span.origin_m(g);
        let extent = g.extent_origin();
        let z0 = span.z_bottom_m(g);
        let tm = g.tile_m();
        // The root last: its attributes name the span the chunks are keyed on.
        let group = json!({
            "zarr_format": 3,
            "node_type": "group",
            "attributes": {
                "Conventions": "CF-1.10",
                "title": "fwlidar voxel tiles: calibrated full-waveform intensity per voxel",
                "crs_wkt": self.info.crs_wkt,
                "epsg": self.info.epsg,
                "origin_m": [corner[0], corner[1], z0],
                "extent_m": [
                    extent[0],
                    extent[1],
                    extent[0] + g.tiles[0] as f64 * tm[0],
                    extent[1] + g.tiles[1] as f64 * tm[1],
                ],
                "tile_grid_origin_m": g.origin_m,
                "voxel_size_m": g.voxel_size_m,
                "tile_size_m": tm,
                "tile_columns": g.tile_columns,
                "height": g.height.name(),
                "intensity_units": self.info.intensity_units,
                "intensity_quantum": g.intensity_quantum,
                "configuration": self.info.configuration,
                "fwlidar": {
                    "version": env!("CARGO_PKG_VERSION"),
                    "grid": g,
                    "arrays": span,
                    "run_key": self.info.run_key,
                },
            },
            // Zarr v3 consolidated metadata, as zarr-python 3 writes and reads it.
            "consolidated_metadata": {
                "kind": "inline",
                "must_understand": false,
                "metadata": nodes,
            },
        });
        write_atomic(&self.root.join("zarr.json"), group.to_string().as_bytes())?;
        sync_dir(&self.root);
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn write_array_meta(
        &self,
        name: &str,
        shape: Value,
        data_type: &str,
        fill: Value,
        chunk: Value,
        dims: Value,
        attrs: Value,
    ) -> Result<Value, StoreError> {
        let dir = self.root.join(name);
        fs::create_dir_all(&dir).map_err(io(&dir))?;
        let codecs = if data_type == "int32" && shape == json!([]) {
            json!([{"name": "bytes", "configuration": {"endian": "little"}}])
        } else if ARRAYS.contains(&name) {
            self.layout.meta(&self.grid)
        } else {
            json!([
                {"name": "bytes", "configuration": {"endian": "little"}},
                self.layout.codec().meta()
            ])
        };
        let meta = json!({
            "zarr_format": 3,
            "node_type": "array",
            "shape": shape,
            "data_type": data_type,
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": chunk}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": fill,
            "codecs": codecs,
            "attributes": attrs,
            "dimension_names": dims,
        });
        write_atomic(&dir.join("zarr.json"), meta.to_string().as_bytes())?;
        Ok(meta)
    }
}

/// The centres of `n` voxels along an axis: `first + (i + 0.5) · step`, metres.
#[derive(Clone, Copy, Debug)]
struct Centres {
    first: f64,
    step: f64,
    n: u64,
}

impl Centres {
    fn new(first: f64, step: f64, n: u64) -> Self {
        Centres { first, step, n }
    }
}

/// Writes the one chunk of coordinate array `name` holding `vals` (metres, little-endian
/// float64, through the store's codec); an empty coordinate (a store with no tile) has none,
/// and a chunk left from before is removed.
fn write_coordinate_chunk(
    root: &Path,
    codec: Codec,
    name: &str,
    vals: Centres,
) -> Result<(), StoreError> {
    let path = root.join(name).join("c").join("0");
    if vals.n == 0 {
        // An empty coordinate (a store with no tile) has no chunk.
        if path.exists() {
            fs::remove_file(&path).map_err(io(&path))?;
        }
        return Ok(());
    }
    let mut raw = Vec::with_capacity(vals.n as usize * 8);
    for i in 0..vals.n {
        let v = vals.first + (i as f64 + 0.5) * vals.step;
        raw.extend_from_slice(&v.to_le_bytes());
    }
    let mut packed = Vec::new();
    codec.encode(&raw, &mut packed).map_err(io(&path))?;
    fs::create_dir_all(path.parent().unwrap_or(root)).map_err(io(&path))?;
    write_atomic(&path, &packed)
}

impl Drop for ZarrStore {
    /// Waits for coordinate chunks still being written (an error is logged: nothing else can
    /// report it here; the next opening of the store writes them again).
    fn drop(&mut self) {
        if let Err(e) = self.join_coordinates() {
            tracing::error!("voxel store coordinates not written: {e}");
        }
    }
}

/// What writing a tile cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WriteCost {
    /// Chunk (shard) files written (arrays × height chunks).
    pub chunks: u64,
    /// Inner chunks encoded (arrays × blocks holding data; `chunks` when not sharded).
    pub inner_chunks: u64,
    /// Bytes through the compressor.
    pub raw_bytes: u64,
    /// Bytes written to disk.
    pub stored_bytes: u64,
}

/// One `syncfs` of the file system holding `root` (Linux); false when unavailable or failed.
fn syncfs(root: &Path) -> bool {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        if let Ok(d) = File::open(root) {
            // SAFETY: `syncfs` only reads the descriptor, which `d` keeps open for the call.
            return unsafe { libc::syncfs(d.as_raw_fd()) } == 0;
        }
    }
    let _ = root;
    false
}

/// Between the in-memory order of a height chunk (`(j·T + i)·H + kk`, columns contiguous) and
/// the `[z, y, x]` order of a block of it: block `(bj, bi)` of `B × B` columns holds voxel
/// `(kk, jj, ii)` at `(kk·B + jj)·B + ii`, column `(bj·B + jj)·T + bi·B + ii`. An unsharded
/// chunk is the one block `B = T`; a shard's inner chunks are its blocks in C order.
///
/// Transposed (Zarr's `transpose` codec, order `[1, 2, 0]`: `[y, x, z]`), voxel `(kk, jj, ii)`
/// of a block is at `(jj·B + ii)·H + kk`: each column's levels contiguous, as in memory.
#[derive(Clone, Copy)]
struct DiskOrder {
    side: usize,
    levels: usize,
    block: usize,
    transposed: bool,
}

impl DiskOrder {
    fn of(grid: &Grid, layout: Layout) -> Self {
        DiskOrder {
            side: grid.tile_columns as usize,
            levels: grid.chunk_levels() as usize,
            block: layout.block(grid).max(1),
            transposed: matches!(
                layout,
                Layout::Sharded {
                    transposed: true,
                    ..
                }
            ),
        }
    }

    /// Where level `k` of column `(jj, ii)` of a block lies, and the step from one level to
    /// the next, in values.
    fn place(self, jj: usize, ii: usize) -> (usize, usize) {
        let b = self.block;
        if self.transposed {
            ((jj * b + ii) * self.levels, 1)
        } else {
            (jj * b + ii, b * b)
        }
    }

    /// Blocks along each side.
    fn blocks(self) -> usize {
        self.side / self.block
    }

    /// Voxels of a block.
    fn block_voxels(self) -> usize {
        self.block * self.block * self.levels
    }

    /// Column of the first voxel of each row `jj` of block `b` (C order of blocks).
    fn row_start(self, b: usize, jj: usize) -> usize {
        let n = self.blocks();
        let (bj, bi) = (b / n, b % n);
        (bj * self.block + jj) * self.side + bi * self.block
    }

    /// Counts in `out` (one entry per block) the columns of each block of `c` where a sample
    /// or a pass landed: the blocks to encode (count > 0), the same for all four arrays. Only
    /// the columns written (or read back) are looked at (`Chunk::live_in`).
    fn occupied(self, c: &super::tile::Chunk, out: &mut Vec<u32>) {
        let b = self.block;
        out.clear();
        out.extend((0..self.blocks() * self.blocks()).map(|blk| {
            (0..b)
                .map(|jj| {
                    let r = self.row_start(blk, jj);
                    c.live_in(r..r + b)
                })
                .sum::<u32>()
        }));
    }

    /// Appends block `blk` of `mem` (an array of chunk `c`, whose unwritten columns hold
    /// `fill`) to `out` in `[z, y, x]` order, little endian. Unwritten columns are not read:
    /// the block starts as `fill` and only the written columns are placed.
    fn write<T: Copy, const N: usize>(
        self,
        c: &super::tile::Chunk,
        pick: for<'a> fn(super::tile::Column<'a>) -> &'a [T],
        fill: T,
        blk: usize,
        out: &mut Vec<u8>,
        enc: fn(T) -> [u8; N],
    ) {
        let (b, l) = (self.block, self.levels);
        let start = out.len();
        out.resize(start + self.block_voxels() * N, 0);
        let dst = &mut out[start..];
        let f = enc(fill);
        if f != [0; N] {
            // The fill value, then the filled part copied onto the rest, doubling (memcpy
            // speed; a store per value was ~8 % of the sparse line's CPU with NaN fills).
            dst[..N].copy_from_slice(&f);
            let mut done = N;
            while done < dst.len() {
                let n = done.min(dst.len() - done);
                dst.copy_within(..n, done);
                done += n;
            }
        }
        // Each column's levels are read where they lie (contiguous, `col·L + k`) and placed at
        // `place` (transposed: contiguous again; else `[z, y, x]` = `((k·B + jj)·B + c)·N`, a
        // stride of one level's plane through the block): the tile writer's CPU on the sparse
        // 7.2 km line 18.35 → 16.6 s against
        // gathering each level's plane with a push per value (the same bytes). Writing into
        // the spare capacity instead of zero-filling first measured the same, so it is not
        // done.
        for jj in 0..b {
            let c0 = self.row_start(blk, jj);
            for i in 0..b {
                let Some(column) = c.column(c0 + i).map(pick) else {
                    continue;
                };
                let column = &column[..l.min(column.len())];
                let (first, step) = self.place(jj, i);
                let (mut at, step) = (first * N, step * N);
                for &v in column {
                    dst[at..at + N].copy_from_slice(&enc(v));
                    at += step;
                }
            }
        }
    }

    /// Gives block `blk` of `mem` (an array of chunk `c`, whose unwritten columns hold `fill`)
    /// to `frame` as runs of values, in the column order of the transposed layout (as
    /// [`write`](Self::write) places them): an unwritten column is one run of `fill`.
    fn runs<T: Copy, const N: usize>(
        self,
        c: &super::tile::Chunk,
        pick: for<'a> fn(super::tile::Column<'a>) -> &'a [T],
        fill: T,
        blk: usize,
        frame: &mut super::fill_frame::FillFrame,
        enc: fn(T) -> [u8; N],
    ) {
        debug_assert!(self.transposed);
        let (b, l) = (self.block, self.levels);
        let f = enc(fill);
        frame.begin(N);
        for jj in 0..b {
            let c0 = self.row_start(blk, jj);
            for i in 0..b {
                let Some(column) = c.column(c0 + i).map(pick) else {
                    frame.push_run(f, l);
                    continue;
                };
                let column = &column[..l.min(column.len())];
                for &v in column {
                    frame.push(enc(v));
                }
                frame.push_run(f, l - column.len());
            }
        }
    }

    /// Fills one array (`pick`) of block `blk` of chunk `c` from `[z, y, x]`-order bytes `raw`
    /// (of the block's length); every column of the block is then written.
    fn read<T: Copy, const N: usize>(
        self,
        raw: &[u8],
        blk: usize,
        c: &mut super::tile::Chunk,
        pick: for<'a> fn(super::tile::ColumnMut<'a>) -> &'a mut [T],
        dec: fn([u8; N]) -> T,
    ) {
        let (b, l) = (self.block, self.levels);
        for jj in 0..b {
            let c0 = self.row_start(blk, jj);
            for i in 0..b {
                if c0 + i >= c.columns() {
                    continue;
                }
                let dst = pick(c.column_mut(c0 + i));
                let (first, step) = self.place(jj, i);
                for (k, d) in dst.iter_mut().enumerate().take(l) {
                    let at = (first + k * step) * N;
                    if let Some(bytes) = raw.get(at..at + N).and_then(|x| x.try_into().ok()) {
                        *d = dec(bytes);
                    }
                }
            }
        }
    }
}

/// Whether `span` lies inside the grid's extent (every span a store takes does: the tiles
/// written are inside it).
fn within(span: &Span, grid: &Grid) -> bool {
    let empty = span.tiles.contains(&0);
    (0..2).all(|a| {
        let (lo, hi) = (
            span.tile_min[a] as i128,
            span.tile_min[a] as i128 + span.tiles[a] as i128,
        );
        let (elo, ehi) = (
            grid.tile_min[a] as i128,
            grid.tile_min[a] as i128 + grid.tiles[a] as i128,
        );
        span.tiles[a] <= grid.tiles[a] && (empty || (lo >= elo && hi <= ehi))
    }) && span.level_chunk_min as u64 + span.level_chunks as u64 <= grid.height_chunks() as u64
}

fn remove_pending(dir: &Path) -> Result<u64, StoreError> {
    let mut n = 0;
    for entry in fs::read_dir(dir).map_err(io(dir))? {
        let entry = entry.map_err(io(dir))?;
        let p = entry.path();
        if entry.file_type().map_err(io(&p))?.is_dir() {
            n += remove_pending(&p)?;
        } else if p.extension().is_some_and(|e| e == "pending")
            || p.file_name()
                .is_some_and(|n| n.to_string_lossy().contains(".pending."))
        {
            fs::remove_file(&p).map_err(io(&p))?;
            n += 1;
        }
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::voxel::grid::VoxelConfig;

    fn grid() -> Grid {
        Grid::new(
            &VoxelConfig {
                extent_m: Some([0.0, 0.0, 16.0, 8.0]),
                z_range_m: [0.0, 0.6],
                tile_columns: 8,
                ..VoxelConfig::default()
            },
            [0.0, 0.0],
        )
    }

    fn info(key: &str) -> StoreInfo {
        StoreInfo {
            crs_wkt: None,
            epsg: Some(32736),
            intensity_units: "V".into(),
            run_key: key.into(),
            configuration: String::new(),
        }
    }

    fn sample(n: usize, seed: u32) -> TileData {
        let mut t = TileData::new(64, n / 64, 4);
        for i in 0..n {
            if (i as u32 ^ seed).is_multiple_of(3) {
                t.deposit(i, i as i64 * 1000 - 7, i as f32 * 0.5);
                t.pass(i);
            }
        }
        t
    }

    #[test]
    fn a_tile_written_reads_back_identically_and_survives_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let g = grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        let t = sample(n, 1);
        s.write_tile([1, 0], &t, 42).unwrap();
        let mut back = TileData::new(64, n / 64, 4);
        assert!(s.read_tile([1, 0], &mut back).unwrap());
        assert_eq!(back.dense().sum_q, t.dense().sum_q);
        assert!(!s.read_tile([0, 0], &mut back).unwrap());
        let mut s2 = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        assert_eq!(s2.watermark([1, 0]), Some(42));
        assert!(s2.read_tile([1, 0], &mut back).unwrap());
        assert_eq!(back.dense().sum_q, t.dense().sum_q);
        assert_eq!(back.dense().samples, t.dense().samples);
        assert_eq!(back.dense().pulses, t.dense().pulses);
        assert!(
            back.dense()
                .max
                .iter()
                .zip(&t.dense().max)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        // Another run or grid: refused, nothing changed.
        let e = ZarrStore::create_or_open(&root, g.clone(), info("b"))
            .err()
            .unwrap();
        assert!(e.to_string().contains("another run"), "{e}");
        let mut g2 = g.clone();
        g2.levels += 1;
        let e = ZarrStore::create_or_open(&root, g2, info("a"))
            .err()
            .unwrap();
        assert!(e.to_string().contains("height ranges differ"), "{e}");
    }

    #[test]
    fn interrupted_commits_complete_and_uncommitted_chunks_vanish() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let g = grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        let old = sample(n, 1);
        s.write_tile([0, 0], &old, 10).unwrap();
        // A crash after the commit record, before the renames: the new content must win.
        let new = sample(n, 2);
        s.write_tile([1, 0], &new, 5).unwrap();
        let rec = s.record_path([1, 0]);
        for a in ARRAYS {
            fs::rename(
                s.chunk_path(a, [1, 0], 0).unwrap(),
                s.pending_path(a, [1, 0], 0).unwrap(),
            )
            .unwrap();
        }
        fs::write(&rec, br#"{"watermark": 20, "pending": true}"#).unwrap();
        // A crash before the commit record: pending chunks of tile (0,0) must be discarded.
        for a in ARRAYS {
            fs::write(s.pending_path(a, [0, 0], 0).unwrap(), b"garbage").unwrap();
        }
        let mut s2 = ZarrStore::open(&root).unwrap();
        assert_eq!(s2.recovered_commits, 1);
        assert_eq!(s2.discarded_pending, 4);
        assert_eq!(s2.watermark([1, 0]), Some(20));
        let mut back = TileData::new(64, n / 64, 4);
        s2.read_tile([1, 0], &mut back).unwrap();
        assert_eq!(back.dense().sum_q, new.dense().sum_q);
        s2.read_tile([0, 0], &mut back).unwrap();
        assert_eq!(back.dense().sum_q, old.dense().sum_q);
        assert_eq!(s2.watermark([0, 0]), Some(10));
    }

    #[test]
    fn a_corrupt_chunk_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let g = grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(&root, g, info("a")).unwrap();
        s.write_tile([0, 0], &sample(n, 1), 1).unwrap();
        let p = s.chunk_path("sample_count", [0, 0], 0).unwrap();
        let good = fs::read(&p).unwrap();
        let mut back = TileData::new(64, n / 64, 4);
        // Shorter than the shard index.
        fs::write(&p, b"not zstd").unwrap();
        let e = s.read_tile([0, 0], &mut back).unwrap_err().to_string();
        assert!(e.contains("sample_count") && e.contains("index"), "{e}");
        // The index intact, the inner chunk garbled.
        let mut bad = good.clone();
        bad[..8].copy_from_slice(b"not zstd");
        fs::write(&p, &bad).unwrap();
        let e = s.read_tile([0, 0], &mut back).unwrap_err().to_string();
        assert!(
            e.contains("sample_count") && e.contains("decompress"),
            "{e}"
        );
        // An index entry pointing past the data.
        let mut bad = good;
        let at = bad.len() - 16;
        bad[at..at + 8].copy_from_slice(&(1u64 << 40).to_le_bytes());
        fs::write(&p, &bad).unwrap();
        let e = s.read_tile([0, 0], &mut back).unwrap_err().to_string();
        assert!(e.contains("outside the shard"), "{e}");
    }

    /// Tiles of 32 × 32 columns, 4 levels: shards of 4 × 4 inner chunks of 8 × 8 columns.
    fn shard_grid() -> Grid {
        Grid::new(
            &VoxelConfig {
                extent_m: Some([0.0, 0.0, 32.0, 16.0]),
                z_range_m: [0.0, 0.6],
                tile_columns: 32,
                ..VoxelConfig::default()
            },
            [0.0, 0.0],
        )
    }

    /// A tile of `g` with deposits and passes in every third voxel (by `seed`).
    fn sample_for(g: &Grid, seed: u32) -> TileData {
        let mut t = TileData::for_grid(g);
        for i in 0..g.tile_voxels() {
            if (i as u32 ^ seed).is_multiple_of(3) {
                t.deposit(i, i as i64 * 1000 - 7, i as f32 * 0.5);
                t.pass(i);
            }
        }
        t
    }

    /// The same accumulators, bit for bit (maxima included).
    fn assert_same(a: &TileData, b: &TileData) {
        let (a, b) = (a.dense(), b.dense());
        assert_eq!(a.sum_q, b.sum_q);
        assert_eq!(a.samples, b.samples);
        assert_eq!(a.pulses, b.pulses);
        let bits = |m: &[f32]| m.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.max), bits(&b.max));
    }

    /// The `(offset, nbytes)` entries of a shard's index (no checksum).
    fn shard_index(path: &Path, blocks: usize) -> Vec<(u64, u64)> {
        let b = fs::read(path).unwrap();
        b[b.len() - blocks * 16..]
            .chunks_exact(16)
            .map(|e| {
                (
                    u64::from_le_bytes(e[..8].try_into().unwrap()),
                    u64::from_le_bytes(e[8..].try_into().unwrap()),
                )
            })
            .collect()
    }

    #[test]
    fn a_sparse_tile_encodes_only_the_inner_chunks_holding_data_in_all_four_arrays() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("v.zarr");
        let g = shard_grid();
        assert_eq!(
            Layout::for_grid(&g),
            Layout::Sharded {
                group: None,
                inner: 8,
                codec: Codec::Zstd(1),
                index_crc: false,
                transposed: true,
            }
        );
        let l = g.levels as usize;
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        let mut t = TileData::for_grid(&g);
        // Column (i=3, j=1): block (0, 0); column (i=17, j=30): block (3, 2), a pass only.
        t.deposit((32 + 3) * l + 2, 77, 7.5);
        t.pass((32 + 3) * l + 2);
        t.pass((30 * 32 + 17) * l + 1);
        let (chunks, cost) = s.write_tile([0, 0], &t, 3).unwrap();
        assert_eq!(chunks, vec![0]);
        assert_eq!(cost.chunks, 4, "one shard per array");
        assert_eq!(cost.inner_chunks, 8, "two inner chunks per array");
        let inner_raw = 8 * 8 * g.chunk_levels() as u64;
        assert_eq!(cost.raw_bytes, 2 * inner_raw * (8 + 4 + 4 + 4));
        let mut stored = 0;
        for a in ARRAYS {
            let p = s.chunk_path(a, [0, 0], 0).unwrap();
            stored += fs::metadata(&p).unwrap().len();
            let idx = shard_index(&p, 16);
            let present: Vec<usize> = (0..16).filter(|b| idx[*b].0 != u64::MAX).collect();
            assert_eq!(present, vec![0, 3 * 4 + 2], "{a}");
            for (b, (o, n)) in idx.iter().enumerate() {
                if !present.contains(&b) {
                    assert_eq!((*o, *n), (u64::MAX, u64::MAX));
                }
            }
            // Inner chunks back to back from the shard's start, then the index.
            let (o0, n0) = idx[0];
            let (o1, n1) = idx[14];
            assert_eq!((o0, o1), (0, n0));
            assert_eq!(fs::metadata(&p).unwrap().len(), n0 + n1 + 16 * 16);
        }
        assert_eq!(cost.stored_bytes, stored);
        let mut back = TileData::for_grid(&g);
        assert!(s.read_tile([0, 0], &mut back).unwrap());
        assert_same(&back, &t);
    }

    #[test]
    fn stores_of_earlier_layouts_are_read_and_resumed_in_their_own_layout() {
        for old in [Layout::Plain(Codec::Zstd(1)), Layout::Plain(Codec::Gzip(1))] {
            let dir = tempfile::tempdir().unwrap();
            let root = dir.path().join("v.zarr");
            let g = shard_grid();
            let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
            // As an earlier version wrote it: one compressed chunk per file.
            s.layout = old;
            s.write_metadata().unwrap();
            let a = sample_for(&g, 1);
            s.write_tile([0, 0], &a, 4).unwrap();
            let p = s.chunk_path("sample_count", [0, 0], 0).unwrap();
            let mut raw = Vec::new();
            match old.codec() {
                Codec::Zstd(_) => zstd::stream::Decoder::new(File::open(&p).unwrap())
                    .unwrap()
                    .read_to_end(&mut raw)
                    .unwrap(),
                Codec::Gzip(_) => GzDecoder::new(File::open(&p).unwrap())
                    .read_to_end(&mut raw)
                    .unwrap(),
            };
            assert_eq!(raw.len(), g.chunk_voxels() * 4, "{old:?}: a whole chunk");
            drop(s);
            // Read as it is; a resumed run writes on in the store's layout.
            let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
            assert_eq!(s.layout, old);
            let mut back = TileData::for_grid(&g);
            assert!(s.read_tile([0, 0], &mut back).unwrap());
            assert_same(&back, &a);
            let b = sample_for(&g, 2);
            s.write_tile([1, 0], &b, 5).unwrap();
            s.fit().unwrap();
            let mut r = ZarrStore::open(&root).unwrap();
            assert_eq!(r.layout, old);
            assert!(r.read_tile([1, 0], &mut back).unwrap());
            assert_same(&back, &b);
            assert!(r.read_tile([0, 0], &mut back).unwrap());
            assert_same(&back, &a);
        }
    }

    #[test]
    fn inner_chunks_are_stored_column_by_column_and_level_ordered_shards_still_read() {
        let dir = tempfile::tempdir().unwrap();
        let g = shard_grid();
        let h = g.chunk_levels() as usize;
        let l = g.levels as usize;
        // Column (i=3, j=1) of block (0, 0): levels 0, 1 and 2 hold samples.
        let mut t = TileData::for_grid(&g);
        for k in 0..3 {
            t.deposit((32 + 3) * l + k, 10 + k as i64, 1.0);
        }
        let mut s =
            ZarrStore::create_or_open(&dir.path().join("new"), g.clone(), info("a")).unwrap();
        s.write_tile([0, 0], &t, 1).unwrap();
        let p = s.chunk_path("sample_count", [0, 0], 0).unwrap();
        let (o, n) = shard_index(&p, 16)[0];
        let bytes = fs::read(&p).unwrap();
        let raw = zstd::bulk::decompress(&bytes[o as usize..(o + n) as usize], 1 << 20).unwrap();
        let counts: Vec<u32> = raw
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        // `[y, x, z]`: column (jj = 1, ii = 3) of the 8 × 8 block starts at (1·8 + 3)·H.
        let at = (8 + 3) * h;
        assert_eq!(&counts[at..at + 4], &[1, 1, 1, 0]);
        assert_eq!(counts.iter().sum::<u32>(), 3);
        // A store of the order before (`[z, y, x]`, no `transpose` codec) reads and resumes in it.
        let root = dir.path().join("old");
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        let Layout::Sharded {
            inner,
            codec,
            index_crc,
            group,
            ..
        } = s.layout
        else {
            panic!("{:?}", s.layout);
        };
        let old = Layout::Sharded {
            inner,
            codec,
            index_crc,
            group,
            transposed: false,
        };
        s.layout = old;
        s.write_metadata().unwrap();
        let a = sample_for(&g, 1);
        s.write_tile([0, 0], &a, 4).unwrap();
        drop(s);
        let text = fs::read_to_string(root.join("sample_count/zarr.json")).unwrap();
        assert!(!text.contains("transpose"), "{text}");
        let mut s = ZarrStore::create_or_open(&root, g.clone(), info("a")).unwrap();
        assert_eq!(s.layout, old);
        let mut back = TileData::for_grid(&g);
        assert!(s.read_tile([0, 0], &mut back).unwrap());
        assert_same(&back, &a);
        // And a new store's metadata names the codec as zarr-python writes it.
        let text = fs::read_to_string(dir.path().join("new/sample_count/zarr.json")).unwrap();
        assert!(
            text.contains(r#"{"configuration":{"order":[1,2,0]},"name":"transpose"}"#),
            "{text}"
        );
    }

    #[test]
    fn a_copied_tile_is_the_bytes_a_decode_and_write_gives() {
        let dir = tempfile::tempdir().unwrap();
        let g = shard_grid();
        let mut src =
            ZarrStore::create_or_open(&dir.path().join("a"), g.clone(), info("a")).unwrap();
        src.write_tile([0, 0], &sample_for(&g, 1), 7).unwrap();
        src.write_tile([1, 0], &sample_for(&g, 2), 7).unwrap();
        let (mut copied, mut written) = (
            ZarrStore::create_or_open(&dir.path().join("c"), g.clone(), info("m")).unwrap(),
            ZarrStore::create_or_open(&dir.path().join("w"), g.clone(), info("m")).unwrap(),
        );
        let mut t = TileData::for_grid(&g);
        for tile in [[0, 0], [1, 0]] {
            assert!(copied.copy_tile(&src, tile, 0).unwrap());
            assert!(src.read_tile(tile, &mut t).unwrap());
            written.write_tile(tile, &t, 0).unwrap();
        }
        // Held already, or absent from the source: not copied, nothing written.
        assert!(!copied.copy_tile(&src, [0, 0], 0).unwrap());
        assert!(!copied.copy_tile(&src, [0, 1], 0).unwrap());
        copied.fit().unwrap();
        written.fit().unwrap();
        let (c, w) = (files(&dir.path().join("c")), files(&dir.path().join("w")));
        assert!(c.len() > 8);
        assert!(c == w, "copying differs from decoding and writing");
        let mut back = TileData::for_grid(&g);
        let mut reopened = ZarrStore::open(&dir.path().join("c")).unwrap();
        assert!(reopened.read_tile([1, 0], &mut back).unwrap());
        assert_same(&back, &sample_for(&g, 2));
    }

    /// A grid of 4 m tiles over [-32, 32)² m (16 × 16 tiles).
    fn wide_grid() -> Grid {
        Grid::new(
            &VoxelConfig {
                extent_m: Some([-32.0, -32.0, 32.0, 32.0]),
                z_range_m: [0.0, 0.6],
                tile_columns: 8,
                ..VoxelConfig::default()
            },
            [0.0, 0.0],
        )
    }

    /// Every file under `root` with its bytes.
    fn files(root: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
        fn walk(base: &Path, dir: &Path, out: &mut std::collections::BTreeMap<String, Vec<u8>>) {
            for e in fs::read_dir(dir).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    walk(base, &p, out);
                } else {
                    let rel = p.strip_prefix(base).unwrap().display().to_string();
                    out.insert(rel, fs::read(&p).unwrap());
                }
            }
        }
        let mut m = Default::default();
        walk(root, root, &mut m);
        m
    }

    fn json_of(path: &Path) -> Value {
        serde_json::from_slice(&fs::read(path).unwrap()).unwrap()
    }

    fn f64s(path: &Path) -> Vec<f64> {
        let mut raw = Vec::new();
        zstd::stream::Decoder::new(File::open(path).unwrap())
            .unwrap()
            .read_to_end(&mut raw)
            .unwrap();
        raw.chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }

    const WRITTEN: [[i64; 2]; 3] = [[-3, 2], [1, -1], [2, 2]];

    /// A store on [`wide_grid`] with the tiles of `WRITTEN`, as a run leaves it before `fit`.
    fn live_store(root: &Path) -> (ZarrStore, Vec<TileData>) {
        let g = wide_grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open(root, g, info("a")).unwrap();
        let mut data = Vec::new();
        for (i, t) in WRITTEN.iter().enumerate() {
            let d = sample(n, i as u32 + 1);
            s.write_tile(*t, &d, 10 + i as u64).unwrap();
            data.push(d);
        }
        (s, data)
    }

    const GROUP: ShardGroup = ShardGroup {
        tiles: 4,
        height_chunks: 1,
    };

    /// A grouped store on [`wide_grid`] with `WRITTEN` and a tile sharing `[1, -1]`'s group.
    fn grouped_store(root: &Path) -> (ZarrStore, Vec<([i64; 2], TileData)>) {
        let g = wide_grid();
        let n = g.tile_voxels();
        let mut s = ZarrStore::create_or_open_grouped(root, g, info("a"), Some(GROUP)).unwrap();
        let mut data = Vec::new();
        for (i, t) in WRITTEN.iter().chain(&[[0, -2]]).enumerate() {
            let d = sample(n, i as u32 + 1);
            s.write_tile(*t, &d, 10 + i as u64).unwrap();
            data.push((*t, d));
        }
        (s, data)
    }

    fn assert_grouped_holds(s: &mut ZarrStore, data: &[([i64; 2], TileData)]) {
        let mut got = TileData::for_grid(s.grid());
        for (t, d) in data {
            assert!(s.read_tile(*t, &mut got).unwrap(), "{t:?}");
            assert_same(&got, d);
        }
        assert_eq!(s.tiles().len(), data.len());
    }

    #[test]
    fn grouped_tiles_share_a_file_per_array_and_read_back_identically_after_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let (mut s, data) = grouped_store(&root);
        // Nothing of the data on disk until a group is written out.
        assert!(
            !files(&root)
                .keys()
                .any(|k| k.starts_with("sample_count/c/"))
        );
        assert_grouped_holds(&mut s, &data); // reading writes the tile's group first
        s.fit().unwrap();
        let shards: Vec<String> = files(&root)
            .into_keys()
            .filter(|k| k.starts_with("sample_count/c/"))
            .collect();
        // [-3, 2], [2, 2] and {[1, -1], [0, -2]}: three groups of 4 x 4 tiles.
        assert_eq!(shards.len(), 3, "{shards:?}");
        assert!(
            !files(&root)
                .keys()
                .any(|k| k.contains("fwlidar_state/tiles"))
        );
        let mut again = ZarrStore::open(&root).unwrap();
        assert_eq!(again.layout.group(), Some(GROUP));
        assert_grouped_holds(&mut again, &data);
        for (t, _) in &data {
            assert_eq!(again.tile_chunks(*t), s.tile_chunks(*t));
        }
        // The arrays start at a group's first tile.
        let sp = *again.span();
        assert_eq!((sp.tile_min[0] - again.grid.tile_min[0]) % 4, 0);
        assert_eq!((sp.tile_min[1] - again.grid.tile_min[1]) % 4, 0);
        // Reopened to write (the extent), a tile written again merges into its group's shard.
        let g = wide_grid();
        let mut w = ZarrStore::create_or_open_grouped(&root, g, info("a"), None).unwrap();
        let extra = sample(w.grid.tile_voxels(), 9);
        w.write_tile([1, -2], &extra, 99).unwrap();
        w.fit().unwrap();
        let mut more = data.clone();
        more.push(([1, -2], extra));
        let mut last = ZarrStore::open(&root).unwrap();
        assert_grouped_holds(&mut last, &more);
        assert_eq!(last.watermark([1, -2]), Some(99));
    }

    #[test]
    fn a_grouped_store_finishes_committed_batches_and_drops_uncommitted_ones() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("voxels.zarr");
        let (mut s, data) = grouped_store(&root);
        s.flush_all().unwrap();
        // A committed batch whose renames were cut short: its shard back to pending.
        let journal = root.join("fwlidar_state/journal");
        let (batches, _) = Journal::read(&journal).unwrap();
        let last = batches.last().unwrap();
        let shard = root.join(&last.shards[0]);
        let pending = PathBuf::from(format!("{}.pending.{}", shard.display(), last.seq));
        fs::rename(&shard, &pending).unwrap();
        // A batch never committed, and a journal line torn by the crash.
        let stray = PathBuf::from(format!("{}.pending.{}", shard.display(), last.seq + 5));
        fs::write(&stray, b"half a shard").unwrap();
        let good_len = fs::metadata(&journal).unwrap().len();
        let mut f = OpenOptions::new().append(true).open(&journal).unwrap();
        f.write_all(b"{\"seq\": 99, \"sha").unwrap();
        drop(f);
        drop(s);
        let mut again = ZarrStore::open(&root).unwrap();
        assert_eq!(again.recovered_commits, 1);
        assert_eq!(again.discarded_pending, 1);
        assert!(shard.exists() && !pending.exists() && !stray.exists());
        assert_eq!(fs::metadata(&journal).unwrap().len(), good_len);
        assert_grouped_holds(&mut again, &data);
        // A damaged line before the last is refused, naming the journal.
        let mut text = fs::read(&journal).unwrap();
        text[2] ^= 0x20;
        fs::write(&journal, &text).unwrap();
        let e = ZarrStore::open(&root).err().unwrap().to_string();
        assert!(e.contains("journal") && e.contains("line 1"), "{e}");
    }

    #[test]
    fn a_merge_copies_tiles_between_layouts_without_decoding() {
        let dir = tempfile::tempdir().unwrap();
        let (mut plain, data) = {
            let (s, d) = live_store(&dir.path().join("plain.zarr"));
            (s, d)
        };
        plain.fit().unwrap();
        let src = ZarrStore::open(&dir.path().join("plain.zarr")).unwrap();
        let g = wide_grid();
        let root = dir.path().join("grouped.zarr");
        let mut dst = ZarrStore::create_or_open_grouped(&root, g, info(""), Some(GROUP)).unwrap();
        for t in WRITTEN {
            assert!(dst.copy_tile(&src, t, 0).unwrap());
        }
        dst.fit().unwrap();
        let mut back = ZarrStore::open(&root).unwrap();
        let pairs: Vec<([i64; 2], TileData)> = WRITTEN.iter().copied().zip(data).collect();
        assert_grouped_holds(&mut back, &pairs);
        // And back from the grouped store into another grouped one.
        let root2 = dir.path().join("again.zarr");
        let mut dst2 =
            ZarrStore::create_or_open_grouped(&root2, wide_grid(), info(""), Some(GROUP)).unwrap();
        for t in WRITTEN {
            assert!(dst2.copy_tile(&back, t, 0).unwrap());
        }
        dst2.fit().unwrap();
        let shard = |r: &Path| {
            files(r)
                .into_iter()
                .filter(|(k, _)| ARRAYS.iter().any(|a| k.starts_with(&format!("{a}/c/"))))
                .collect::<Vec<_>>()
        };
        assert_eq!(shard(&root), shard(&root2));
    }

    #[test]
    fn a_store_created_on_its_tiles_ends_as_one_created_on_the_extent_and_fitted() {
        let dir = tempfile::tempdir().unwrap();
        let (want, fitted_span, chunks) = {
            let root = dir.path().join("want.zarr");
            let (mut s, _) = live_store(&root);
            let chunks: Vec<([i64; 2], Vec<u32>)> = WRITTEN
                .iter()
                .map(|t| (*t, s.tile_chunks(*t).unwrap().to_vec()))
                .collect();
            s.fit().unwrap();
            (files(&root), *s.span(), chunks)
        };
        let root = dir.path().join("on_tiles.zarr");
        let g = wide_grid();
        let n = g.tile_voxels();
        let on = chunks.iter().map(|(t, c)| (*t, c.as_slice()));
        let mut s = ZarrStore::create_on_tiles(&root, g, info("a"), None, on).unwrap();
        // The arrays take their final span at once; the coordinates are the span's.
        assert!(s.span().same_tiles(&fitted_span), "{:?}", s.span());
        let x = json_of(&root.join("x/zarr.json"));
        assert_eq!(x["shape"], json!([fitted_span.tiles[0] * 8]));
        for (i, t) in WRITTEN.iter().enumerate() {
            s.write_tile(*t, &sample(n, i as u32 + 1), 10 + i as u64)
                .unwrap();
        }
        let e = s.write_tile([3, -3], &sample(n, 9), 20).unwrap_err();
        assert!(e.to_string().contains("outside the arrays"), "{e}");
        s.fit().unwrap();
        drop(s);
        assert_eq!(files(&root), want);
        // Only into an absent or empty folder.
        let again = ZarrStore::create_on_tiles(&root, wide_grid(), info("a"), None, []);
        let e = again.err().expect("a second store in the same folder");
        assert!(e.to_string().contains("not empty"), "{e}");
    }

    fn assert_holds_written(s: &mut ZarrStore, data: &[TileData]) {
        let mut back = TileData::for_grid(s.grid());
        assert_eq!(s.tiles().len(), WRITTEN.len());
        for (t, d) in WRITTEN.iter().zip(data) {
            assert!(s.read_tile(*t, &mut back).unwrap(), "{t:?}");
            assert_eq!(back.dense().sum_q, d.dense().sum_q, "{t:?}");
            assert_eq!(back.dense().samples, d.dense().samples, "{t:?}");
        }
    }

    #[test]
    fn fit_shrinks_the_arrays_to_the_tiles_written_and_reopening_restores_the_extent() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("v.zarr");
        let (mut s, data) = live_store(&root);
        // While writing: the whole extent, 16 × 16 tiles from tile (-8, -8).
        assert_eq!(*s.span(), Span::extent(s.grid()));
        assert_eq!(s.span().tile_min, [-8, -8]);
        assert!(root.join("sample_count/c/0/7/9").is_file(), "tile (1, -1)");
        s.fit().unwrap();
        // The bounding box of (-3, 2), (1, -1), (2, 2): x -3..=2, y -1..=2.
        let span = *s.span();
        assert_eq!(
            span,
            Span {
                tile_min: [-3, -1],
                tiles: [6, 4],
                level_chunk_min: 0,
                level_chunks: 1,
                fitted: true
            }
        );
        assert_holds_written(&mut s, &data);
        // Chunk keys counted from the new corner; nothing left at the old ones.
        for (t, key) in WRITTEN.iter().zip(["3/0", "0/4", "3/5"]) {
            for a in ARRAYS {
                assert!(root.join(a).join("c/0").join(key).is_file(), "{a} {t:?}");
            }
        }
        assert!(!root.join("sample_count/c/0/7").exists());
        assert!(!root.join("fwlidar_state/staging").exists());
        assert!(!root.join("fwlidar_state/relayout").exists());
        // Metadata: shape, coordinates (voxel centres from x = -12 m, y = -4 m), the span, and
        // the consolidated metadata equal to every node's own document.
        let root_meta = json_of(&root.join("zarr.json"));
        assert_eq!(
            root_meta["attributes"]["fwlidar"]["arrays"]["tiles"],
            json!([6, 4])
        );
        assert_eq!(
            root_meta["attributes"]["origin_m"],
            json!([-12.0, -4.0, 0.0])
        );
        assert_eq!(
            root_meta["attributes"]["extent_m"],
            json!([-32.0, -32.0, 32.0, 32.0])
        );
        let cm = &root_meta["consolidated_metadata"];
        assert_eq!(cm["kind"], "inline");
        let nodes = cm["metadata"].as_object().unwrap();
        let mut names: Vec<&str> = nodes.keys().map(String::as_str).collect();
        names.sort_unstable();
        assert_eq!(
            names,
            [
                "fwlidar_state",
                "intensity_max",
                "intensity_sum",
                "pulse_count",
                "sample_count",
                "spatial_ref",
                "x",
                "y",
                "z"
            ]
        );
        for (name, node) in nodes {
            let mut own = json_of(&root.join(name).join("zarr.json"));
            if name == "fwlidar_state" {
                own["consolidated_metadata"] =
                    json!({"kind": "inline", "must_understand": false, "metadata": {}});
            }
            assert_eq!(*node, own, "{name}");
        }
        let levels = s.grid().levels as u64;
        assert_eq!(nodes["sample_count"]["shape"], json!([levels, 32, 48]));
        let xs = f64s(&root.join("x/c/0"));
        let ys = f64s(&root.join("y/c/0"));
        assert_eq!(xs.len(), 48);
        assert_eq!((xs[0], xs[47]), (-11.75, 11.75));
        assert_eq!((ys[0], ys[31]), (-3.75, 11.75));
        let fitted = files(&root);

        // Writing outside the fitted arrays is refused; reopening to write restores the extent.
        let n = s.grid().tile_voxels();
        let e = s.write_tile([-8, -8], &sample(n, 9), 1).unwrap_err();
        assert!(e.to_string().contains("outside the arrays"), "{e}");
        drop(s);
        let mut s = ZarrStore::create_or_open(&root, wide_grid(), info("a")).unwrap();
        assert_eq!(*s.span(), Span::extent(s.grid()));
        assert!(root.join("sample_count/c/0/7/9").is_file());
        assert_holds_written(&mut s, &data);
        assert_eq!(json_of(&root.join("x/zarr.json"))["shape"], json!([128]));
        // Fitting again gives the same files, byte for byte.
        s.fit().unwrap();
        assert_eq!(files(&root), fitted);
        // A read-only open keeps the fitted arrays.
        let mut r = ZarrStore::open(&root).unwrap();
        assert_eq!(r.span(), &span);
        assert_holds_written(&mut r, &data);
    }

    #[test]
    fn a_change_of_span_cut_short_is_finished_on_the_next_open() {
        let dir = tempfile::tempdir().unwrap();
        let want = {
            let root = dir.path().join("want.zarr");
            let (mut s, _) = live_store(&root);
            s.fit().unwrap();
            files(&root)
        };
        let target = Span::around(&wide_grid(), WRITTEN.iter().map(|t| (*t, &[0u32][..])));
        let journal = |s: &ZarrStore| {
            fs::write(s.journal_path(), serde_json::to_vec(&target).unwrap()).unwrap();
        };
        // Cut during the first step: the journal written, one tile's chunks staged, the
        // metadata still on the extent.
        let root = dir.path().join("a.zarr");
        let (s, data) = live_store(&root);
        journal(&s);
        fs::create_dir_all(s.staging_dir()).unwrap();
        for a in ARRAYS {
            let t = WRITTEN[1];
            let to = s.staging_dir().join(format!("{a}.{}_{}_0", t[0], t[1]));
            fs::rename(s.chunk_path(a, t, 0).unwrap(), to).unwrap();
        }
        drop(s);
        let mut s = ZarrStore::open(&root).unwrap();
        assert_eq!(*s.span(), target);
        assert_holds_written(&mut s, &data);
        assert_eq!(files(&root), want);

        // Cut during the last step: the metadata rewritten for the new span, some chunks still
        // in staging.
        let root = dir.path().join("b.zarr");
        let (mut s, data) = live_store(&root);
        journal(&s);
        fs::create_dir_all(s.staging_dir()).unwrap();
        for t in WRITTEN {
            for a in ARRAYS {
                let to = s.staging_dir().join(format!("{a}.{}_{}_0", t[0], t[1]));
                fs::rename(s.chunk_path(a, t, 0).unwrap(), to).unwrap();
            }
        }
        for a in ARRAYS {
            fs::remove_dir_all(root.join(a).join("c")).unwrap();
        }
        s.span = target;
        s.write_metadata().unwrap();
        let t = WRITTEN[2];
        let to = s.chunk_path("pulse_count", t, 0).unwrap();
        fs::create_dir_all(to.parent().unwrap()).unwrap();
        fs::rename(
            s.staging_dir()
                .join(format!("pulse_count.{}_{}_0", t[0], t[1])),
            to,
        )
        .unwrap();
        drop(s);
        let mut s = ZarrStore::open(&root).unwrap();
        assert_holds_written(&mut s, &data);
        assert_eq!(files(&root), want);
    }

    #[test]
    fn a_store_without_tiles_fits_to_empty_arrays() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("v.zarr");
        let mut s = ZarrStore::create_or_open(&root, wide_grid(), info("a")).unwrap();
        s.fit().unwrap();
        assert_eq!(s.span().tiles, [0, 0]);
        let meta = json_of(&root.join("zarr.json"));
        let nodes = &meta["consolidated_metadata"]["metadata"];
        assert_eq!(nodes["sample_count"]["shape"], json!([0, 0, 0]));
        assert_eq!(nodes["x"]["shape"], json!([0]));
        assert!(
            !root.join("x/c/0").exists(),
            "no chunk for an empty coordinate"
        );
        assert!(!root.join("z/c/0").exists());
        let r = ZarrStore::open(&root).unwrap();
        assert!(r.tiles().is_empty());
    }
}
