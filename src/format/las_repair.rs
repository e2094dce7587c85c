//! Rebuilding the header of a LAS 1.4 file that was cut off before its writer finished it
//! (`fwlidar repair`): a crash leaves point records after the VLRs but a header whose point
//! count, per-return counts and bounding box are stale (zero, or as of the last time the writer
//! rewrote them), and maybe a partial last record.
//!
//! [`analyse`] reads the header, walks the VLRs and EVLRs (refusing, with the field named, a file
//! that is not LAS 1.4 point format 6–10 or whose VLR or EVLR area is itself cut), counts the
//! whole point records the file holds, reads them for the bounding box and per-return counts,
//! and — for formats 9 and 10 with an external `.wdp` — drops the trailing points whose waveform
//! packets lie past the end of the `.wdp` (its buffer was handed to the OS later than the
//! points'). The result is a [`RepairPlan`]: the new header bytes, the length to cut the file
//! to, the `.wdp` record length to write, and a [`RepairReport`] of every field changed.
//! [`apply`] writes it after copying the originals to `NAME.bak`. Neither panics on any input
//! (proptest in `tests/las_repair.rs`, fuzz target `las_repair`).

use std::io::{BufReader, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::format::las_write::{EVLR_HEADER_SIZE, HEADER_SIZE, VLR_HEADER_SIZE};

/// What makes a file unrepairable, or repair impossible; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum RepairError {
    /// Not a LAS file at all.
    #[error("{file}: not a LAS file ({reason})")]
    NotLas {
        /// The file.
        file: String,
        /// What was found.
        reason: String,
    },
    /// A header field or record that repair cannot accept.
    #[error("{file}: {field}: {reason}")]
    Field {
        /// The file.
        file: String,
        /// The field or record.
        field: String,
        /// Why.
        reason: String,
    },
    /// The backup already exists: nothing was changed.
    #[error("{file}: the backup {backup} already exists; move it away first (nothing was changed)")]
    BackupExists {
        /// The file to repair.
        file: String,
        /// The backup path.
        backup: String,
    },
    /// Reading or writing failed.
    #[error("{file}: {what}: {source}")]
    Io {
        /// The file.
        file: String,
        /// What was being done.
        what: String,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// One header field changed by the repair.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FieldChange {
    /// Field name as the LAS specification calls it.
    pub field: String,
    /// Value found.
    pub before: serde_json::Value,
    /// Value written.
    pub after: serde_json::Value,
}

/// What the `.wdp` beside the file held and what changes in it.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct WdpReport {
    /// Path of the `.wdp`.
    pub file: String,
    /// Its size, bytes.
    pub bytes: u64,
    /// Record length after header found in its 60-byte header.
    pub record_length_before: u64,
    /// Record length written (`bytes − 60`).
    pub record_length_after: u64,
    /// Backup written (`NAME.bak`), when it changed and the plan was applied.
    pub backup: Option<String>,
}

/// What repair found and changed (`fwlidar repair --json`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct RepairReport {
    /// The file.
    pub file: String,
    /// Its size before, bytes.
    pub file_bytes: u64,
    /// Its size after, bytes (less by `trailing_bytes_dropped`).
    pub file_bytes_after: u64,
    /// Point data record format.
    pub point_format: u8,
    /// Point data record length, bytes.
    pub point_record_length: u16,
    /// Offset to the first point record.
    pub offset_to_point_data: u64,
    /// Number of point records the header stated.
    pub points_in_header: u64,
    /// Number of point records after the repair.
    pub points: u64,
    /// Bytes of a partial last point record cut off the end of the file.
    pub trailing_bytes_dropped: u64,
    /// Whole trailing point records dropped because their waveform packets lie past the end of
    /// the `.wdp`.
    pub points_dropped_without_waveform: u64,
    /// Points kept whose waveform packet lies past the end of the `.wdp` (not trailing: left as
    /// they are).
    pub packets_out_of_range: u64,
    /// Header fields changed.
    pub changed: Vec<FieldChange>,
    /// The `.wdp` (formats 9, 10 with external waveforms), when found.
    pub wdp: Option<WdpReport>,
    /// Notes (e.g. the `.wdp` was not found).
    pub notes: Vec<String>,
    /// Backup of the file written (`NAME.bak`), when the plan was applied.
    pub backup: Option<String>,
    /// Whether anything had to change.
    pub repaired: bool,
}

