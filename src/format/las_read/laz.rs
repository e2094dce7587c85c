//! LAZ (LASzip-compressed) point records: decompressed, chunk by chunk, into the same bytes a
//! plain LAS file holds, so that [`super::LasReader`] decodes every point through one code path.
//!
//! The arithmetic decoding is the `laz` crate's (a pure-Rust port of LASzip); this module
//! checks what the crate trusts before handing it anything:
//!
//! - the LASzip VLR: compressor 2 (point-wise chunked: items version 1 or 2, point formats 4
//!   and 5) or 3 (layered chunked: items version 3 or 4, formats 9 and 10), arithmetic coder,
//!   and items that are exactly the point format's fields (plus extra bytes) with the record
//!   length of the header;
//! - the chunk table: its offset, its header and its entry count against the file (each chunk
//!   starts with one uncompressed point, so a count the compressed bytes cannot hold is refused
//!   before the crate allocates a table for it), then every chunk's byte range against the
//!   start of the table and the points of all chunks against the header's count;
//! - each layered chunk's layer sizes against the chunk's bytes, before the crate allocates a
//!   buffer for each layer.
//!
//! The crate is then given a window onto one chunk's bytes at a time ([`Window`]): it cannot
//! read past the chunk, and a damaged chunk ends in an error naming the chunk and the point.
//! Memory: a 64 KiB read buffer, the crate's per-field models (made again at each chunk start,
//! as LASzip does) and, for layered chunks, the crate's copy of the chunk's layers (LASzip's
//! default chunk is 50 000 points, about 1–2 MB). Nothing is allocated per point.
//!
//! **Panics in the crate.** The arithmetic decoder indexes its tables with values decoded from
//! the file; damaged data can make it index out of bounds (or, in builds with overflow checks,
//! overflow), which panics. No check made in advance can rule that out short of decoding, so
//! every call into the crate runs under [`std::panic::catch_unwind`] (the last resort), and a
//! panic becomes an error naming the file, the chunk and the point. While such a call runs, a
//! panic hook installed once ([`guarded`]) keeps the panic from being printed on that thread;
//! other threads' panics go to the hook that was there before. The decompressor is never used
//! again after a panic. (A build with `panic = "abort"` would abort instead.)

use std::cell::Cell;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Once;

use laz::laszip::ChunkTable;
use laz::record::{
    LayeredPointRecordDecompressor, RecordDecompressor, SequentialPointRecordDecompressor,
};
use laz::{DecompressionSelection, LazItem, LazItemType, LazVlr};

use super::{LasInfo, LasReadError, invalid, io_err};

/// User id of the LASzip VLR.
pub const LASZIP_USER_ID: &str = "laszip encoded";
/// Record id of the LASzip VLR.
pub const LASZIP_RECORD_ID: u16 = 22204;
/// LASzip compressor: point-wise chunked (items version 1 and 2).
const COMPRESSOR_POINTWISE_CHUNKED: u16 = 2;
/// LASzip compressor: layered chunked (items version 3 and 4).
const COMPRESSOR_LAYERED_CHUNKED: u16 = 3;
/// Bytes of the read buffer between the file and the decoder.
const READ_BUFFER: usize = 1 << 16;

thread_local! {
    /// Set while this thread runs a [`guarded`] call into the `laz` crate.
    static QUIET: Cell<bool> = const { Cell::new(false) };
}
static HOOK: Once = Once::new();

/// Installs, once per process, a panic hook that stays silent on a thread inside [`guarded`]
/// and passes every other panic to the hook that was there before.
fn install_quiet_hook() {
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(Cell::get) {
                previous(info);
            }
        }));
    });
}

/// Runs `f`, a call into the `laz` crate; a panic inside it becomes `Err(its message)`.
fn guarded<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    install_quiet_hook();
    QUIET.with(|q| q.set(true));
    let r = catch_unwind(AssertUnwindSafe(f));
    QUIET.with(|q| q.set(false));
    r.map_err(|payload| {
        payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "a panic without a message".into())
    })
}

/// A reader restricted to the bytes `[.., end)` of `R`, through a buffer: the decoder of one
/// chunk sees the end of the chunk as the end of its input.
struct Window<R> {
    inner: BufReader<R>,
    /// Position of `inner`, absolute (`u64::MAX`: unknown, the next `set` seeks).
    pos: u64,
    /// One past the last byte readable.
    end: u64,
}

