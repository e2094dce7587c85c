//! Variable length records (VLRs, between the header and the pulse records) and appended ones
//! (AVLRs, after the pulse records, walked backwards from the end of the file: each carries its
//! payload in front of its 96-byte footer; the one with record ID `0xFFFFFFFF` ends the list).

use std::io::{Read, Seek, SeekFrom};

use super::error::PulseWavesError;
use super::header::PlsHeader;
use super::le;

/// Size of a VLR header (and of an AVLR footer), bytes.
pub const VLR_HEADER_LEN: u64 = 96;
/// User ID of the records the specification defines.
pub const SPEC_USER: &str = "PulseWaves_Spec";
/// User ID of the georeferencing records.
pub const PROJ_USER: &str = "PulseWaves_Proj";
/// Record ID of the AVLR that ends the appended list.
pub const AVLR_END: u32 = 0xFFFF_FFFF;

/// A record whose payload the reader keeps.
#[derive(Clone, Debug, PartialEq)]
pub struct Vlr {
    /// User ID (e.g. `PulseWaves_Spec`).
    pub user_id: String,
    /// Record ID.
    pub record_id: u32,
    /// Description, text.
    pub description: String,
    /// The payload.
    pub payload: Vec<u8>,
    /// Where it was: `VLR 3` or `AVLR 1` (for messages).
    pub place: String,
}

/// What the record walk found.
#[derive(Clone, Debug, Default)]
pub struct VlrScan {
    /// Records the reader interprets (scanners, descriptors, projection), VLRs first.
    pub kept: Vec<Vlr>,
    /// Records skipped (lookup tables, other users' records).
    pub skipped: u64,
    /// Lookup table records seen (`PulseWaves_Spec` 300001..300255); not applied.
    pub lookup_tables: u64,
}

/// Whether the reader interprets records of this user and ID.
pub fn is_interpreted(user_id: &str, record_id: u32) -> bool {
    match user_id {
        SPEC_USER => {
            (100_001..=100_255).contains(&record_id) || (200_001..=200_255).contains(&record_id)
        }
        PROJ_USER | "LASF_Projection" => matches!(record_id, 34735..=34737 | 2112),
        _ => false,
    }
}

struct RawHeader {
    user_id: String,
    record_id: u32,
    record_length: i64,
    description: String,
}

fn parse_header(b: &[u8; VLR_HEADER_LEN as usize]) -> RawHeader {
    RawHeader {
        user_id: le::text(b, 0, 16),
        record_id: le::u32(b, 16),
        record_length: le::i64(b, 24),
        description: le::text(b, 32, 64),
    }
}

fn read_at<R: Read + Seek>(
    r: &mut R,
    file: &str,
    at: u64,
    buf: &mut [u8],
) -> Result<(), PulseWavesError> {
    r.seek(SeekFrom::Start(at))
        .map_err(|e| PulseWavesError::io(file, e))?;
    r.read_exact(buf).map_err(|e| PulseWavesError::io(file, e))
}