/// What [`apply`] writes.
#[derive(Clone, Debug, PartialEq)]
pub struct RepairPlan {
    /// The new public header block (the header's own size; only LAS 1.4 fields rewritten).
    pub header: Vec<u8>,
    /// Length to cut the file to.
    pub new_len: u64,
    /// New record length of the `.wdp` (written at its byte 20), when it changes.
    pub wdp_record_length: Option<u64>,
    /// The report.
    pub report: RepairReport,
}

/// The `.wdp` beside `las`: `X.wdp` (or `X.WDP`) for `X.las`, and `X.wdp.partial` for a file
/// still under its temporary name `X.las.partial`. `None` when none exists.
pub fn wdp_path(las: &Path) -> Option<PathBuf> {
    let name = las.file_name()?.to_string_lossy().into_owned();
    let candidates: Vec<PathBuf> = if let Some(base) = name.strip_suffix(".partial") {
        let stem = Path::new(base).with_extension("");
        let stem = stem.to_string_lossy();
        vec![
            las.with_file_name(format!("{stem}.wdp.partial")),
            las.with_file_name(format!("{stem}.WDP.partial")),
        ]
    } else {
        vec![las.with_extension("wdp"), las.with_extension("WDP")]
    };
    candidates.into_iter().find(|p| p.is_file())
}

fn field(file: &str, field: &str, reason: impl Into<String>) -> RepairError {
    RepairError::Field {
        file: file.to_string(),
        field: field.to_string(),
        reason: reason.into(),
    }
}

fn io(file: &str, what: &str, source: std::io::Error) -> RepairError {
    RepairError::Io {
        file: file.to_string(),
        what: what.to_string(),
        source,
    }
}

fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap_or([0; 4]))
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap_or([0; 8]))
}
fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().unwrap_or([0; 8]))
}

/// Smallest record length of point formats 6–10, and the offset of the wave packet fields of 9
/// and 10.
fn layout(format: u8) -> Option<(u16, Option<usize>)> {
    Some(match format {
        6 => (30, None),
        7 => (36, None),
        8 => (38, None),
        9 => (59, Some(30)),
        10 => (67, Some(38)),
        _ => return None,
    })
}

fn read_exact_at<R: Read + Seek>(
    r: &mut R,
    file: &str,
    at: u64,
    buf: &mut [u8],
    what: &str,
) -> Result<(), RepairError> {
    r.seek(SeekFrom::Start(at))
        .and_then(|_| r.read_exact(buf))
        .map_err(|e| io(file, what, e))
}

