//! Cloud-Optimized GeoTIFF writer ([`write_cog`]), written against TIFF 6.0 (tiles, DEFLATE,
//! predictors; TIFF Technical Note 3 for the floating-point predictor), BigTIFF, GeoTIFF 1.1
//! and the COG layout that GDAL's COG driver writes and `rio cogeo validate` checks:
//!
//! ```text
//!  header (8 bytes; BigTIFF 16) ─ GDAL ghost header (optional, ~190 bytes)
//!  IFD 0   full resolution  (+ its out-of-line values: tile offsets, GeoKeys, metadata …)
//!  IFD 1   overview 2×      (NewSubfileType = 1, reduced resolution)
//!  …       overview 2^k×    (the first level that fits in one tile)
//!  tile data: the smallest overview first, … , the full resolution last; tiles row-major,
//!            each as [u32 size][DEFLATE bytes][its last 4 bytes again] when the ghost header
//!            announces BLOCK_LEADER / BLOCK_TRAILER
//! ```
//!
//! Samples are Float32, pixel-interleaved (`PlanarConfiguration` 1) when there are several
//! bands; edge tiles are padded to full tiles with the nodata value. Overviews halve each side
//! (rounding up) by averaging the up-to-4 valid cells beneath (nodata and NaN ignored; a cell
//! with none valid is nodata), each level from the previous one, until the level fits in one
//! tile. Everything is encoded in memory first (tile sizes fix the offsets the IFDs state),
//! then written in one pass to `NAME.partial` and renamed.

use std::io::Write;
use std::path::Path;

use super::{Raster, RasterError, is_geographic_epsg, is_nodata, nodata_text, xml_escape};

/// The TIFF predictor applied before DEFLATE.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Predictor {
    /// No predictor (TIFF `Predictor` 1).
    None,
    /// The floating-point predictor (TIFF `Predictor` 3, Technical Note 3): each tile row's
    /// bytes are reordered most-significant byte plane first, then differenced byte by byte
    /// (stride = samples per pixel). Smooth fields compress markedly better.
    FloatingPoint,
}

/// How [`write_cog`] encodes the file.
#[derive(Clone, Debug)]
pub struct CogOptions {
    /// Tile side in cells (a multiple of 16, 16–4096; COGs use 256 or 512).
    pub tile_size: usize,
    /// DEFLATE level, 0 (store) to 9 (smallest); 6 is zlib's default.
    pub deflate_level: u32,
    /// The predictor.
    pub predictor: Predictor,
    /// Whether to write reduced-resolution overviews (COGs larger than a tile should have them).
    pub overviews: bool,
    /// Whether to write GDAL's "ghost" structural metadata after the TIFF header (and with it
    /// the 4-byte size before and the repeated last 4 bytes after each tile it announces).
    pub ghost_header: bool,
    /// Write BigTIFF even when a classic TIFF would do (it is chosen anyway past 4 GiB).
    pub force_bigtiff: bool,
    /// Threads compressing tiles (1 = the calling thread only).
    pub threads: usize,
}

impl Default for CogOptions {
    fn default() -> Self {
        CogOptions {
            tile_size: 256,
            deflate_level: 6,
            predictor: Predictor::FloatingPoint,
            overviews: true,
            ghost_header: true,
            force_bigtiff: false,
            threads: 1,
        }
    }
}

/// TIFF tags written here.
mod tag {
    pub const NEW_SUBFILE_TYPE: u16 = 254;
    pub const IMAGE_WIDTH: u16 = 256;
    pub const IMAGE_LENGTH: u16 = 257;
    pub const BITS_PER_SAMPLE: u16 = 258;
    pub const COMPRESSION: u16 = 259;
    pub const PHOTOMETRIC: u16 = 262;
    pub const SAMPLES_PER_PIXEL: u16 = 277;
    pub const PLANAR_CONFIGURATION: u16 = 284;
    pub const PREDICTOR: u16 = 317;
    pub const TILE_WIDTH: u16 = 322;
    pub const TILE_LENGTH: u16 = 323;
    pub const TILE_OFFSETS: u16 = 324;
    pub const TILE_BYTE_COUNTS: u16 = 325;
    pub const EXTRA_SAMPLES: u16 = 338;
    pub const SAMPLE_FORMAT: u16 = 339;
    pub const MODEL_PIXEL_SCALE: u16 = 33550;
    pub const MODEL_TIEPOINT: u16 = 33922;
    pub const GEO_KEY_DIRECTORY: u16 = 34735;
    pub const GDAL_METADATA: u16 = 42112;
    pub const GDAL_NODATA: u16 = 42113;
}