/// Reads the VLRs and AVLRs of `file` (`file_len` bytes), keeping the payloads of the records
/// [`is_interpreted`] says the reader needs. Payload sizes are bounded by the file.
pub fn scan<R: Read + Seek>(
    r: &mut R,
    file: &str,
    header: &PlsHeader,
    file_len: u64,
) -> Result<VlrScan, PulseWavesError> {
    let mut out = VlrScan::default();
    let limit = header.pulse_data_start();
    let mut at = header.header_size as u64;
    for i in 0..header.number_of_vlrs {
        let place = format!("VLR {i}");
        let end = at.saturating_add(VLR_HEADER_LEN);
        if end > limit {
            return Err(PulseWavesError::invalid(
                file,
                format!("{place} header"),
                format!(
                    "bytes {at}..{end} run past offset_to_pulse_data {limit} (number_of_vlrs {})",
                    header.number_of_vlrs
                ),
            ));
        }
        let mut hb = [0u8; VLR_HEADER_LEN as usize];
        read_at(r, file, at, &mut hb)?;
        let h = parse_header(&hb);
        let len = u64::try_from(h.record_length).ok();
        let payload_end = len.and_then(|l| end.checked_add(l));
        let payload_end = match payload_end {
            Some(e) if e <= limit => e,
            _ => {
                return Err(PulseWavesError::invalid(
                    file,
                    format!(
                        "{place} (record {}): record_length_after_header",
                        h.record_id
                    ),
                    format!(
                        "{} bytes from byte {end} run past offset_to_pulse_data {limit}",
                        h.record_length
                    ),
                ));
            }
        };
        keep(r, file, h, end, payload_end, place, &mut out)?;
        at = payload_end;
    }
    if header.number_of_avlrs != 0 {
        scan_appended(r, file, header, file_len, &mut out)?;
    }
    Ok(out)
}

fn keep<R: Read + Seek>(
    r: &mut R,
    file: &str,
    h: RawHeader,
    start: u64,
    end: u64,
    place: String,
    out: &mut VlrScan,
) -> Result<(), PulseWavesError> {
    if h.user_id == SPEC_USER && (300_001..=300_255).contains(&h.record_id) {
        out.lookup_tables += 1;
    }
    if !is_interpreted(&h.user_id, h.record_id) {
        out.skipped += 1;
        return Ok(());
    }
    // `end - start` is bounded by the file's length (checked by the caller).
    let mut payload = vec![0u8; end.saturating_sub(start) as usize];
    read_at(r, file, start, &mut payload)?;
    out.kept.push(Vlr {
        user_id: h.user_id,
        record_id: h.record_id,
        description: h.description,
        payload,
        place,
    });
    Ok(())
}

fn scan_appended<R: Read + Seek>(
    r: &mut R,
    file: &str,
    header: &PlsHeader,
    file_len: u64,
    out: &mut VlrScan,
) -> Result<(), PulseWavesError> {
    let floor = header.pulse_data_end();
    let mut pos = file_len;
    let mut appended = Vec::new();
    let mut count: u64 = 0;
    loop {
        if header.number_of_avlrs > 0 && count >= header.number_of_avlrs as u64 {
            break;
        }
        let place = format!("AVLR {count}");
        let start = match pos.checked_sub(VLR_HEADER_LEN) {
            Some(s) if s >= floor => s,
            _ => {
                return Err(PulseWavesError::invalid(
                    file,
                    format!("{place} footer"),
                    format!(
                        "no room between the pulse records (ending at byte {floor}) and byte \
                         {pos} (number_of_avlrs {}, no end-of-list AVLR found)",
                        header.number_of_avlrs
                    ),
                ));
            }
        };
        let mut hb = [0u8; VLR_HEADER_LEN as usize];
        read_at(r, file, start, &mut hb)?;
        let h = parse_header(&hb);
        count += 1;
        if h.record_id == AVLR_END {
            break;
        }
        let payload_start = u64::try_from(h.record_length)
            .ok()
            .and_then(|l| start.checked_sub(l))
            .filter(|&s| s >= floor);
        let Some(payload_start) = payload_start else {
            return Err(PulseWavesError::invalid(
                file,
                format!(
                    "{place} (record {}): record_length_before_footer",
                    h.record_id
                ),
                format!(
                    "{} bytes before byte {start} reach into the pulse records (ending at byte \
                     {floor})",
                    h.record_length
                ),
            ));
        };
        let mut one = VlrScan::default();
        keep(r, file, h, payload_start, start, place, &mut one)?;
        out.skipped += one.skipped;
        out.lookup_tables += one.lookup_tables;
        appended.extend(one.kept);
        pos = payload_start;
    }
    // Walked from the end: restore file order so later records win over earlier ones.
    appended.reverse();
    out.kept.extend(appended);
    Ok(())
}