/// Works out what the header of `r` (named `file`, `file_len` bytes) should say. `wdp`: the
/// `.wdp`'s name, length and first 60 bytes (as many as it has), when there is one.
pub fn analyse<R: Read + Seek>(
    r: &mut R,
    file: &str,
    file_len: u64,
    wdp: Option<(&str, u64, &[u8])>,
) -> Result<RepairPlan, RepairError> {
    check_signature(r, file, file_len)?;
    let h = read_header(r, file, file_len)?;
    let layout = point_layout(file, &h, file_len)?;
    check_vlrs(r, file, &h, layout.offset)?;
    let (end, waveform_evlr) = check_evlrs(r, file, &h, layout.offset, file_len)?;
    check_internal_waveforms(file, &h, layout.global, waveform_evlr)?;
    let (whole, trailing) = count_records(file, &layout, end, file_len)?;
    let (scale, off) = scale_and_offset(file, &h)?;

    // The external .wdp: its size bounds the packets.
    let external = layout.global & 0b100 != 0 && layout.wave_at.is_some();
    let mut report = RepairReport {
        file: file.to_string(),
        file_bytes: file_len,
        point_format: layout.format,
        point_record_length: layout.record_len,
        offset_to_point_data: layout.offset,
        points_in_header: {
            let n = u64_at(&h, 247);
            if n == 0 {
                u64::from(u32_at(&h, 107))
            } else {
                n
            }
        },
        trailing_bytes_dropped: trailing,
        ..Default::default()
    };
    let (wdp_len, wdp_record_length) = if external {
        check_wdp(wdp, &mut report)?
    } else {
        (None, None)
    };

    let kept = scan_points(r, file, &layout, whole, external, wdp_len, &mut report)?;
    let n = kept.points;
    report.points = n;
    let new_len = if end == file_len {
        layout.offset + n * u64::from(layout.record_len)
    } else {
        file_len
    };
    report.file_bytes_after = new_len;

    // The new header.
    let mut nh = h.clone();
    rewrite_bounds(&h, &mut nh, &kept, scale, off, &mut report);
    rewrite_counts(&h, &mut nh, &kept, &mut report);
    report.repaired =
        !report.changed.is_empty() || new_len != file_len || wdp_record_length.is_some();
    Ok(RepairPlan {
        header: nh,
        new_len,
        wdp_record_length,
        report,
    })
}

/// Refuses a file shorter than 4 bytes or whose first 4 bytes are not `LASF`.
fn check_signature<R: Read + Seek>(
    r: &mut R,
    file: &str,
    file_len: u64,
) -> Result<(), RepairError> {
    let mut sig = [0u8; 4];
    if file_len < 4 {
        return Err(RepairError::NotLas {
            file: file.into(),
            reason: format!("{file_len} bytes, shorter than the file signature"),
        });
    }
    read_exact_at(r, file, 0, &mut sig, "reading the file signature")?;
    if &sig != b"LASF" {
        return Err(RepairError::NotLas {
            file: file.into(),
            reason: format!(
                "file signature {:?}, expected \"LASF\"",
                String::from_utf8_lossy(&sig)
            ),
        });
    }
    Ok(())
}

/// Reads the public header block (its stated size, bytes), refusing a file that is not LAS 1.4,
/// whose header size is below a LAS 1.4 header's, or that is shorter than its header.
fn read_header<R: Read + Seek>(
    r: &mut R,
    file: &str,
    file_len: u64,
) -> Result<Vec<u8>, RepairError> {
    if file_len < 96 {
        return Err(field(
            file,
            "header",
            format!("the file has {file_len} bytes, less than a LAS header"),
        ));
    }
    let mut head = [0u8; 96];
    read_exact_at(r, file, 0, &mut head, "reading the header")?;
    let (major, minor) = (head[24], head[25]);
    if (major, minor) != (1, 4) {
        return Err(field(
            file,
            "version",
            format!("LAS {major}.{minor}: repair handles LAS 1.4 only"),
        ));
    }
    let header_size = u16_at(&head, 94);
    if usize::from(header_size) < HEADER_SIZE {
        return Err(field(
            file,
            "header size",
            format!("{header_size} bytes, a LAS 1.4 header has at least {HEADER_SIZE}"),
        ));
    }
    if file_len < u64::from(header_size) {
        return Err(field(
            file,
            "header",
            format!("the file has {file_len} bytes, the header {header_size}: it is cut"),
        ));
    }
    let mut h = vec![0u8; usize::from(header_size)];
    read_exact_at(r, file, 0, &mut h, "reading the header")?;
    Ok(h)
}

/// The point records' layout as the header states it.
struct PointLayout {
    /// Point data record format (6 to 10).
    format: u8,
    /// Point data record length, bytes.
    record_len: u16,
    /// Offset of the wave packet fields in a record (formats 9 and 10).
    wave_at: Option<usize>,
    /// Global encoding bits.
    global: u16,
    /// Offset to the first point record, bytes.
    offset: u64,
}