impl<R: Read + Seek> Window<R> {
    /// Moves to `start` and ends the window at `end`.
    fn set(&mut self, start: u64, end: u64) -> std::io::Result<()> {
        if start != self.pos {
            match i64::try_from(i128::from(start) - i128::from(self.pos)) {
                Ok(d) if self.pos != u64::MAX => self.inner.seek_relative(d)?,
                _ => {
                    self.inner.seek(SeekFrom::Start(start))?;
                }
            }
            self.pos = start;
        }
        self.end = end;
        Ok(())
    }
}

impl<R: Read> Read for Window<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let left = usize::try_from(self.end.saturating_sub(self.pos)).unwrap_or(usize::MAX);
        let take = left.min(buf.len());
        if take == 0 {
            return Ok(0);
        }
        let n = self.inner.read(&mut buf[..take])?;
        self.pos += n as u64;
        Ok(n)
    }
}

impl<R: Read + Seek> Seek for Window<R> {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        let target = match to {
            SeekFrom::Start(p) => Some(p),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
            SeekFrom::End(d) => self.end.checked_add_signed(d),
        };
        let Some(target) = target else {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "seek before the start of the file",
            ));
        };
        let end = self.end;
        self.set(target, end)?;
        Ok(target)
    }
}

/// The `laz` crate's decompressor of one chunk's records.
enum Decoder<R: Read + Seek> {
    /// Point-wise chunked (point formats 4, 5).
    Sequential(SequentialPointRecordDecompressor<'static, Window<R>>),
    /// Layered chunked (point formats 9, 10).
    Layered(LayeredPointRecordDecompressor<'static, Window<R>>),
}

impl<R: Read + Seek> Decoder<R> {
    fn window(&mut self) -> &mut Window<R> {
        match self {
            Decoder::Sequential(d) => d.get_mut(),
            Decoder::Layered(d) => d.get_mut(),
        }
    }

    /// Makes the decompressor ready for a new chunk (the window already set on it).
    fn start_chunk(&mut self, items: &Vec<LazItem>) -> laz::Result<()> {
        match self {
            Decoder::Sequential(d) => {
                d.reset();
                d.set_fields_from(items)
            }
            Decoder::Layered(d) => {
                d.reset();
                d.set_fields_from(items)?;
                d.set_selection(DecompressionSelection::all());
                Ok(())
            }
        }
    }

    fn next(&mut self, out: &mut [u8]) -> std::io::Result<()> {
        match self {
            Decoder::Sequential(d) => d.decompress_next(out),
            Decoder::Layered(d) => d.decompress_next(out),
        }
    }
}

/// One chunk of compressed points.
#[derive(Clone, Copy, Debug)]
struct Chunk {
    /// First byte in the file.
    start: u64,
    /// Length, bytes.
    bytes: u64,
    /// Points it holds (of those the header announces).
    points: u64,
    /// Number of its first point.
    first: u64,
}

/// The LAZ point records of a file, decompressed one record at a time.
pub(super) struct LazPoints<R: Read + Seek> {
    file: String,
    items: Vec<LazItem>,
    decoder: Decoder<R>,
    chunks: Vec<Chunk>,
    /// Index of the chunk being read (`chunks.len()` before the first).
    current: usize,
    /// Points read from the current chunk.
    read_in_chunk: u64,
    /// Layer sizes stored at the start of each layered chunk (0 for point-wise chunks).
    layers: usize,
    /// The uncompressed point, count and layer sizes at the start of a layered chunk.
    chunk_head: Vec<u8>,
    /// First byte of the compressed points (after the chunk table offset).
    data_start: u64,
    /// First byte of the chunk table.
    table_at: u64,
    /// Set after an error inside a chunk: the decompressor is not used again.
    failed: bool,
    /// Chunks started.
    pub(super) chunks_started: u64,
}

/// The field of an error about the LASzip VLR.
const VLR_FIELD: &str = "LASzip VLR (\"laszip encoded\" 22204)";

/// Canonical size of an item, bytes (`None` for extra bytes, whose size is their count).
fn item_size(t: LazItemType) -> Option<u16> {
    Some(match t {
        LazItemType::Point10 => 20,
        LazItemType::GpsTime => 8,
        LazItemType::RGB12 | LazItemType::RGB14 => 6,
        LazItemType::RGBNIR14 => 8,
        LazItemType::WavePacket13 | LazItemType::WavePacket14 => 29,
        LazItemType::Point14 => 30,
        LazItemType::Byte(_) | LazItemType::Byte14(_) => return None,
    })
}

/// Layer sizes a layered chunk stores for an item.
fn item_layers(t: LazItemType) -> usize {
    match t {
        LazItemType::Point14 => 9,
        LazItemType::RGBNIR14 => 2,
        LazItemType::Byte14(n) | LazItemType::Byte(n) => usize::from(n),
        _ => 1,
    }
}

/// The items a point format's records are made of, in order (extra bytes may follow). Formats
/// without waveforms are listed too (the reader refuses them before, but the decompression
/// itself is tested on a real format 8 file).
fn expected_items(format: u8) -> &'static [LazItemType] {
    use LazItemType::{GpsTime, Point10, Point14, RGB12, RGB14, RGBNIR14};
    match format {
        0 => &[Point10],
        1 => &[Point10, GpsTime],
        2 => &[Point10, RGB12],
        3 => &[Point10, GpsTime, RGB12],
        6 => &[Point14],
        7 => &[Point14, RGB14],
        8 => &[Point14, RGBNIR14],
        4 => &[
            LazItemType::Point10,
            LazItemType::GpsTime,
            LazItemType::WavePacket13,
        ],
        5 => &[
            LazItemType::Point10,
            LazItemType::GpsTime,
            LazItemType::RGB12,
            LazItemType::WavePacket13,
        ],
        9 => &[LazItemType::Point14, LazItemType::WavePacket14],
        10 => &[
            LazItemType::Point14,
            LazItemType::RGBNIR14,
            LazItemType::WavePacket14,
        ],
        _ => &[],
    }
}

fn item_list(items: &[LazItem]) -> String {
    items
        .iter()
        .map(|i| format!("{:?} v{} ({} bytes)", i.item_type(), i.version(), i.size()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Checks the VLR against the point format and record length; returns the items and whether the
/// chunks are layered.
fn check_vlr(info: &LasInfo, payload: &[u8]) -> Result<(LazVlr, Vec<LazItem>, bool), LasReadError> {
    let file = &info.file;
    let format = info.header.point_format;
    let record_len = u64::from(info.header.point_record_length);
    let u16_at = |at: usize| {
        payload
            .get(at..at + 2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
    };
    let (Some(compressor), Some(coder)) = (u16_at(0), u16_at(2)) else {
        return Err(invalid(
            file,
            VLR_FIELD,
            format!("{} bytes, too short", payload.len()),
        ));
    };
    let vlr = match guarded(|| LazVlr::from_buffer(payload)) {
        Ok(Ok(v)) => v,
        Ok(Err(e)) => return Err(invalid(file, VLR_FIELD, e.to_string())),
        Err(p) => return Err(invalid(file, VLR_FIELD, format!("unreadable ({p})"))),
    };
    let items = vlr.items().clone();
    let layered = match compressor {
        COMPRESSOR_POINTWISE_CHUNKED => false,
        COMPRESSOR_LAYERED_CHUNKED => true,
        1 => {
            return Err(LasReadError::Unsupported {
                file: file.clone(),
                field: format!("{VLR_FIELD}: compressor"),
                what: "1 (point-wise without chunks, written by LASzip 1.x before June 2011; \
                       compress it again with a current laszip)"
                    .into(),
            });
        }
        c => {
            return Err(invalid(
                file,
                format!("{VLR_FIELD}: compressor"),
                format!("{c} (2, point-wise chunked, or 3, layered chunked, expected)"),
            ));
        }
    };
    if coder != 0 {
        return Err(invalid(
            file,
            format!("{VLR_FIELD}: coder"),
            format!("{coder} (0, arithmetic, is the only one defined)"),
        ));
    }
    let versions: &[u16] = if layered { &[3, 4] } else { &[1, 2] };
    let want = expected_items(format);
    let mismatch = || {
        invalid(
            file,
            format!("{VLR_FIELD}: items"),
            format!(
                "{} do not describe point format {format} with compressor {compressor} (expected \
                 {:?} version {versions:?}, then extra bytes, {record_len} bytes in all)",
                item_list(&items),
                want
            ),
        )
    };
    if items.len() < want.len() {
        return Err(mismatch());
    }
    let mut total = 0u64;
    for (k, item) in items.iter().enumerate() {
        let t = item.item_type();
        let ok_type = match want.get(k) {
            Some(&w) => t == w,
            None if layered => matches!(t, LazItemType::Byte14(n) if n > 0),
            None => matches!(t, LazItemType::Byte(n) if n > 0),
        };
        let ok_size = item_size(t).is_none_or(|s| s == item.size());
        if !ok_type || !ok_size || !versions.contains(&item.version()) {
            return Err(mismatch());
        }
        total += u64::from(item.size());
    }
    if total != record_len {
        return Err(mismatch());
    }
    Ok((vlr, items, layered))
}

/// Reads `buf.len()` bytes at `at` of `r`, which has `len` bytes; `what` names them.
fn read_exact_at<R: Read + Seek>(
    r: &mut R,
    file: &str,
    len: u64,
    at: u64,
    buf: &mut [u8],
    what: &str,
) -> Result<(), LasReadError> {
    let end = at.checked_add(buf.len() as u64);
    if end.is_none_or(|e| e > len) {
        return Err(LasReadError::Truncated {
            file: file.to_string(),
            what: what.to_string(),
            start: at,
            end: end.unwrap_or(u64::MAX),
            len,
        });
    }
    r.seek(SeekFrom::Start(at))
        .and_then(|_| r.read_exact(buf))
        .map_err(|e| io_err(file, what, e))
}

/// Where the chunk table of a LAZ file lies and how many chunks its header states.
struct TablePlace {
    /// Offset of the chunk table, bytes.
    table_at: u64,
    /// Start of the first chunk (after the 8-byte chunk table offset), bytes.
    data_start: u64,
    /// Number of chunks the table header states.
    count: u64,
}

/// The field naming the chunk table at byte `table_at`.
fn table_field(table_at: u64) -> String {
    format!("LAZ chunk table (byte {table_at})")
}

/// Reads the chunk table offset of the file `info` describes: the first 8 bytes of the point
/// data, or the file's last 8 bytes when those are not past the point data (a writer that could
/// not seek back writes it there; LASzip reads it there). Refused unless past the offset
/// itself. Returns the offset, bytes.
fn chunk_table_offset<R: Read + Seek>(r: &mut R, info: &LasInfo) -> Result<u64, LasReadError> {
    let file = info.file.as_str();
    let len = info.file_len;
    let at = u64::from(info.header.offset_to_point_data);
    // The chunk table offset: the first 8 bytes of the point data. A writer that could not
    // seek back writes it as the file's last 8 bytes instead (LASzip reads it there).
    let mut b8 = [0u8; 8];
    read_exact_at(r, file, len, at, &mut b8, "the LAZ chunk table offset")?;
    let mut table_at = i64::from_le_bytes(b8);
    if table_at <= at as i64 && len >= at + 16 {
        read_exact_at(r, file, len, len - 8, &mut b8, "the LAZ chunk table offset")?;
        table_at = i64::from_le_bytes(b8);
    }
    let data_start = at + 8;
    if table_at < data_start as i64 {
        return Err(invalid(
            file,
            format!("LAZ chunk table offset (byte {at})"),
            format!(
                "{table_at}: no chunk table (the writer did not finish the file, or it is \
                 truncated)"
            ),
        ));
    }
    Ok(table_at as u64)
}

/// Reads the header of the chunk table at `table_at` (bytes) and checks its chunk count: no
/// more chunks than the compressed bytes before it can hold, and some when the header
/// announces points.
fn chunk_count<R: Read + Seek>(
    r: &mut R,
    info: &LasInfo,
    table_at: u64,
) -> Result<TablePlace, LasReadError> {
    let file = info.file.as_str();
    let len = info.file_len;
    let record_len = u64::from(info.header.point_record_length);
    let n_points = info.header.number_of_points;
    let at = u64::from(info.header.offset_to_point_data);
    let data_start = at + 8;
    let mut b = [0u8; 8];
    read_exact_at(
        r,
        file,
        len,
        table_at,
        &mut b,
        &format!("the LAZ chunk table header (offset {table_at} read at byte {at})"),
    )?;
    let count = u64::from(u32::from_le_bytes([b[4], b[5], b[6], b[7]]));
    // Each chunk starts with one uncompressed point and at least 4 bytes of coded data.
    let min_chunk = record_len + 4;
    let data_bytes = table_at - data_start;
    let most = data_bytes / min_chunk;
    if count > most {
        return Err(invalid(
            file,
            table_field(table_at),
            format!(
                "{count} chunks, but the {data_bytes} bytes of compressed points before it \
                 hold at most {most} (each chunk starts with an uncompressed {record_len}-byte \
                 point)"
            ),
        ));
    }
    if n_points > 0 && count == 0 {
        return Err(invalid(
            file,
            table_field(table_at),
            format!("no chunks, but the header announces {n_points} points"),
        ));
    }
    Ok(TablePlace {
        table_at,
        data_start,
        count,
    })
}

/// Decodes the chunk table's entries (`variable`: with a point count each), under
/// [`guarded`]; entries past the end of the file or that do not decode are refused.
fn read_chunk_table<R: Read + Seek>(
    r: &mut R,
    info: &LasInfo,
    place: &TablePlace,
    variable: bool,
) -> Result<ChunkTable, LasReadError> {
    let file = info.file.as_str();
    let (table_at, count, len) = (place.table_at, place.count, info.file_len);
    r.seek(SeekFrom::Start(table_at))
        .map_err(|e| io_err(file, "the LAZ chunk table", e))?;
    let mut br = BufReader::with_capacity(4096, &mut *r);
    match guarded(|| ChunkTable::read(&mut br, variable)) {
        Ok(Ok(t)) => Ok(t),
        Ok(Err(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof => Err(invalid(
            file,
            table_field(table_at),
            format!("its {count} entries run past the end of the file ({len} bytes)"),
        )),
        Ok(Err(e)) => Err(io_err(file, "the LAZ chunk table", e)),
        Err(p) => Err(invalid(
            file,
            table_field(table_at),
            format!("damaged: its entries do not decode ({p})"),
        )),
    }
}

/// The chunks of `table`, laid end to end from the start of the point data: each chunk's byte
/// range must end before the chunk table and hold at least one uncompressed point, and the
/// chunks must hold every point the header announces (a last chunk's surplus is left out).
fn chunk_ranges(
    info: &LasInfo,
    table: &ChunkTable,
    vlr: &LazVlr,
    place: &TablePlace,
) -> Result<Vec<Chunk>, LasReadError> {
    let file = info.file.as_str();
    let record_len = u64::from(info.header.point_record_length);
    let n_points = info.header.number_of_points;
    let (table_at, count) = (place.table_at, place.count);
    let min_chunk = record_len + 4;
    let variable = vlr.uses_variable_size_chunks();
    let chunk_size = u64::from(vlr.chunk_size());
    let mut chunks = Vec::with_capacity(table.len());
    let mut start = place.data_start;
    let mut first = 0u64;
    for (i, e) in table.as_ref().iter().enumerate() {
        if first >= n_points {
            break;
        }
        let stated = if variable { e.point_count } else { chunk_size };
        let field = || format!("LAZ chunk {i} of {count} (chunk table at byte {table_at})");
        if stated == 0 {
            return Err(invalid(file, field(), "0 points"));
        }
        let end = start.checked_add(e.byte_count).filter(|&e| e <= table_at);
        let Some(end) = end else {
            return Err(invalid(
                file,
                field(),
                format!(
                    "{} bytes from byte {start}: past the start of the chunk table",
                    e.byte_count
                ),
            ));
        };
        if e.byte_count < min_chunk {
            return Err(invalid(
                file,
                field(),
                format!(
                    "{} bytes, fewer than one uncompressed {record_len}-byte point and the \
                     coder's 4",
                    e.byte_count
                ),
            ));
        }
        let points = stated.min(n_points - first);
        chunks.push(Chunk {
            start,
            bytes: e.byte_count,
            points,
            first,
        });
        start = end;
        first += points;
    }
    if first < n_points {
        return Err(invalid(
            file,
            table_field(table_at),
            format!("its {count} chunks hold {first} points, but the header announces {n_points}"),
        ));
    }
    Ok(chunks)
}

impl<R: Read + Seek> LazPoints<R> {
    /// Checks the LASzip VLR `payload` and the chunk table of `r` (the whole file, described by
    /// `info`), and makes the decompressor.
    pub(super) fn open(info: &LasInfo, payload: &[u8], mut r: R) -> Result<Self, LasReadError> {
        let (vlr, items, layered) = check_vlr(info, payload)?;
        let record_len = u64::from(info.header.point_record_length);
        let table_at = chunk_table_offset(&mut r, info)?;
        let place = chunk_count(&mut r, info, table_at)?;
        let variable = vlr.uses_variable_size_chunks();
        let table = read_chunk_table(&mut r, info, &place, variable)?;
        let chunks = chunk_ranges(info, &table, &vlr, &place)?;

        let layers = if layered {
            items.iter().map(|i| item_layers(i.item_type())).sum()
        } else {
            0
        };
        let window = Window {
            inner: BufReader::with_capacity(READ_BUFFER, r),
            // Unknown: the first `set` seeks.
            pos: u64::MAX,
            end: 0,
        };
        let decoder = if layered {
            Decoder::Layered(LayeredPointRecordDecompressor::new(window))
        } else {
            Decoder::Sequential(SequentialPointRecordDecompressor::new(window))
        };
        Ok(LazPoints {
            file: info.file.clone(),
            items,
            decoder,
            current: chunks.len(),
            chunks,
            read_in_chunk: 0,
            layers,
            chunk_head: vec![0u8; record_len as usize + 4 + 4 * layers],
            data_start: place.data_start,
            table_at,
            failed: false,
            chunks_started: 0,
        })
    }

    /// The field naming point `n` in chunk `c`.
    fn where_(&self, n: u64, c: usize) -> String {
        match self.chunks.get(c) {
            Some(k) => format!(
                "point {n} (LAZ chunk {c} of {}: points {}..{}, bytes {}..{})",
                self.chunks.len(),
                k.first,
                k.first + k.points,
                k.start,
                k.start + k.bytes
            ),
            None => format!("point {n}"),
        }
    }

    /// Moves to the next chunk, for point `n`.
    fn start_chunk(&mut self, n: u64) -> Result<(), LasReadError> {
        let c = if self.current >= self.chunks.len() {
            0
        } else {
            self.current + 1
        };
        let Some(&k) = self.chunks.get(c) else {
            return Err(invalid(
                &self.file,
                format!("point {n}"),
                "past the last LAZ chunk",
            ));
        };
        self.current = c;
        self.read_in_chunk = 0;
        // Cleared once the chunk is ready: an error below leaves the decompressor unusable.
        self.failed = true;
        let end = k.start + k.bytes;
        let what = || format!("LAZ chunk {c}");
        let w = self.decoder.window();
        w.set(k.start, end)
            .map_err(|e| io_err(&self.file, what(), e))?;
        if self.layers > 0 {
            // The layer sizes must fit in the chunk before the crate allocates for them.
            let head = self.chunk_head.len() as u64;
            if k.bytes < head {
                return Err(invalid(
                    &self.file,
                    self.where_(n, c),
                    format!(
                        "the chunk's {} bytes are fewer than its first point and layer sizes \
                         ({head})",
                        k.bytes
                    ),
                ));
            }
            w.read_exact(&mut self.chunk_head)
                .map_err(|e| io_err(&self.file, what(), e))?;
            w.set(k.start, end)
                .map_err(|e| io_err(&self.file, what(), e))?;
            let sizes = &self.chunk_head[self.chunk_head.len() - 4 * self.layers..];
            let layer_bytes: u64 = sizes
                .chunks_exact(4)
                .map(|s| u64::from(u32::from_le_bytes([s[0], s[1], s[2], s[3]])))
                .sum();
            if head + layer_bytes > k.bytes {
                return Err(invalid(
                    &self.file,
                    self.where_(n, c),
                    format!(
                        "damaged: its {} layers add up to {layer_bytes} bytes, but the chunk has \
                         {} after its first point and layer sizes",
                        self.layers,
                        k.bytes - head
                    ),
                ));
            }
        }
        match guarded(|| self.decoder.start_chunk(&self.items)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                return Err(invalid(&self.file, self.where_(n, c), e.to_string()));
            }
            Err(p) => {
                return Err(invalid(
                    &self.file,
                    self.where_(n, c),
                    format!("the LAZ decoder failed ({p})"),
                ));
            }
        }
        self.failed = false;
        self.chunks_started += 1;
        Ok(())
    }

    /// Decompresses point `n` (the next one) into `out` (the record length).
    pub(super) fn read_point(&mut self, n: u64, out: &mut [u8]) -> Result<(), LasReadError> {
        if self.failed {
            return Err(invalid(
                &self.file,
                format!("point {n}"),
                "not read: decompression stopped at an earlier error",
            ));
        }
        let in_chunk = self
            .chunks
            .get(self.current)
            .is_some_and(|k| self.read_in_chunk < k.points);
        if !in_chunk {
            self.start_chunk(n)?;
        }
        match guarded(|| self.decoder.next(out)) {
            Ok(Ok(())) => {
                self.read_in_chunk += 1;
                Ok(())
            }
            Ok(Err(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                self.failed = true;
                Err(invalid(
                    &self.file,
                    self.where_(n, self.current),
                    "damaged: the compressed data ends before this point (the chunk is cut or \
                     its bytes are wrong)",
                ))
            }
            Ok(Err(e)) => {
                self.failed = true;
                Err(io_err(&self.file, self.where_(n, self.current), e))
            }
            Err(p) => {
                self.failed = true;
                Err(invalid(
                    &self.file,
                    self.where_(n, self.current),
                    format!("damaged: the LAZ decoder failed on it ({p})"),
                ))
            }
        }
    }

    /// Bytes of the compressed points covered so far (estimated within the current chunk) and
    /// in all, counted from the start of the point data.
    pub(super) fn progress(&self) -> (u64, u64) {
        let total = self.table_at.saturating_sub(self.data_start);
        let done = match self.chunks.get(self.current) {
            Some(k) if k.points > 0 => {
                let within = (k.bytes as u128 * self.read_in_chunk as u128 / k.points as u128)
                    .min(u128::from(k.bytes)) as u64;
                (k.start - self.data_start) + within
            }
            _ => 0,
        };
        (done, total)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_inside_guarded_is_an_error_and_silent() {
        let r: Result<(), String> = guarded(|| panic!("index out of bounds: the len is 3"));
        assert_eq!(r.unwrap_err(), "index out of bounds: the len is 3");
        let r = guarded(|| {
            let v: Vec<u8> = Vec::new();
            let i = v.len() + 2;
            v[i]
        });
        assert!(r.unwrap_err().contains("index out of bounds"));
        assert_eq!(guarded(|| 7), Ok(7));
        assert!(!QUIET.with(Cell::get));
    }

    #[test]
    fn window_ends_reads_at_its_end_and_seeks_inside_the_file() {
        let bytes: Vec<u8> = (0..100u8).collect();
        let mut w = Window {
            inner: BufReader::with_capacity(8, std::io::Cursor::new(bytes)),
            pos: u64::MAX,
            end: 0,
        };
        w.set(10, 20).unwrap();
        let mut b = [0u8; 16];
        assert!(w.read_exact(&mut b).is_err());
        w.set(10, 20).unwrap();
        let mut b = [0u8; 10];
        w.read_exact(&mut b).unwrap();
        assert_eq!(b[0], 10);
        assert_eq!(b[9], 19);
        assert_eq!(w.read(&mut b).unwrap(), 0);
        assert_eq!(w.seek(SeekFrom::Current(-5)).unwrap(), 15);
        w.read_exact(&mut b[..5]).unwrap();
        assert_eq!(b[0], 15);
        assert_eq!(w.seek(SeekFrom::End(-1)).unwrap(), 19);
        assert!(w.seek(SeekFrom::Current(-100)).is_err());
    }

    /// A real LAZ from another writer (PDAL 2.4.3, IGN LiDAR HD tile of `tests/data`:
    /// LAS 1.4 point format 8, 60 653 points, 22 343 classified ground per its MANIFEST.md)
    /// decompressed through the checks and windows of this module: every point lies inside the
    /// header's bounds, the returns per number equal the header's counts, and the ground count
    /// is the manifest's.
    #[test]
    fn a_pdal_laz_decompresses_to_the_points_its_header_states() {
        use crate::format::las_write::Header;
        let path = crate::fixtures::path("dem/ign_lidarhd/test_data_77055_627760_LA93_IGN69.laz");
        let b = std::fs::read(&path).unwrap();
        let u16_at = |at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
        let u32_at = |at: usize| u32::from_le_bytes(b[at..at + 4].try_into().unwrap());
        let u64_at = |at: usize| u64::from_le_bytes(b[at..at + 8].try_into().unwrap());
        let f64_at = |at: usize| f64::from_le_bytes(b[at..at + 8].try_into().unwrap());
        assert_eq!(b[104], 0x80 | 8);
        // The LASzip VLR, walking the VLRs.
        let mut at = usize::from(u16_at(94));
        let mut payload = None;
        for _ in 0..u32_at(100) {
            let len = usize::from(u16_at(at + 20));
            if &b[at + 2..at + 16] == LASZIP_USER_ID.as_bytes() && u16_at(at + 18) == 22204 {
                payload = Some(b[at + 54..at + 54 + len].to_vec());
            }
            at += 54 + len;
        }
        let payload = payload.expect("LASzip VLR");
        let by_return: [u64; 15] = std::array::from_fn(|k| u64_at(255 + 8 * k));
        let header = Header {
            global_encoding: u16_at(6),
            system_identifier: String::new(),
            generating_software: String::new(),
            creation_day_of_year: 0,
            creation_year: 0,
            offset_to_point_data: u32_at(96),
            number_of_vlrs: u32_at(100),
            point_format: 8,
            point_record_length: u16_at(105),
            scale: [f64_at(131), f64_at(139), f64_at(147)],
            offset: [f64_at(155), f64_at(163), f64_at(171)],
            max: [f64_at(179), f64_at(195), f64_at(211)],
            min: [f64_at(187), f64_at(203), f64_at(219)],
            start_of_waveform_data: 0,
            start_of_first_evlr: u64_at(235),
            number_of_evlrs: u32_at(243),
            number_of_points: u64_at(247),
            points_by_return: by_return,
        };
        assert_eq!(header.number_of_points, 60_653);
        let info = LasInfo {
            file: "ign.laz".into(),
            file_len: b.len() as u64,
            version: (1, 4),
            header_size: u16_at(94),
            header: header.clone(),
            descriptors: Vec::new(),
            wkt: None,
            epsg: None,
            waveform: super::super::WaveformLocation::Absent,
            laz: Some(payload.clone()),
        };
        let mut z = LazPoints::open(&info, &payload, std::io::Cursor::new(&b[..])).unwrap();
        let mut rec = vec![0u8; usize::from(header.point_record_length)];
        let (mut ground, mut outside) = (0u64, 0u64);
        let mut counted = [0u64; 15];
        for n in 0..header.number_of_points {
            z.read_point(n, &mut rec).unwrap();
            for k in 0..3 {
                let raw = i32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().unwrap());
                let v = f64::from(raw) * header.scale[k] + header.offset[k];
                let slack = header.scale[k];
                if v < header.min[k] - slack || v > header.max[k] + slack {
                    outside += 1;
                }
            }
            let r = usize::from(rec[14] & 0x0f);
            if (1..=15).contains(&r) {
                counted[r - 1] += 1;
            }
            ground += u64::from(rec[16] == 2);
        }
        assert_eq!(outside, 0);
        assert_eq!(counted, header.points_by_return);
        assert_eq!(ground, 22_343);
        assert!(z.chunks_started >= 1);
        let (done, all) = z.progress();
        assert_eq!(done, all);
    }

    #[test]
    fn layer_counts_and_items_per_format() {
        assert_eq!(item_layers(LazItemType::Point14), 9);
        assert_eq!(item_layers(LazItemType::Byte14(4)), 4);
        assert_eq!(item_layers(LazItemType::WavePacket14), 1);
        for (f, size) in [(4u16, 57u16), (5, 63), (9, 59), (10, 67)] {
            let s: u16 = expected_items(f as u8)
                .iter()
                .map(|&t| item_size(t).unwrap())
                .sum();
            assert_eq!(s, size, "format {f}");
        }
    }
}