/// A TIFF field value.
enum Val {
    Short(Vec<u16>),
    Long(Vec<u32>),
    Long8(Vec<u64>),
    Double(Vec<f64>),
    /// Written NUL-terminated.
    Ascii(String),
}

impl Val {
    fn type_code(&self) -> u16 {
        match self {
            Val::Ascii(_) => 2,
            Val::Short(_) => 3,
            Val::Long(_) => 4,
            Val::Double(_) => 12,
            Val::Long8(_) => 16,
        }
    }

    fn count(&self) -> u64 {
        match self {
            Val::Short(v) => v.len() as u64,
            Val::Long(v) => v.len() as u64,
            Val::Long8(v) => v.len() as u64,
            Val::Double(v) => v.len() as u64,
            Val::Ascii(s) => s.len() as u64 + 1,
        }
    }

    fn byte_len(&self) -> u64 {
        match self {
            Val::Short(v) => 2 * v.len() as u64,
            Val::Long(v) => 4 * v.len() as u64,
            Val::Long8(v) => 8 * v.len() as u64,
            Val::Double(v) => 8 * v.len() as u64,
            Val::Ascii(s) => s.len() as u64 + 1,
        }
    }

    fn bytes(&self, out: &mut Vec<u8>) {
        match self {
            Val::Short(v) => v
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Val::Long(v) => v
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Val::Long8(v) => v
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Val::Double(v) => v
                .iter()
                .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            Val::Ascii(s) => {
                out.extend_from_slice(s.as_bytes());
                out.push(0);
            }
        }
    }
}

/// Classic TIFF or BigTIFF field sizes.
#[derive(Clone, Copy)]
struct Kind {
    big: bool,
}

impl Kind {
    fn header_len(self) -> u64 {
        if self.big { 16 } else { 8 }
    }
    /// Bytes a value may take inside its entry.
    fn inline(self) -> u64 {
        if self.big { 8 } else { 4 }
    }
    fn entry_len(self) -> u64 {
        if self.big { 20 } else { 12 }
    }
    /// Entry count field + next-IFD pointer.
    fn ifd_fixed(self) -> u64 {
        if self.big { 16 } else { 6 }
    }
}

/// Bytes an IFD takes with its out-of-line values (each value starts on an even offset).
fn ifd_len(entries: &[(u16, Val)], kind: Kind) -> u64 {
    let mut n = kind.ifd_fixed() + kind.entry_len() * entries.len() as u64;
    for (_, v) in entries {
        let b = v.byte_len();
        if b > kind.inline() {
            n += b + (b & 1);
        }
    }
    n
}

/// Serialises an IFD (entries sorted by tag) to be placed at `at`, pointing to `next` (0 for
/// the last).
fn ifd_bytes(entries: &[(u16, Val)], kind: Kind, at: u64, next: u64, out: &mut Vec<u8>) {
    let start = out.len();
    let mut extra = Vec::new();
    let mut extra_at = at + kind.ifd_fixed() + kind.entry_len() * entries.len() as u64;
    if kind.big {
        out.extend_from_slice(&(entries.len() as u64).to_le_bytes());
    } else {
        out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    }
    for (t, v) in entries {
        out.extend_from_slice(&t.to_le_bytes());
        out.extend_from_slice(&v.type_code().to_le_bytes());
        if kind.big {
            out.extend_from_slice(&v.count().to_le_bytes());
        } else {
            out.extend_from_slice(&(v.count() as u32).to_le_bytes());
        }
        let b = v.byte_len();
        if b <= kind.inline() {
            let mut field = Vec::with_capacity(8);
            v.bytes(&mut field);
            field.resize(kind.inline() as usize, 0);
            out.extend_from_slice(&field);
        } else {
            if kind.big {
                out.extend_from_slice(&extra_at.to_le_bytes());
            } else {
                out.extend_from_slice(&(extra_at as u32).to_le_bytes());
            }
            v.bytes(&mut extra);
            if b & 1 == 1 {
                extra.push(0);
            }
            extra_at += b + (b & 1);
        }
    }
    if kind.big {
        out.extend_from_slice(&next.to_le_bytes());
    } else {
        out.extend_from_slice(&(next as u32).to_le_bytes());
    }
    out.extend_from_slice(&extra);
    debug_assert_eq!((out.len() - start) as u64, ifd_len(entries, kind));
}