/// Checks the point-record layout of header `h`: an uncompressed format 6 to 10, a record
/// length that holds the format, and an offset to the point data between the end of the header
/// and the end of the file (`file_len` bytes).
fn point_layout(file: &str, h: &[u8], file_len: u64) -> Result<PointLayout, RepairError> {
    let header_size = u16_at(h, 94);
    let raw_format = h[104];
    if raw_format & 0xc0 != 0 {
        return Err(field(
            file,
            "point data record format",
            format!("{raw_format}: compressed (LAZ) files are not repaired"),
        ));
    }
    let format = raw_format;
    let Some((min_len, wave_at)) = layout(format) else {
        return Err(field(
            file,
            "point data record format",
            format!("{format}: repair handles formats 6 to 10"),
        ));
    };
    let record_len = u16_at(h, 105);
    if record_len < min_len {
        return Err(field(
            file,
            "point data record length",
            format!("{record_len} bytes, format {format} needs at least {min_len}"),
        ));
    }
    let global = u16_at(h, 6);
    let offset = u64::from(u32_at(h, 96));
    if offset < u64::from(header_size) {
        return Err(field(
            file,
            "offset to point data",
            format!("{offset}, inside the {header_size}-byte header"),
        ));
    }
    if offset > file_len {
        return Err(field(
            file,
            "offset to point data",
            format!("{offset}, past the end of the file ({file_len} bytes): the VLR area is cut"),
        ));
    }
    Ok(PointLayout {
        format,
        record_len,
        wave_at,
        global,
        offset,
    })
}

/// Walks the VLRs the header `h` states: each must lie between the header and the point data
/// (which starts at byte `offset`).
fn check_vlrs<R: Read + Seek>(
    r: &mut R,
    file: &str,
    h: &[u8],
    offset: u64,
) -> Result<(), RepairError> {
    let header_size = u16_at(h, 94);
    // The VLRs must lie between the header and the points.
    let n_vlrs = u32_at(h, 100);
    let mut at = u64::from(header_size);
    let mut vh = [0u8; VLR_HEADER_SIZE];
    for i in 0..n_vlrs {
        if at + VLR_HEADER_SIZE as u64 > offset {
            return Err(field(
                file,
                &format!("VLR {i}"),
                format!(
                    "its header at byte {at} runs past the start of the point data ({offset}): \
                     the VLR area is cut or the number of VLRs ({n_vlrs}) is wrong"
                ),
            ));
        }
        read_exact_at(r, file, at, &mut vh, "reading a VLR header")?;
        let len = u64::from(u16_at(&vh, 20));
        at += VLR_HEADER_SIZE as u64 + len;
        if at > offset {
            return Err(field(
                file,
                &format!("VLR {i}"),
                format!(
                    "its {len}-byte payload ends at byte {at}, past the start of the point data \
                     ({offset}): the VLR area is cut"
                ),
            ));
        }
    }
    Ok(())
}

/// Walks the EVLRs the header `h` states, when any: each must lie whole in the file
/// (`file_len` bytes), after the point data (from byte `offset`). Returns where the point
/// data ends (the first EVLR, or the end of the file), bytes, and where the last EVLR of record
/// id 65535 (waveform data packets) starts, if one does.
fn check_evlrs<R: Read + Seek>(
    r: &mut R,
    file: &str,
    h: &[u8],
    offset: u64,
    file_len: u64,
) -> Result<(u64, Option<u64>), RepairError> {
    // EVLRs, when the header states any, must all be in the file; the points end at the first.
    let start_evlr = u64_at(h, 235);
    let n_evlrs = u32_at(h, 243);
    let mut end = file_len;
    let mut waveform_evlr = None;
    if n_evlrs > 0 {
        if start_evlr < offset || start_evlr > file_len {
            return Err(field(
                file,
                "start of first extended variable length record",
                format!(
                    "{start_evlr}, outside the point data and EVLRs ({offset}..{file_len}) of \
                     a file stating {n_evlrs} EVLRs"
                ),
            ));
        }
        let mut at = start_evlr;
        let mut eh = [0u8; EVLR_HEADER_SIZE];
        for i in 0..n_evlrs {
            if at.saturating_add(EVLR_HEADER_SIZE as u64) > file_len {
                return Err(field(
                    file,
                    &format!("EVLR {i}"),
                    format!("its header at byte {at} runs past the end of the file: it is cut"),
                ));
            }
            read_exact_at(r, file, at, &mut eh, "reading an EVLR header")?;
            if u16_at(&eh, 18) == 65535 {
                waveform_evlr = Some(at);
            }
            let len = u64_at(&eh, 20);
            at = at
                .saturating_add(EVLR_HEADER_SIZE as u64)
                .saturating_add(len);
            if at > file_len {
                return Err(field(
                    file,
                    &format!("EVLR {i}"),
                    format!("its {len}-byte payload runs past the end of the file: it is cut"),
                ));
            }
        }
        end = start_evlr;
    }
    Ok((end, waveform_evlr))
}

/// With internal waveform packets (global encoding bit 1), the header's start of the waveform
/// data packet record must be where an EVLR of record id 65535 starts (`waveform_evlr`).
fn check_internal_waveforms(
    file: &str,
    h: &[u8],
    global: u16,
    waveform_evlr: Option<u64>,
) -> Result<(), RepairError> {
    if global & 0b10 != 0 {
        let start_wdp = u64_at(h, 227);
        if waveform_evlr != Some(start_wdp) {
            return Err(field(
                file,
                "start of waveform data packet record",
                format!(
                    "{start_wdp}: the waveform packets are internal (global encoding bit 1) but \
                     no EVLR of record id 65535 starts there"
                ),
            ));
        }
    }
    Ok(())
}

/// The whole point records between the point data's start and `end` (bytes), and the bytes of
/// a partial last record; refused when that partial record is followed by EVLRs (it is not the
/// end of the file, `file_len` bytes, that was cut).
fn count_records(
    file: &str,
    layout: &PointLayout,
    end: u64,
    file_len: u64,
) -> Result<(u64, u64), RepairError> {
    let record_len = layout.record_len;
    let avail = end - layout.offset;
    let whole = avail / u64::from(record_len);
    let trailing = avail % u64::from(record_len);
    if trailing != 0 && end != file_len {
        return Err(field(
            file,
            "point data",
            format!(
                "{avail} bytes between the VLRs and the first EVLR are not a whole number of \
                 {record_len}-byte records"
            ),
        ));
    }
    Ok((whole, trailing))
}

/// The X, Y, Z scale factors and offsets of header `h` (metres per unit, metres), refused
/// unless finite (and the scale factors non-zero).
fn scale_and_offset(file: &str, h: &[u8]) -> Result<([f64; 3], [f64; 3]), RepairError> {
    let scale = [f64_at(h, 131), f64_at(h, 139), f64_at(h, 147)];
    let off = [f64_at(h, 155), f64_at(h, 163), f64_at(h, 171)];
    for (k, axis) in ["X", "Y", "Z"].iter().enumerate() {
        if !(scale[k].is_finite() && scale[k] != 0.0) {
            return Err(field(
                file,
                &format!("{axis} scale factor"),
                format!("{}: must be finite and non-zero", scale[k]),
            ));
        }
        if !off[k].is_finite() {
            return Err(field(
                file,
                &format!("{axis} offset"),
                format!("{}: must be finite", off[k]),
            ));
        }
    }
    Ok((scale, off))
}