/// One resolution level: its size and its bands (row-major).
struct Level<'a> {
    width: usize,
    height: usize,
    bands: Vec<std::borrow::Cow<'a, [f32]>>,
}

impl Level<'_> {
    fn tiles_across(&self, ts: usize) -> usize {
        self.width.div_ceil(ts)
    }
    fn tiles_down(&self, ts: usize) -> usize {
        self.height.div_ceil(ts)
    }
}

/// The next coarser level: each side halved (rounding up), each cell the mean of the valid
/// cells among the up-to-4 beneath it, nodata where none is valid.
fn downsample(level: &Level<'_>, nodata: f32) -> Level<'static> {
    let (w, h) = (level.width.div_ceil(2), level.height.div_ceil(2));
    let bands = level
        .bands
        .iter()
        .map(|src| {
            let mut out = vec![nodata; w * h];
            for r in 0..h {
                let r0 = 2 * r;
                let r1 = (r0 + 1).min(level.height - 1);
                for c in 0..w {
                    let c0 = 2 * c;
                    let c1 = (c0 + 1).min(level.width - 1);
                    let mut sum = 0.0f64;
                    let mut n = 0u32;
                    // Distinct cells only: at an odd edge r1 == r0 or c1 == c0.
                    let rows: &[usize] = if r1 != r0 { &[r0, r1] } else { &[r0] };
                    let cols: &[usize] = if c1 != c0 { &[c0, c1] } else { &[c0] };
                    for &rr in rows {
                        for &cc in cols {
                            let v = src[rr * level.width + cc];
                            if !is_nodata(v, nodata) {
                                sum += f64::from(v);
                                n += 1;
                            }
                        }
                    }
                    if n > 0 {
                        out[r * w + c] = (sum / f64::from(n)) as f32;
                    }
                }
            }
            std::borrow::Cow::Owned(out)
        })
        .collect();
    Level {
        width: w,
        height: h,
        bands,
    }
}

/// The raw bytes of tile (tx, ty) of `level` (pixel-interleaved Float32, padded with nodata),
/// with the predictor applied, into `buf`.
fn tile_raw(
    level: &Level<'_>,
    ts: usize,
    tx: usize,
    ty: usize,
    nodata: f32,
    predictor: Predictor,
    buf: &mut Vec<u8>,
) {
    let spp = level.bands.len();
    let row_values = ts * spp;
    let row_bytes = row_values * 4;
    buf.clear();
    buf.resize(row_bytes * ts, 0);
    let mut row = vec![0f32; row_values];
    for r in 0..ts {
        let y = ty * ts + r;
        for c in 0..ts {
            let x = tx * ts + c;
            let inside = x < level.width && y < level.height;
            for (b, band) in level.bands.iter().enumerate() {
                row[c * spp + b] = if inside {
                    band[y * level.width + x]
                } else {
                    nodata
                };
            }
        }
        let out = &mut buf[r * row_bytes..(r + 1) * row_bytes];
        match predictor {
            Predictor::None => {
                for (i, v) in row.iter().enumerate() {
                    out[4 * i..4 * i + 4].copy_from_slice(&v.to_le_bytes());
                }
            }
            Predictor::FloatingPoint => {
                // Byte planes, most significant first (TIFF TN3, as libtiff's fpDiff) …
                for (i, v) in row.iter().enumerate() {
                    let b = v.to_be_bytes();
                    out[i] = b[0];
                    out[row_values + i] = b[1];
                    out[2 * row_values + i] = b[2];
                    out[3 * row_values + i] = b[3];
                }
                // … then each byte minus the byte `spp` before it, across the whole row.
                for i in (spp..row_bytes).rev() {
                    out[i] = out[i].wrapping_sub(out[i - spp]);
                }
            }
        }
    }
}

/// DEFLATE (zlib stream, TIFF Compression 8) of every tile of `level`, row-major.
fn encode_level(level: &Level<'_>, ts: usize, nodata: f32, opt: &CogOptions) -> Vec<Vec<u8>> {
    let (across, down) = (level.tiles_across(ts), level.tiles_down(ts));
    let n = across * down;
    let encode = |i: usize, raw: &mut Vec<u8>| -> Vec<u8> {
        tile_raw(
            level,
            ts,
            i % across,
            i / across,
            nodata,
            opt.predictor,
            raw,
        );
        let mut z = flate2::write::ZlibEncoder::new(
            Vec::with_capacity(raw.len() / 2),
            flate2::Compression::new(opt.deflate_level.min(9)),
        );
        // Writing into a Vec cannot fail.
        z.write_all(raw).expect("deflate into memory");
        z.finish().expect("deflate into memory")
    };
    let threads = opt.threads.clamp(1, 64).min(n.max(1));
    if threads == 1 {
        let mut raw = Vec::new();
        return (0..n).map(|i| encode(i, &mut raw)).collect();
    }
    let mut out: Vec<Vec<u8>> = vec![Vec::new(); n];
    let chunk = n.div_ceil(threads);
    std::thread::scope(|s| {
        for (k, part) in out.chunks_mut(chunk).enumerate() {
            let encode = &encode;
            s.spawn(move || {
                let mut raw = Vec::new();
                for (j, slot) in part.iter_mut().enumerate() {
                    *slot = encode(k * chunk + j, &mut raw);
                }
            });
        }
    });
    out
}

/// The GDAL ghost header: structural metadata placed between the TIFF header and the first IFD
/// (the same keys GDAL's COG driver writes; the size counts the bytes after its first line).
fn ghost_header() -> Vec<u8> {
    let body = "LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\n\
                BLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ";
    format!(
        "GDAL_STRUCTURAL_METADATA_SIZE={:06} bytes\n{body}",
        body.len()
    )
    .into_bytes()
}

/// `GDAL_METADATA` XML naming each band (role `description`) and its unit (role `unittype`),
/// or `None` when there is nothing to say.
fn gdal_metadata(r: &Raster) -> Option<String> {
    let mut items = String::new();
    for (i, name) in r.band_names.iter().enumerate() {
        if !name.is_empty() {
            items.push_str(&format!(
                "  <Item name=\"DESCRIPTION\" sample=\"{i}\" role=\"description\">{}</Item>\n",
                xml_escape(name)
            ));
        }
    }
    for (i, unit) in r.band_units.iter().enumerate() {
        if !unit.is_empty() {
            items.push_str(&format!(
                "  <Item name=\"UNITTYPE\" sample=\"{i}\" role=\"unittype\">{}</Item>\n",
                xml_escape(unit)
            ));
        }
    }
    (!items.is_empty()).then(|| format!("<GDALMetadata>\n{items}</GDALMetadata>"))
}

/// The tags of one level's IFD with the given tile offsets and byte counts.
fn level_entries(
    r: &Raster,
    level: &Level<'_>,
    overview: bool,
    opt: &CogOptions,
    kind: Kind,
    offsets: Vec<u64>,
    counts: Vec<u64>,
) -> Vec<(u16, Val)> {
    let spp = r.bands.len();
    let short = |v: usize| Val::Short(vec![v as u16]);
    let mut e = vec![
        (
            tag::NEW_SUBFILE_TYPE,
            Val::Long(vec![if overview { 1 } else { 0 }]),
        ),
        (tag::IMAGE_WIDTH, Val::Long(vec![level.width as u32])),
        (tag::IMAGE_LENGTH, Val::Long(vec![level.height as u32])),
        (tag::BITS_PER_SAMPLE, Val::Short(vec![32; spp])),
        (tag::COMPRESSION, short(8)),
        (tag::PHOTOMETRIC, short(1)),
        (tag::SAMPLES_PER_PIXEL, short(spp)),
        (tag::PLANAR_CONFIGURATION, short(1)),
        (
            tag::PREDICTOR,
            short(match opt.predictor {
                Predictor::None => 1,
                Predictor::FloatingPoint => 3,
            }),
        ),
        (tag::TILE_WIDTH, short(opt.tile_size)),
        (tag::TILE_LENGTH, short(opt.tile_size)),
        (tag::SAMPLE_FORMAT, Val::Short(vec![3; spp])),
        (tag::GDAL_NODATA, Val::Ascii(nodata_text(r.nodata))),
    ];
    if kind.big {
        e.push((tag::TILE_OFFSETS, Val::Long8(offsets)));
        e.push((tag::TILE_BYTE_COUNTS, Val::Long8(counts)));
    } else {
        e.push((
            tag::TILE_OFFSETS,
            Val::Long(offsets.iter().map(|&o| o as u32).collect()),
        ));
        e.push((
            tag::TILE_BYTE_COUNTS,
            Val::Long(counts.iter().map(|&o| o as u32).collect()),
        ));
    }
    if spp > 1 {
        // Further samples are "unspecified data" (bands), not alpha.
        e.push((tag::EXTRA_SAMPLES, Val::Short(vec![0; spp - 1])));
    }
    if !overview {
        e.push((
            tag::MODEL_PIXEL_SCALE,
            Val::Double(vec![r.cell_size, r.cell_size, 0.0]),
        ));
        e.push((
            tag::MODEL_TIEPOINT,
            Val::Double(vec![0.0, 0.0, 0.0, r.origin_x, r.origin_y, 0.0]),
        ));
        let (model, key) = if is_geographic_epsg(r.epsg) {
            (2, 2048) // ModelTypeGeographic, GeographicTypeGeoKey
        } else {
            (1, 3072) // ModelTypeProjected, ProjectedCSTypeGeoKey
        };
        let keys = vec![
            1,
            1,
            0,
            3, // directory version 1, revision 1.0, 3 keys
            1024,
            0,
            1,
            model, // GTModelTypeGeoKey
            1025,
            0,
            1,
            1, // GTRasterTypeGeoKey = RasterPixelIsArea
            key,
            0,
            1,
            r.epsg as u16,
        ];
        e.push((tag::GEO_KEY_DIRECTORY, Val::Short(keys)));
        if let Some(xml) = gdal_metadata(r) {
            e.push((tag::GDAL_METADATA, Val::Ascii(xml)));
        }
    }
    e.sort_by_key(|(t, _)| *t);
    e
}

/// Writes `raster` to `path` as a Cloud-Optimized GeoTIFF (tiled, DEFLATE, overviews, CRS,
/// nodata, band names), atomically: the file appears complete or not at all.
///
/// Errors: [`RasterError::Invalid`] for a raster that cannot be written (empty, band sizes
/// that do not match, sides over [`super::MAX_DIMENSION`], an EPSG code GeoTIFF cannot state, a
/// tile size that is not a multiple of 16), [`RasterError::Io`] when the file cannot be
/// written (nothing is left behind).
pub fn write_cog(path: &Path, raster: &Raster, opt: &CogOptions) -> Result<(), RasterError> {
    raster.validate(path)?;
    let ts = opt.tile_size;
    if !(16..=4096).contains(&ts) || !ts.is_multiple_of(16) {
        return Err(RasterError::invalid(
            path,
            format!("tile_size {ts}: TIFF tiles must be a multiple of 16, 16–4096"),
        ));
    }
    // Levels: the full resolution, then halvings until one tile holds the level.
    let mut levels = vec![Level {
        width: raster.width,
        height: raster.height,
        bands: raster
            .bands
            .iter()
            .map(|b| std::borrow::Cow::Borrowed(b.as_slice()))
            .collect(),
    }];
    while opt.overviews && {
        let l = levels.last().expect("one level");
        l.width > ts || l.height > ts
    } {
        let next = downsample(levels.last().expect("one level"), raster.nodata);
        levels.push(next);
    }
    let tiles: Vec<Vec<Vec<u8>>> = levels
        .iter()
        .map(|l| encode_level(l, ts, raster.nodata, opt))
        .collect();
    let framed = opt.ghost_header; // leader + trailer around each tile
    let frame = if framed { 8u64 } else { 0 };
    let ghost = if opt.ghost_header {
        ghost_header()
    } else {
        Vec::new()
    };
    let data_len: u64 = tiles.iter().flatten().map(|t| t.len() as u64 + frame).sum();

    let plan = |kind: Kind| -> (Vec<u64>, u64) {
        // IFD positions; the data starts after the last IFD.
        let mut at = kind.header_len() + ghost.len() as u64;
        at += at & 1;
        let mut pos = Vec::new();
        for (i, l) in levels.iter().enumerate() {
            let n = tiles[i].len();
            let e = level_entries(raster, l, i > 0, opt, kind, vec![0; n], vec![0; n]);
            pos.push(at);
            at += ifd_len(&e, kind);
        }
        (pos, at)
    };
    let mut kind = Kind {
        big: opt.force_bigtiff,
    };
    let (mut ifd_pos, mut data_start) = plan(kind);
    if !kind.big && data_start + data_len > u64::from(u32::MAX) {
        kind = Kind { big: true };
        (ifd_pos, data_start) = plan(kind);
    }

    // Tile offsets: the smallest overview's data first, the full resolution last.
    let mut offsets: Vec<Vec<u64>> = vec![Vec::new(); levels.len()];
    let mut at = data_start;
    for i in (0..levels.len()).rev() {
        for t in &tiles[i] {
            offsets[i].push(at + frame / 2);
            at += t.len() as u64 + frame;
        }
    }

    let mut head = Vec::with_capacity(data_start as usize);
    if kind.big {
        head.extend_from_slice(b"II\x2b\x00\x08\x00\x00\x00");
        head.extend_from_slice(&ifd_pos[0].to_le_bytes());
    } else {
        head.extend_from_slice(b"II\x2a\x00");
        head.extend_from_slice(&(ifd_pos[0] as u32).to_le_bytes());
    }
    head.extend_from_slice(&ghost);
    head.resize(ifd_pos[0] as usize, 0);
    for (i, l) in levels.iter().enumerate() {
        let counts = tiles[i].iter().map(|t| t.len() as u64).collect();
        let e = level_entries(raster, l, i > 0, opt, kind, offsets[i].clone(), counts);
        let next = ifd_pos.get(i + 1).copied().unwrap_or(0);
        ifd_bytes(&e, kind, ifd_pos[i], next, &mut head);
    }
    debug_assert_eq!(head.len() as u64, data_start);

    super::write_atomic(path, |w| {
        w.write_all(&head)?;
        for level_tiles in tiles.iter().rev() {
            for t in level_tiles {
                if framed {
                    w.write_all(&(t.len() as u32).to_le_bytes())?;
                }
                w.write_all(t)?;
                if framed {
                    w.write_all(&t[t.len() - 4..])?;
                }
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::MAX_DIMENSION;
    use tiff::decoder::{Decoder, DecodingResult};

    /// One IFD as parsed back: (tag → (type, count, values as u64 for integer types)).
    struct Parsed {
        at: u64,
        end: u64,
        tags: std::collections::BTreeMap<u16, Vec<u64>>,
    }

    /// A minimal TIFF/BigTIFF IFD walker over our own output (little-endian only).
    fn parse(bytes: &[u8]) -> (bool, Vec<Parsed>) {
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]) as u64;
        let u32_at = |o: usize| u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap()) as u64;
        let u64_at = |o: usize| u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap());
        assert_eq!(&bytes[..2], b"II");
        let big = u16_at(2) == 43;
        let mut next = if big { u64_at(8) } else { u32_at(4) };
        let mut out = Vec::new();
        while next != 0 {
            let at = next as usize;
            let (n, mut p) = if big {
                (u64_at(at), at + 8)
            } else {
                (u16_at(at), at + 2)
            };
            let mut tags = std::collections::BTreeMap::new();
            let mut end = 0u64;
            for _ in 0..n {
                let (tag, ty) = (u16_at(p) as u16, u16_at(p + 2));
                let (count, field) = if big {
                    (u64_at(p + 4), p + 12)
                } else {
                    (u32_at(p + 4), p + 8)
                };
                let size = match ty {
                    2 => 1,
                    3 => 2,
                    4 => 4,
                    12 | 16 => 8,
                    t => panic!("type {t}"),
                };
                let len = size * count;
                let inline = if big { 8 } else { 4 };
                let data = if len <= inline {
                    field
                } else {
                    let o = if big { u64_at(field) } else { u32_at(field) };
                    end = end.max(o + len);
                    o as usize
                };
                let vals = (0..count as usize)
                    .map(|i| match ty {
                        3 => u16_at(data + 2 * i),
                        4 => u32_at(data + 4 * i),
                        16 => u64_at(data + 8 * i),
                        _ => 0,
                    })
                    .collect();
                tags.insert(tag, vals);
                p += if big { 20 } else { 12 };
            }
            next = if big { u64_at(p) } else { u32_at(p) };
            let ifd_end = (p + if big { 8 } else { 4 }) as u64;
            out.push(Parsed {
                at: at as u64,
                end: end.max(ifd_end),
                tags,
            });
        }
        (big, out)
    }

    fn pattern(w: usize, h: usize) -> Raster {
        let mut r = Raster::new(w, h, 500_000.0, 4_200_000.0, 1.0, 32618, -9999.0);
        let v: Vec<f32> = (0..w * h)
            .map(|i| {
                let (c, r) = (i % w, i / w);
                if (c / 7 + r / 5) % 11 == 0 {
                    -9999.0
                } else {
                    (c as f32) * 0.25 + (r as f32) * 1.5 - 3.0
                }
            })
            .collect();
        r.push_band("canopy_height", "m", v);
        r
    }

    fn read_all(path: &Path) -> Vec<(u32, u32, Vec<f32>)> {
        let mut d = Decoder::new(std::fs::File::open(path).unwrap()).unwrap();
        let mut out = Vec::new();
        loop {
            let (w, h) = d.dimensions().unwrap();
            match d.read_image().unwrap() {
                DecodingResult::F32(v) => out.push((w, h, v)),
                _ => panic!("not f32"),
            }
            if !d.more_images() {
                break;
            }
            d.next_image().unwrap();
        }
        out
    }

    #[test]
    fn layout_ifds_first_then_data_smallest_overview_first() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.tif");
        let r = pattern(700, 500);
        write_cog(&p, &r, &CogOptions::default()).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        let (big, ifds) = parse(&bytes);
        assert!(!big);
        // 700×500 → 350×250 → 175×125 (fits a 256 tile): 3 IFDs.
        assert_eq!(ifds.len(), 3);
        let ghost = String::from_utf8_lossy(&bytes[8..ifds[0].at as usize]).into_owned();
        assert!(ghost.starts_with("GDAL_STRUCTURAL_METADATA_SIZE="));
        assert!(ghost.contains("LAYOUT=IFDS_BEFORE_DATA"));
        assert!(ifds[0].at < 300, "main IFD at {}", ifds[0].at);
        let ifds_end = ifds.iter().map(|i| i.end).max().unwrap();
        let sizes = [(700, 500), (350, 250), (175, 125)];
        let mut first_data = Vec::new();
        for (i, ifd) in ifds.iter().enumerate() {
            assert!(i == 0 || ifd.at > ifds[i - 1].at);
            assert_eq!(ifd.tags[&254], [u64::from(i > 0)]);
            assert_eq!(ifd.tags[&256], [sizes[i].0]);
            assert_eq!(ifd.tags[&257], [sizes[i].1]);
            assert_eq!(ifd.tags[&322], [256]);
            assert_eq!(ifd.tags[&317], [3]);
            let (off, cnt) = (&ifd.tags[&324], &ifd.tags[&325]);
            let n = sizes[i].0.div_ceil(256) * sizes[i].1.div_ceil(256);
            assert_eq!(off.len() as u64, n);
            for (&o, &c) in off.iter().zip(cnt) {
                assert!(o >= ifds_end + 4 && o + c + 4 <= bytes.len() as u64);
                let (o, c) = (o as usize, c as usize);
                // Leader = size, trailer = the last 4 bytes again.
                assert_eq!(
                    u32::from_le_bytes(bytes[o - 4..o].try_into().unwrap()) as usize,
                    c
                );
                assert_eq!(bytes[o + c - 4..o + c], bytes[o + c..o + c + 4]);
            }
            // Row-major tiles.
            assert!(off.windows(2).all(|w| w[0] < w[1]));
            first_data.push(off[0]);
        }
        // Smallest overview's data first, the full resolution last.
        assert!(first_data[2] < first_data[1] && first_data[1] < first_data[0]);
        assert!(ifds[0].tags.contains_key(&34735) && !ifds[1].tags.contains_key(&34735));
        assert_eq!(
            ifds[0].tags[&34735],
            [1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32618]
        );
        // Values back through the `tiff` crate's decoder (tiles, DEFLATE, predictor 3).
        let levels = read_all(&p);
        assert_eq!(levels.len(), 3);
        assert_eq!(levels[0].2, r.bands[0]);
    }

    #[test]
    fn every_predictor_band_count_and_bigtiff_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        for (predictor, bands, big) in [
            (Predictor::None, 1, false),
            (Predictor::FloatingPoint, 3, false),
            (Predictor::FloatingPoint, 2, true),
        ] {
            let mut r = pattern(70, 45);
            for b in 1..bands {
                let v = r.bands[0].iter().map(|x| x * b as f32 + 0.5).collect();
                r.push_band(&format!("b{b}"), "", v);
            }
            let p = dir.path().join("m.tif");
            let opt = CogOptions {
                tile_size: 32,
                predictor,
                force_bigtiff: big,
                threads: 2,
                ..CogOptions::default()
            };
            write_cog(&p, &r, &opt).unwrap();
            let (is_big, ifds) = parse(&std::fs::read(&p).unwrap());
            assert_eq!(is_big, big);
            assert_eq!(ifds.len(), 3); // 70×45 → 35×23 → 18×12
            let levels = read_all(&p);
            let back = &levels[0].2;
            for (i, band) in r.bands.iter().enumerate() {
                let got: Vec<f32> = back.iter().skip(i).step_by(bands).copied().collect();
                assert_eq!(&got, band, "{predictor:?} band {i}");
            }
        }
    }

    #[test]
    fn overviews_average_valid_cells_and_keep_nodata() {
        let nd = -1.0;
        let mut r = Raster::new(5, 3, 0.0, 3.0, 1.0, 4326, nd);
        #[rustfmt::skip]
        let v = vec![
            1.0, 3.0,  nd,  nd, 7.0,
            5.0,  nd,  nd,  nd, f32::NAN,
            2.0, 4.0, 8.0,  nd, 9.0,
        ];
        r.push_band("x", "", v);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("o.tif");
        let opt = CogOptions {
            tile_size: 16,
            ..CogOptions::default()
        };
        // Fits one tile: no overview.
        write_cog(&p, &r, &opt).unwrap();
        assert_eq!(read_all(&p).len(), 1);
        let lvl = downsample(
            &Level {
                width: 5,
                height: 3,
                bands: vec![std::borrow::Cow::Borrowed(&r.bands[0])],
            },
            nd,
        );
        assert_eq!((lvl.width, lvl.height), (3, 2));
        // (1+3+5)/3, all nodata, 7 (NaN ignored); (2+4)/2, 8, 9.
        assert_eq!(&*lvl.bands[0], &[3.0, nd, 7.0, 3.0, 8.0, 9.0]);
        // And through the file: a raster bigger than a tile gets the same overview.
        let mut big = Raster::new(40, 20, 0.0, 20.0, 1.0, 4326, nd);
        let mut v = vec![nd; 800];
        v[0] = 2.0;
        v[41] = 4.0; // (1, 1): same 2×2 block as (0, 0)
        v[2] = 6.0;
        big.push_band("x", "", v);
        write_cog(&p, &big, &opt).unwrap();
        let levels = read_all(&p);
        assert_eq!(levels.len(), 3); // 40×20 → 20×10 → 10×5
        assert_eq!((levels[1].0, levels[1].1), (20, 10));
        assert_eq!(&levels[1].2[..3], &[3.0, 6.0, nd]);
        // Each level from the previous one: (3 + 6) / 2.
        assert_eq!(levels[2].2[0], 4.5);
        assert!(levels[1].2[3..].iter().all(|&x| x == nd));
        let (_, ifds) = parse(&std::fs::read(&p).unwrap());
        assert_eq!(
            ifds[0].tags[&34735],
            [1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326]
        );
    }

    #[test]
    fn unwritable_path_errors_naming_it_and_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        // The final name is an existing directory: the rename fails after the data is written.
        let target = dir.path().join("taken");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("keep"), b"x").unwrap();
        let e = write_cog(&target, &pattern(20, 20), &CogOptions::default()).unwrap_err();
        assert!(matches!(e, RasterError::Io { .. }));
        assert!(e.to_string().contains("taken"), "{e}");
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 1, "only the directory remains");
        // A missing folder.
        let p = dir.path().join("no/such/dir/a.tif");
        let e = write_cog(&p, &pattern(20, 20), &CogOptions::default()).unwrap_err();
        assert!(e.to_string().contains("no/such/dir/a.tif"), "{e}");
    }

    #[test]
    fn bad_rasters_are_refused_clearly() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.tif");
        let huge = Raster::new(MAX_DIMENSION + 1, 1, 0.0, 0.0, 1.0, 32618, 0.0);
        let e = write_cog(&p, &huge, &CogOptions::default()).unwrap_err();
        assert!(e.to_string().contains("too large"), "{e}");
        assert!(e.to_string().contains("h.tif"), "{e}");
        let mut short = Raster::new(10, 10, 0.0, 0.0, 1.0, 32618, 0.0);
        short.push_band("a", "", vec![0.0; 99]);
        let e = write_cog(&p, &short, &CogOptions::default()).unwrap_err();
        assert!(e.to_string().contains("99 values"), "{e}");
        let mut bad_epsg = pattern(10, 10);
        bad_epsg.epsg = 102_100;
        assert!(write_cog(&p, &bad_epsg, &CogOptions::default()).is_err());
        let opt = CogOptions {
            tile_size: 100,
            ..CogOptions::default()
        };
        assert!(write_cog(&p, &pattern(10, 10), &opt).is_err());
        assert!(!p.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