/// Checks the external `.wdp` (`wdp`: its name, length in bytes and first 60 bytes) of a file
/// whose waveform packets are external, and records it in `report` (or a note when there is
/// none). Returns its length, bytes, and the record length to write in it when the stated one
/// is not its size less the 60-byte header.
fn check_wdp(
    wdp: Option<(&str, u64, &[u8])>,
    report: &mut RepairReport,
) -> Result<(Option<u64>, Option<u64>), RepairError> {
    let mut wdp_len = None;
    let mut wdp_record_length = None;
    match wdp {
        Some((name, len, head)) => {
            if len < EVLR_HEADER_SIZE as u64 || head.len() < EVLR_HEADER_SIZE {
                return Err(field(
                    name,
                    "waveform data packet record header",
                    format!("the file has {len} bytes, the record header 60: it is cut"),
                ));
            }
            if u16_at(head, 18) != 65535 {
                return Err(field(
                    name,
                    "record id",
                    format!(
                        "{}: not a waveform data packet record (65535)",
                        u16_at(head, 18)
                    ),
                ));
            }
            let before = u64_at(head, 20);
            let after = len - EVLR_HEADER_SIZE as u64;
            if before != after {
                wdp_record_length = Some(after);
            }
            report.wdp = Some(WdpReport {
                file: name.to_string(),
                bytes: len,
                record_length_before: before,
                record_length_after: after,
                backup: None,
            });
            wdp_len = Some(len);
        }
        None => report.notes.push(
            "the waveform packets are external (global encoding bit 2) but no .wdp was \
             found beside the file: packets not checked"
                .into(),
        ),
    }
    Ok((wdp_len, wdp_record_length))
}

/// What the points kept say: bounds in integer coordinates, counts by return number, and how
/// many points are kept.
struct KeptPoints {
    /// Smallest X, Y, Z (integer units of the header's scale).
    min: [i32; 3],
    /// Largest X, Y, Z (integer units of the header's scale).
    max: [i32; 3],
    /// Points by return number 1 to 15.
    by_return: [u64; 15],
    /// Points kept.
    points: u64,
}

/// Reads the `whole` point records: their bounds and per-return counts, kept up to the last
/// point whose waveform packet lies inside the `.wdp` (`wdp_len` bytes, when `external`).
/// Counts in `report` the points kept without their packet and the trailing points dropped.
fn scan_points<R: Read + Seek>(
    r: &mut R,
    file: &str,
    layout: &PointLayout,
    whole: u64,
    external: bool,
    wdp_len: Option<u64>,
    report: &mut RepairReport,
) -> Result<KeptPoints, RepairError> {
    // Read the points: bounds, per-return counts, packets in range.
    let mut rd = BufReader::with_capacity(1 << 20, &mut *r);
    rd.seek(SeekFrom::Start(layout.offset))
        .map_err(|e| io(file, "seeking to the point data", e))?;
    let mut rec = vec![0u8; usize::from(layout.record_len)];
    let mut min = [i32::MAX; 3];
    let mut max = [i32::MIN; 3];
    let mut by_return = [0u64; 15];
    // Per-point statistics are kept up to the last point whose packet is in range, so trailing
    // points without their packet can be dropped.
    let mut kept = (min, max, by_return, 0u64);
    let mut bad_since_kept = 0u64;
    for i in 0..whole {
        rd.read_exact(&mut rec)
            .map_err(|e| io(file, &format!("reading point {i}"), e))?;
        let xyz = [
            u32_at(&rec, 0) as i32,
            u32_at(&rec, 4) as i32,
            u32_at(&rec, 8) as i32,
        ];
        for k in 0..3 {
            min[k] = min[k].min(xyz[k]);
            max[k] = max[k].max(xyz[k]);
        }
        let rn = rec[14] & 0x0f;
        if (1..=15).contains(&rn) {
            by_return[usize::from(rn) - 1] += 1;
        }
        let in_range = match (layout.wave_at, wdp_len) {
            (Some(w), Some(len)) if external && rec[w] != 0 => {
                let o = u64_at(&rec, w + 1);
                let size = u64::from(u32_at(&rec, w + 9));
                o.checked_add(size).is_some_and(|e| e <= len)
            }
            _ => true,
        };
        if in_range {
            report.packets_out_of_range += bad_since_kept;
            bad_since_kept = 0;
            kept = (min, max, by_return, i + 1);
        } else {
            bad_since_kept += 1;
        }
    }
    drop(rd);
    let (min, max, by_return, points) = kept;
    report.points_dropped_without_waveform = bad_since_kept;
    Ok(KeptPoints {
        min,
        max,
        by_return,
        points,
    })
}

/// Writes into the new header `nh` the bounding box of the points kept (metres, from the
/// `scale` factors and offsets `off`; zeros when none is kept), recording in `report` every
/// bound that differs from the old header `h`'s.
fn rewrite_bounds(
    h: &[u8],
    nh: &mut [u8],
    kept: &KeptPoints,
    scale: [f64; 3],
    off: [f64; 3],
    report: &mut RepairReport,
) {
    let (min, max, n) = (kept.min, kept.max, kept.points);
    let bound = |v: i32, k: usize| {
        if n == 0 {
            0.0
        } else {
            off[k] + f64::from(v) * scale[k]
        }
    };
    let bounds = [
        ("max X", 179, bound(max[0], 0)),
        ("min X", 187, bound(min[0], 0)),
        ("max Y", 195, bound(max[1], 1)),
        ("min Y", 203, bound(min[1], 1)),
        ("max Z", 211, bound(max[2], 2)),
        ("min Z", 219, bound(min[2], 2)),
    ];
    for (name, at, v) in bounds {
        let before = f64_at(h, at);
        if before.to_bits() != v.to_bits() {
            report.changed.push(FieldChange {
                field: name.into(),
                before: serde_json::json!(before),
                after: serde_json::json!(v),
            });
            nh[at..at + 8].copy_from_slice(&v.to_le_bytes());
        }
    }
}

/// Writes into the new header `nh` the point counts of the points kept: the legacy counts
/// zeroed (formats 6–10), the number of point records and the counts by return, recording in
/// `report` every count that differs from the old header `h`'s.
fn rewrite_counts(h: &[u8], nh: &mut [u8], kept: &KeptPoints, report: &mut RepairReport) {
    let (n, by_return) = (kept.points, kept.by_return);
    // Legacy counts are zero for formats 6-10 (LAS 1.4).
    let legacy_n = u32_at(h, 107);
    if legacy_n != 0 {
        report.changed.push(FieldChange {
            field: "legacy number of point records".into(),
            before: legacy_n.into(),
            after: 0.into(),
        });
    }
    let legacy_by: Vec<u32> = (0..5).map(|k| u32_at(h, 111 + 4 * k)).collect();
    if legacy_by.iter().any(|&v| v != 0) {
        report.changed.push(FieldChange {
            field: "legacy number of points by return".into(),
            before: serde_json::json!(legacy_by),
            after: serde_json::json!([0, 0, 0, 0, 0]),
        });
    }
    nh[107..131].fill(0);
    let n_before = u64_at(h, 247);
    if n_before != n {
        report.changed.push(FieldChange {
            field: "number of point records".into(),
            before: n_before.into(),
            after: n.into(),
        });
        nh[247..255].copy_from_slice(&n.to_le_bytes());
    }
    let by_before: Vec<u64> = (0..15).map(|k| u64_at(h, 255 + 8 * k)).collect();
    if by_before != by_return {
        report.changed.push(FieldChange {
            field: "number of points by return".into(),
            before: serde_json::json!(by_before),
            after: serde_json::json!(by_return),
        });
        for (k, v) in by_return.iter().enumerate() {
            nh[255 + 8 * k..263 + 8 * k].copy_from_slice(&v.to_le_bytes());
        }
    }
}

fn backup_path(p: &Path) -> PathBuf {
    let mut s = p.as_os_str().to_os_string();
    s.push(".bak");
    PathBuf::from(s)
}

/// Analyses `path` (and the `.wdp` beside it) and, when something must change, copies the
/// originals to `NAME.bak` (refusing if one exists) and writes the new header in place, cuts a
/// partial last record and fixes the `.wdp`'s record length; each file is synced. Returns the
/// report (`backup` set when written). Nothing is written when nothing must change.
pub fn repair_file(path: &Path) -> Result<RepairReport, RepairError> {
    let name = path.display().to_string();
    let mut f = std::fs::File::open(path).map_err(|e| io(&name, "cannot open", e))?;
    let len = f
        .metadata()
        .map_err(|e| io(&name, "cannot read its size", e))?
        .len();
    let wdp = wdp_path(path);
    let wdp_info = match &wdp {
        Some(p) => {
            let wname = p.display().to_string();
            let mut w = std::fs::File::open(p).map_err(|e| io(&wname, "cannot open", e))?;
            let wlen = w
                .metadata()
                .map_err(|e| io(&wname, "cannot read its size", e))?
                .len();
            let mut head = Vec::with_capacity(EVLR_HEADER_SIZE);
            (&mut w)
                .take(EVLR_HEADER_SIZE as u64)
                .read_to_end(&mut head)
                .map_err(|e| io(&wname, "reading its header", e))?;
            Some((wname, wlen, head))
        }
        None => None,
    };
    let mut plan = analyse(
        &mut f,
        &name,
        len,
        wdp_info
            .as_ref()
            .map(|(n, l, h)| (n.as_str(), *l, h.as_slice())),
    )?;
    drop(f);
    if !plan.report.repaired {
        return Ok(plan.report);
    }
    apply(path, wdp.as_deref(), &mut plan)?;
    Ok(plan.report)
}

/// Writes `plan` to `path` (and the `.wdp` at `wdp`): opens each for writing first (an
/// unwritable file is refused before anything is copied), refuses an existing `NAME.bak`,
/// copies the originals there, then writes and syncs.
pub fn apply(path: &Path, wdp: Option<&Path>, plan: &mut RepairPlan) -> Result<(), RepairError> {
    let name = path.display().to_string();
    let open_rw = |p: &Path| {
        std::fs::OpenOptions::new()
            .write(true)
            .open(p)
            .map_err(|e| io(&p.display().to_string(), "cannot open for writing", e))
    };
    let mut f = open_rw(path)?;
    let wdp = wdp.filter(|_| plan.wdp_record_length.is_some());
    let mut w = match wdp {
        Some(p) => Some(open_rw(p)?),
        None => None,
    };
    let bak = backup_path(path);
    let wbak = wdp.map(backup_path);
    for b in std::iter::once(&bak).chain(wbak.as_ref()) {
        if b.exists() {
            return Err(RepairError::BackupExists {
                file: name.clone(),
                backup: b.display().to_string(),
            });
        }
    }
    copy_new(path, &bak)?;
    plan.report.backup = Some(bak.display().to_string());
    if let (Some(src), Some(dst)) = (wdp, &wbak) {
        copy_new(src, dst)?;
        if let Some(r) = plan.report.wdp.as_mut() {
            r.backup = Some(dst.display().to_string());
        }
    }
    f.seek(SeekFrom::Start(0))
        .and_then(|_| f.write_all(&plan.header))
        .and_then(|_| f.set_len(plan.new_len))
        .and_then(|_| f.sync_all())
        .map_err(|e| io(&name, "writing the repaired header", e))?;
    if let (Some(w), Some(p), Some(v)) = (w.as_mut(), wdp, plan.wdp_record_length) {
        w.seek(SeekFrom::Start(20))
            .and_then(|_| w.write_all(&v.to_le_bytes()))
            .and_then(|_| w.sync_all())
            .map_err(|e| io(&p.display().to_string(), "writing its record length", e))?;
    }
    Ok(())
}

/// Copies `src` to a new file `dst` (never over an existing one) and syncs it.
fn copy_new(src: &Path, dst: &Path) -> Result<(), RepairError> {
    let dname = dst.display().to_string();
    let mut out = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(dst)
        .map_err(|e| io(&dname, "cannot create the backup", e))?;
    let mut inp =
        std::fs::File::open(src).map_err(|e| io(&src.display().to_string(), "cannot open", e))?;
    std::io::copy(&mut inp, &mut out)
        .and_then(|_| out.sync_all())
        .map_err(|e| io(&dname, "writing the backup", e))?;
    Ok(())
}
