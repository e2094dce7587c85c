//! The LAS public header block, the VLRs and EVLRs fwlidar reads ([`LasInfo`]), and the byte
//! decoding of point records with waveforms.

use std::io::{BufReader, Read, Seek, SeekFrom};

use super::laz::{LASZIP_RECORD_ID, LASZIP_USER_ID};
use super::{
    GLOBAL_WAVEFORM_INTERNAL, HEADER_SIZE_13, LasReadError, MAX_WKT_BYTES, invalid, io_err,
};
use crate::format::las_write::{
    DESCRIPTOR_RECORD_ID_BASE, DESCRIPTOR_SIZE, EVLR_HEADER_SIZE, GLOBAL_ADJUSTED_STANDARD_GPS,
    GLOBAL_WAVEFORM_EXTERNAL, GLOBAL_WKT, HEADER_SIZE, Header, LASF_PROJECTION, LASF_SPEC,
    MAX_DESCRIPTORS, PointRecord6, PointRecord9, VLR_HEADER_SIZE, WAVEFORM_DATA_RECORD_ID,
    WKT_RECORD_ID, WavePacketDescriptor,
};

/// Record id of the GeoTIFF GeoKeyDirectoryTag VLR (`LASF_Projection`).
pub const GEO_KEY_DIRECTORY_RECORD_ID: u16 = 34735;
/// Record id of the last possible waveform packet descriptor (index 255).
const DESCRIPTOR_RECORD_ID_LAST: u16 = DESCRIPTOR_RECORD_ID_BASE + MAX_DESCRIPTORS as u16;

/// Where the waveform data packets of a file are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaveformLocation {
    /// In the `.wdp` file beside the LAS file (global encoding bit 2); packet offsets count from
    /// the start of the `.wdp` (its 60-byte record header included).
    External,
    /// In the LAS file itself; packet offsets count from `record_start`, the first byte of the
    /// waveform data packet record's 60-byte header.
    Internal {
        /// Byte position of the waveform data packet record's header in the LAS file.
        record_start: u64,
    },
    /// The header states no waveform data (bits 1 and 2 clear, no start of waveform data): a
    /// point that names a packet is an error.
    Absent,
}

/// A waveform packet descriptor VLR as found (payload decoded even when shorter than 26 bytes:
/// missing bytes read as zero, and `payload_len` says so).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DescriptorRecord {
    /// The decoded fields.
    pub descriptor: WavePacketDescriptor,
    /// Length of the VLR payload, bytes (26 expected).
    pub payload_len: u64,
}

/// What the header and the (E)VLRs of a LAS file state.
#[derive(Clone, Debug, PartialEq)]
pub struct LasInfo {
    /// Name of the file in errors (its path).
    pub file: String,
    /// Length of the file, bytes.
    pub file_len: u64,
    /// Version major, minor (1, 3 or 1, 4).
    pub version: (u8, u8),
    /// Header size field, bytes.
    pub header_size: u16,
    /// The public header fields (as `las_write::Header`; `number_of_points` is the 64-bit count
    /// in LAS 1.4 when non-zero, else the legacy count; `points_by_return` likewise).
    pub header: Header,
    /// Waveform packet descriptors by index (`descriptors[i]` is index i; index 0 is never set).
    pub descriptors: Vec<Option<DescriptorRecord>>,
    /// OGC WKT of the coordinate reference system (VLR or EVLR `LASF_Projection` / 2112), NULs
    /// trimmed.
    pub wkt: Option<String>,
    /// EPSG code from the GeoKey directory (`LASF_Projection` / 34735): [`epsg_of_geokeys`].
    pub epsg: Option<u16>,
    /// Where the waveform packets are.
    pub waveform: WaveformLocation,
    /// The payload of the LASzip VLR (`laszip encoded` 22204) when the point records are
    /// LAZ-compressed (point data record format with bit 7 set, e.g. 137 for format 9;
    /// `header.point_format` holds the format without it); `None` for plain LAS.
    pub laz: Option<Vec<u8>>,
}

/// Byte layout of the point formats that carry waveforms.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct PointLayout {
    /// Smallest record length, bytes.
    size: usize,
    /// Offset of the GPS time.
    gps_at: usize,
    /// Offset of the wave packet descriptor index (the 29 waveform bytes follow).
    wave_at: usize,
    /// Formats 9 and 10 (4-bit return numbers, 16-bit scan angle).
    extended: bool,
}

impl PointLayout {
    pub(super) fn of(format: u8) -> Option<PointLayout> {
        let (size, gps_at, wave_at, extended) = match format {
            4 => (57, 20, 28, false),
            5 => (63, 20, 34, false),
            9 => (59, 22, 30, true),
            10 => (67, 22, 38, true),
            _ => return None,
        };
        Some(PointLayout {
            size,
            gps_at,
            wave_at,
            extended,
        })
    }
}

/// `N` bytes of `b` at `at`; zeros when out of range (callers check lengths first, so this only
/// keeps the parser panic-free).
fn arr<const N: usize>(b: &[u8], at: usize) -> [u8; N] {
    b.get(at..at.saturating_add(N))
        .and_then(|s| s.try_into().ok())
        .unwrap_or([0; N])
}
fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes(arr(b, at))
}
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(arr(b, at))
}
fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(arr(b, at))
}
fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(arr(b, at))
}
fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(arr(b, at))
}
fn text(b: &[u8]) -> String {
    let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
    String::from_utf8_lossy(&b[..end]).into_owned()
}

impl WavePacketDescriptor {
    /// Decodes a descriptor payload; bytes missing from a short payload read as zero.
    pub fn decode(b: &[u8]) -> WavePacketDescriptor {
        WavePacketDescriptor {
            bits_per_sample: b.first().copied().unwrap_or(0),
            compression: b.get(1).copied().unwrap_or(0),
            number_of_samples: u32_at(b, 2),
            temporal_spacing_ps: u32_at(b, 6),
            digitizer_gain: f64_at(b, 10),
            digitizer_offset: f64_at(b, 18),
        }
    }
}

impl PointRecord9 {
    /// Decodes the fields fwlidar uses from a point record of format 4, 5, 9 or 10 (`b` at
    /// least the format's size; shorter input reads as zeros). For formats 4 and 5 the scan
    /// angle rank (whole degrees) is converted to 0.006° units and the 3-bit return numbers are
    /// used; the scanner channel is 0.
    pub(super) fn decode(b: &[u8], layout: PointLayout) -> PointRecord9 {
        let w = layout.wave_at;
        let flags = b.get(14).copied().unwrap_or(0);
        let (return_number, number_of_returns, scanner_channel, scan_angle) = if layout.extended {
            (
                flags & 0x0f,
                flags >> 4,
                (b.get(15).copied().unwrap_or(0) >> 4) & 0x03,
                u16_at(b, 18) as i16,
            )
        } else {
            let rank = f64::from(b.get(16).copied().unwrap_or(0) as i8);
            (
                flags & 0x07,
                (flags >> 3) & 0x07,
                0,
                (rank / 0.006).round() as i16,
            )
        };
        PointRecord9 {
            core: PointRecord6 {
                xyz: [
                    u32_at(b, 0) as i32,
                    u32_at(b, 4) as i32,
                    u32_at(b, 8) as i32,
                ],
                intensity: u16_at(b, 12),
                return_number,
                number_of_returns,
                scanner_channel,
                classification: b
                    .get(if layout.extended { 16 } else { 15 })
                    .copied()
                    .unwrap_or(0),
                scan_angle,
                gps_time: f64_at(b, layout.gps_at),
            },
            wave_packet_index: b.get(w).copied().unwrap_or(0),
            wave_offset: u64_at(b, w + 1),
            wave_size: u32_at(b, w + 9),
            wave_location_ps: f32_at(b, w + 13),
            xyz_t: [f32_at(b, w + 17), f32_at(b, w + 21), f32_at(b, w + 25)],
        }
    }
}

/// A buffered reader that remembers its position, so that reading at the position it is at,
/// or a little ahead, costs no seek (a plain `BufReader::seek` drops its buffer).
pub(super) struct Positioned<R> {
    r: BufReader<R>,
    /// Position of `r`; `u64::MAX` after a failed read (the next read seeks).
    pos: u64,
}

impl<R: Read + Seek> Positioned<R> {
    pub(super) fn new(r: R, capacity: usize) -> Self {
        Positioned {
            r: BufReader::with_capacity(capacity, r),
            pos: u64::MAX,
        }
    }

    /// Reads `buf.len()` bytes at `at`.
    pub(super) fn read_exact_at(&mut self, at: u64, buf: &mut [u8]) -> std::io::Result<()> {
        if at != self.pos {
            match i64::try_from(i128::from(at) - i128::from(self.pos)) {
                Ok(d) if self.pos != u64::MAX => self.r.seek_relative(d)?,
                _ => {
                    self.r.seek(SeekFrom::Start(at))?;
                }
            }
        }
        self.pos = u64::MAX;
        self.r.read_exact(buf)?;
        self.pos = at + buf.len() as u64;
        Ok(())
    }
}

/// Reads `buf.len()` bytes at `at`, after checking they lie in the file.
fn read_at<R: Read + Seek>(
    r: &mut Positioned<R>,
    file: &str,
    file_len: u64,
    at: u64,
    buf: &mut [u8],
    what: &str,
) -> Result<(), LasReadError> {
    let end = at.checked_add(buf.len() as u64);
    if end.is_none_or(|e| e > file_len) {
        return Err(LasReadError::Truncated {
            file: file.to_string(),
            what: what.to_string(),
            start: at,
            end: end.unwrap_or(u64::MAX),
            len: file_len,
        });
    }
    r.read_exact_at(at, buf).map_err(|e| io_err(file, what, e))
}

/// Length of a seekable input, bytes.
pub(super) fn stream_len<R: Seek>(r: &mut R, file: &str) -> Result<u64, LasReadError> {
    r.seek(SeekFrom::End(0))
        .map_err(|e| io_err(file, "its length", e))
}

/// EPSG code of a GeoKey directory payload, by the precedence of [`crate::format::geokeys`]:
/// a projected code (3072), else EPSG:4978 for a geocentric model (1024 = 3; another datum when
/// 2048 names one), else a geographic code (2048) unless the model is projected.
pub fn epsg_of_geokeys(b: &[u8]) -> Option<u16> {
    crate::format::geokeys::GeoKeyDirectory::parse(b).epsg()
}

/// Indices set in `d`, runs of three or more written `a-b`: `1, 2`, `1-100`, `none`.
pub(super) fn defined_list(d: &[Option<DescriptorRecord>]) -> String {
    let idx: Vec<usize> = (1..d.len()).filter(|&i| d[i].is_some()).collect();
    if idx.is_empty() {
        return "none".into();
    }
    let mut parts = Vec::new();
    let mut i = 0;
    while i < idx.len() {
        let mut j = i;
        while j + 1 < idx.len() && idx[j + 1] == idx[j] + 1 {
            j += 1;
        }
        if j >= i + 2 {
            parts.push(format!("{}-{}", idx[i], idx[j]));
        } else {
            parts.extend(idx[i..=j].iter().map(|v| v.to_string()));
        }
        i = j + 1;
    }
    parts.join(", ")
}

/// What a (E)VLR holds that the reader keeps.
fn take_record<R: Read + Seek>(
    r: &mut Positioned<R>,
    info: &mut LasInfo,
    user: &str,
    record_id: u16,
    payload_at: u64,
    payload_len: u64,
    label: &str,
) -> Result<(), LasReadError> {
    let file = info.file.clone();
    if user == LASF_SPEC
        && (DESCRIPTOR_RECORD_ID_BASE + 1..=DESCRIPTOR_RECORD_ID_LAST).contains(&record_id)
    {
        let mut b = [0u8; DESCRIPTOR_SIZE];
        let n = payload_len.min(DESCRIPTOR_SIZE as u64) as usize;
        read_at(r, &file, info.file_len, payload_at, &mut b[..n], label)?;
        let index = usize::from(record_id - DESCRIPTOR_RECORD_ID_BASE);
        if let Some(slot) = info.descriptors.get_mut(index) {
            *slot = Some(DescriptorRecord {
                descriptor: WavePacketDescriptor::decode(&b[..n]),
                payload_len,
            });
        }
    } else if user == LASF_PROJECTION && record_id == WKT_RECORD_ID && info.wkt.is_none() {
        if payload_len > MAX_WKT_BYTES {
            return Err(invalid(
                &file,
                label,
                format!("an OGC WKT of {payload_len} bytes (at most {MAX_WKT_BYTES} are read)"),
            ));
        }
        // Bounded by MAX_WKT_BYTES, and read_at checks it lies in the file first.
        let mut b = vec![0u8; payload_len as usize];
        read_at(r, &file, info.file_len, payload_at, &mut b, label)?;
        let wkt = text(&b);
        if !wkt.trim().is_empty() {
            info.wkt = Some(wkt);
        }
    } else if user == LASZIP_USER_ID && record_id == LASZIP_RECORD_ID && info.laz.is_none() {
        // At most 65535 bytes (a VLR), and read_at checks it lies in the file first.
        let n = payload_len.min(u64::from(u16::MAX)) as usize;
        let mut b = vec![0u8; n.min(info.file_len as usize)];
        read_at(r, &file, info.file_len, payload_at, &mut b, label)?;
        info.laz = Some(b);
    } else if user == LASF_PROJECTION && record_id == GEO_KEY_DIRECTORY_RECORD_ID {
        let n = payload_len.min(u64::from(u16::MAX)) as usize;
        let mut b = vec![0u8; n.min(info.file_len as usize)];
        read_at(r, &file, info.file_len, payload_at, &mut b, label)?;
        info.epsg = epsg_of_geokeys(&b);
    }
    Ok(())
}

/// The first bytes of the public header block, as read by [`read_header_block`].
struct HeaderBlock {
    /// The first `HEADER_SIZE` bytes of the file (zeros past its end).
    bytes: [u8; HEADER_SIZE],
    /// Version major, minor.
    version: (u8, u8),
    /// Header size field, bytes.
    header_size: u16,
}

/// Reads the public header block of a file of `file_len` bytes: refuses a file without the
/// `LASF` signature, shorter than a header of its version, not LAS 1.3 or 1.4, or whose header
/// size field is below its version's header size.
fn read_header_block<R: Read + Seek>(
    r: &mut Positioned<R>,
    file: &str,
    file_len: u64,
) -> Result<HeaderBlock, LasReadError> {
    let mut h = [0u8; HEADER_SIZE];
    let n = file_len.min(HEADER_SIZE as u64) as usize;
    read_at(r, file, file_len, 0, &mut h[..n], "the public header block")?;
    if &h[0..4] != b"LASF" {
        return Err(LasReadError::Signature {
            file: file.into(),
            found: String::from_utf8_lossy(&h[..n.min(4)]).into_owned(),
        });
    }
    if file_len < HEADER_SIZE_13 as u64 {
        return Err(LasReadError::Truncated {
            file: file.into(),
            what: "the public header block".into(),
            start: 0,
            end: HEADER_SIZE_13 as u64,
            len: file_len,
        });
    }
    let version = (h[24], h[25]);
    if version.0 != 1 || !(3..=4).contains(&version.1) {
        return Err(LasReadError::Unsupported {
            file: file.into(),
            field: "header: version".into(),
            what: format!(
                "LAS {}.{} (waveform packets need LAS 1.3 or 1.4)",
                version.0, version.1
            ),
        });
    }
    let header_size = u16_at(&h, 94);
    let need = if version.1 >= 4 {
        HEADER_SIZE
    } else {
        HEADER_SIZE_13
    };
    if usize::from(header_size) < need {
        return Err(invalid(
            file,
            "header: header size",
            format!(
                "{header_size} bytes, but a LAS 1.{} header has {need}",
                version.1
            ),
        ));
    }
    if file_len < need as u64 {
        return Err(LasReadError::Truncated {
            file: file.into(),
            what: format!("the LAS 1.{} public header block", version.1),
            start: 0,
            end: need as u64,
            len: file_len,
        });
    }
    Ok(HeaderBlock {
        bytes: h,
        version,
        header_size,
    })
}

/// The point data record format of a header, as checked by [`check_point_format`].
struct PointFormat {
    /// The format field as stored (bit 7 set when LAZ-compressed).
    raw: u8,
    /// Whether the point records are LAZ-compressed (bit 7).
    compressed: bool,
    /// The format without the compression bit.
    format: u8,
}

/// Checks the point-record layout the header `h` states: a LAS point format (bit 6 clear) that
/// carries waveform packets (4, 5, 9, 10), a record length that holds it, and point data that
/// start after the `header_size`-byte header.
fn check_point_format(
    file: &str,
    h: &[u8; HEADER_SIZE],
    header_size: u16,
) -> Result<PointFormat, LasReadError> {
    let offset_to_point_data = u32_at(h, 96);
    let raw_format = h[104];
    // LASzip marks compressed point records by setting bit 7.
    let compressed = raw_format & 0x80 != 0;
    let point_format = raw_format & 0x7f;
    if point_format & 0x40 != 0 {
        return Err(LasReadError::Unsupported {
            file: file.into(),
            field: "header: point data record format".into(),
            what: format!(
                "{raw_format} (bit 6 set: no LAS format; early experimental LASzip versions \
                 marked their files so)"
            ),
        });
    }
    let point_record_length = u16_at(h, 105);
    if u64::from(offset_to_point_data) < u64::from(header_size) {
        return Err(invalid(
            file,
            "header: offset to point data",
            format!("{offset_to_point_data}, inside the {header_size}-byte header"),
        ));
    }
    let Some(layout) = PointLayout::of(point_format) else {
        let laz = if compressed {
            format!(" (LAZ-compressed, stored as {raw_format})")
        } else {
            String::new()
        };
        return Err(LasReadError::Unsupported {
            file: file.into(),
            field: "header: point data record format".into(),
            what: format!(
                "point format {point_format}{laz}, which carries no waveform packets \
                 (formats 4, 5, 9 and 10 do)"
            ),
        });
    };
    if usize::from(point_record_length) < layout.size {
        return Err(invalid(
            file,
            "header: point data record length",
            format!(
                "{point_record_length} bytes, but point format {point_format} needs at \
                 least {}",
                layout.size
            ),
        ));
    }
    Ok(PointFormat {
        raw: raw_format,
        compressed,
        format: point_format,
    })
}

/// The public header fields of header bytes `h` of LAS `version`: the point counts are the
/// 64-bit ones of LAS 1.4 when non-zero, else the legacy ones.
fn decode_header(h: &[u8; HEADER_SIZE], version: (u8, u8), format: &PointFormat) -> Header {
    let legacy_points = u64::from(u32_at(h, 107));
    let mut legacy_by_return = [0u64; 15];
    for (k, v) in legacy_by_return.iter_mut().take(5).enumerate() {
        *v = u64::from(u32_at(h, 111 + 4 * k));
    }
    let f = |at: usize| f64_at(h, at);
    let is_14 = version.1 >= 4;
    let (start_of_first_evlr, number_of_evlrs, points_64) = if is_14 {
        (u64_at(h, 235), u32_at(h, 243), u64_at(h, 247))
    } else {
        (0, 0, 0)
    };
    let (number_of_points, points_by_return) = if points_64 != 0 {
        let mut by = [0u64; 15];
        for (k, v) in by.iter_mut().enumerate() {
            *v = u64_at(h, 255 + 8 * k);
        }
        (points_64, by)
    } else {
        (legacy_points, legacy_by_return)
    };
    Header {
        global_encoding: u16_at(h, 6),
        system_identifier: text(&h[26..58]),
        generating_software: text(&h[58..90]),
        creation_day_of_year: u16_at(h, 90),
        creation_year: u16_at(h, 92),
        offset_to_point_data: u32_at(h, 96),
        number_of_vlrs: u32_at(h, 100),
        point_format: format.format,
        point_record_length: u16_at(h, 105),
        scale: [f(131), f(139), f(147)],
        offset: [f(155), f(163), f(171)],
        max: [f(179), f(195), f(211)],
        min: [f(187), f(203), f(219)],
        start_of_waveform_data: u64_at(h, 227),
        start_of_first_evlr,
        number_of_evlrs,
        number_of_points,
        points_by_return,
    }
}

/// The point records `header` announces must lie in the file (`file_len` bytes). LAZ
/// (`compressed`): checked against the chunk table when the points are opened, `laz.rs`.
fn check_points_fit(
    file: &str,
    header: &Header,
    compressed: bool,
    file_len: u64,
) -> Result<(), LasReadError> {
    let (number_of_points, point_record_length, offset_to_point_data) = (
        header.number_of_points,
        header.point_record_length,
        header.offset_to_point_data,
    );
    // The point records must lie in the file (LAZ: checked against the chunk table when the
    // points are opened, `laz.rs`).
    let points_end = number_of_points
        .checked_mul(u64::from(point_record_length))
        .and_then(|b| b.checked_add(u64::from(offset_to_point_data)));
    if !compressed && points_end.is_none_or(|e| e > file_len) {
        return Err(LasReadError::Truncated {
            file: file.into(),
            what: format!(
                "{number_of_points} point records of {point_record_length} bytes from byte \
                 {offset_to_point_data}"
            ),
            start: u64::from(offset_to_point_data),
            end: points_end.unwrap_or(u64::MAX),
            len: file_len,
        });
    }
    Ok(())
}

impl LasInfo {
    /// Reads the public header, the VLRs and (LAS 1.4) the EVLRs of `r`, named `file` in errors.
    /// Checks that the point records the header announces fit in the file.
    pub fn read<R: Read + Seek>(file: &str, r: &mut R) -> Result<LasInfo, LasReadError> {
        let file_len = stream_len(r, file)?;
        // Header and VLRs are read through one buffer: a file with hundreds of descriptor VLRs
        // costs a few reads, not two system calls per record.
        let r = &mut Positioned::new(r, 1 << 13);
        let block = read_header_block(r, file, file_len)?;
        let h = &block.bytes;
        let format = check_point_format(file, h, block.header_size)?;
        let header = decode_header(h, block.version, &format);
        check_points_fit(file, &header, format.compressed, file_len)?;
        let mut info = LasInfo {
            file: file.into(),
            file_len,
            version: block.version,
            header_size: block.header_size,
            header,
            descriptors: vec![None; MAX_DESCRIPTORS + 1],
            wkt: None,
            epsg: None,
            waveform: WaveformLocation::Absent,
            laz: None,
        };
        info.read_vlrs(r)?;
        info.check_laszip_vlr(&format)?;
        let waveform_evlr = info.read_evlrs(r)?;
        info.waveform = info.waveform_location(waveform_evlr)?;
        Ok(info)
    }

    /// Reads the VLRs, between the header and the points, keeping what [`take_record`] keeps;
    /// each must lie whole before the point data.
    fn read_vlrs<R: Read + Seek>(&mut self, r: &mut Positioned<R>) -> Result<(), LasReadError> {
        let (file, file_len) = (self.file.clone(), self.file_len);
        let file = file.as_str();
        let number_of_vlrs = self.header.number_of_vlrs;
        // VLRs: between the header and the points.
        let mut at = u64::from(self.header_size);
        let vlr_end = u64::from(self.header.offset_to_point_data);
        let mut vh = [0u8; VLR_HEADER_SIZE];
        for i in 0..number_of_vlrs {
            if at + VLR_HEADER_SIZE as u64 > vlr_end {
                return Err(invalid(
                    file,
                    format!("VLR {i} (of {number_of_vlrs})"),
                    format!(
                        "its header at byte {at} runs past the start of the point data \
                         ({vlr_end})"
                    ),
                ));
            }
            read_at(r, file, file_len, at, &mut vh, &format!("VLR {i} header"))?;
            let user = text(&vh[2..18]);
            let record_id = u16_at(&vh, 18);
            let len = u64::from(u16_at(&vh, 20));
            let payload_at = at + VLR_HEADER_SIZE as u64;
            let label = format!("VLR {i} ({user} {record_id})");
            if payload_at + len > vlr_end {
                return Err(invalid(
                    file,
                    label,
                    format!(
                        "its {len}-byte payload at byte {payload_at} runs past the start of the \
                         point data ({vlr_end})"
                    ),
                ));
            }
            take_record(r, self, &user, record_id, payload_at, len, &label)?;
            at = payload_at + len;
        }
        Ok(())
    }

    /// Compressed point records need the LASzip VLR; a plain file's LASzip VLR (kept from the
    /// LAZ it was decompressed from) is dropped.
    fn check_laszip_vlr(&mut self, format: &PointFormat) -> Result<(), LasReadError> {
        let (raw_format, point_format) = (format.raw, format.format);
        if format.compressed && self.laz.is_none() {
            return Err(invalid(
                &self.file,
                "header: point data record format",
                format!(
                    "{raw_format} says the point records are LAZ-compressed (format \
                     {point_format} with bit 7 set), but no LASzip VLR (\"{LASZIP_USER_ID}\" \
                     {LASZIP_RECORD_ID}) describes how"
                ),
            ));
        }
        if !format.compressed {
            // A plain LAS file that kept the VLR of the LAZ it was decompressed from.
            self.laz = None;
        }
        Ok(())
    }

    /// Reads the EVLRs (LAS 1.4), after the points, keeping what [`take_record`] keeps; each
    /// must lie whole in the file. Returns where the first waveform data packet EVLR
    /// (`LASF_Spec` 65535) starts, bytes, if one does.
    fn read_evlrs<R: Read + Seek>(
        &mut self,
        r: &mut Positioned<R>,
    ) -> Result<Option<u64>, LasReadError> {
        let (file, file_len) = (self.file.clone(), self.file_len);
        let file = file.as_str();
        let is_14 = self.version.1 >= 4;
        let (start_of_first_evlr, number_of_evlrs) =
            (self.header.start_of_first_evlr, self.header.number_of_evlrs);
        // EVLRs (LAS 1.4): after the points.
        let mut waveform_evlr = None;
        if is_14 && number_of_evlrs > 0 && start_of_first_evlr != 0 {
            let mut at = start_of_first_evlr;
            let mut eh = [0u8; EVLR_HEADER_SIZE];
            for i in 0..number_of_evlrs {
                let what = format!("EVLR {i} (of {number_of_evlrs}) header");
                read_at(r, file, file_len, at, &mut eh, &what)?;
                let user = text(&eh[2..18]);
                let record_id = u16_at(&eh, 18);
                let len = u64_at(&eh, 20);
                let payload_at = at + EVLR_HEADER_SIZE as u64;
                let end = payload_at.checked_add(len);
                if end.is_none_or(|e| e > file_len) {
                    return Err(LasReadError::Truncated {
                        file: file.into(),
                        what: format!("the {len}-byte payload of EVLR {i} ({user} {record_id})"),
                        start: payload_at,
                        end: end.unwrap_or(u64::MAX),
                        len: file_len,
                    });
                }
                if user == LASF_SPEC && record_id == WAVEFORM_DATA_RECORD_ID {
                    waveform_evlr.get_or_insert(at);
                } else {
                    let label = format!("EVLR {i} ({user} {record_id})");
                    take_record(r, self, &user, record_id, payload_at, len, &label)?;
                }
                at = payload_at + len;
            }
        }
        Ok(waveform_evlr)
    }

    /// Where the waveform packets are, from the global encoding and the start of the waveform
    /// data packet record (else the first waveform EVLR, `waveform_evlr`, for internal
    /// packets); an internal record's 60-byte header must lie in the file.
    fn waveform_location(
        &self,
        waveform_evlr: Option<u64>,
    ) -> Result<WaveformLocation, LasReadError> {
        let (file, file_len) = (self.file.as_str(), self.file_len);
        let global_encoding = self.header.global_encoding;
        let start = self.header.start_of_waveform_data;
        Ok(if global_encoding & GLOBAL_WAVEFORM_EXTERNAL != 0 {
            WaveformLocation::External
        } else if global_encoding & GLOBAL_WAVEFORM_INTERNAL != 0 || start != 0 {
            let record_start = if start != 0 {
                start
            } else {
                waveform_evlr.ok_or_else(|| {
                    invalid(
                        file,
                        "header: start of waveform data packet record",
                        "0, and global encoding bit 1 says the packets are internal but no EVLR \
                         LASF_Spec 65535 holds them",
                    )
                })?
            };
            let end = record_start.checked_add(EVLR_HEADER_SIZE as u64);
            if end.is_none_or(|e| e > file_len) {
                return Err(LasReadError::Truncated {
                    file: file.into(),
                    what: "the waveform data packet record header".into(),
                    start: record_start,
                    end: end.unwrap_or(u64::MAX),
                    len: file_len,
                });
            }
            WaveformLocation::Internal { record_start }
        } else {
            WaveformLocation::Absent
        })
    }

    /// The coordinate reference system as [`crate::core::facts::SourceFacts::crs`] wants it: the WKT
    /// when global encoding bit 4 says WKT is authoritative, else `EPSG:<code>` from plain
    /// GeoKeys, else the WKT when there is one.
    pub fn crs(&self) -> Option<String> {
        let wkt_first = self.header.global_encoding & GLOBAL_WKT != 0;
        match (&self.wkt, self.epsg) {
            (Some(w), _) if wkt_first => Some(w.clone()),
            (_, Some(code)) => Some(format!("EPSG:{code}")),
            (w, None) => w.clone(),
        }
    }

    /// Time base of the points' GPS time: `gps_adjusted_standard` (global encoding bit 0) or
    /// `gps_seconds_of_week`.
    pub fn time_base(&self) -> &'static str {
        if self.header.global_encoding & GLOBAL_ADJUSTED_STANDARD_GPS != 0 {
            "gps_adjusted_standard"
        } else {
            "gps_seconds_of_week"
        }
    }

    /// Number of waveform packet descriptors defined.
    pub fn descriptors_defined(&self) -> usize {
        self.descriptors.iter().filter(|d| d.is_some()).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geokeys_give_a_plain_epsg_code() {
        let mut b = Vec::new();
        for v in [
            1u16, 1, 0, 3, 1024, 0, 1, 1, 2048, 0, 1, 4326, 3072, 0, 1, 32633,
        ] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(epsg_of_geokeys(&b), Some(32633));
        // Bytes 14..16 hold the model type (key 1024), 30..32 the projected code (key 3072).
        // User-defined projected CS of a projected model: the geographic code names only the
        // projection's datum, so no code.
        b[30..32].copy_from_slice(&32767u16.to_le_bytes());
        assert_eq!(epsg_of_geokeys(&b), None);
        // A geographic model: still user-defined.
        b[14..16].copy_from_slice(&2u16.to_le_bytes());
        assert_eq!(epsg_of_geokeys(&b), None, "3072 = 32767 is user-defined");
        // Without a projected code, a geographic model's geographic code.
        b[30..32].copy_from_slice(&0u16.to_le_bytes());
        assert_eq!(epsg_of_geokeys(&b), Some(4326));
        // A projected code stored elsewhere (TIFF tag location not 0) is not read as a code.
        b[30..32].copy_from_slice(&32633u16.to_le_bytes());
        b[26..28].copy_from_slice(&34736u16.to_le_bytes());
        assert_eq!(epsg_of_geokeys(&b), Some(4326));
        // A geocentric model on WGS 84: EPSG:4978.
        b[14..16].copy_from_slice(&3u16.to_le_bytes());
        assert_eq!(epsg_of_geokeys(&b), Some(4978));
        // A key count larger than the payload reads no further than the payload.
        b[6..8].copy_from_slice(&1000u16.to_le_bytes());
        assert_eq!(epsg_of_geokeys(&b), Some(4978));
        assert_eq!(epsg_of_geokeys(&b[..7]), None);
    }

    #[test]
    fn defined_descriptors_are_listed_in_runs() {
        let mut d = vec![None; 256];
        assert_eq!(defined_list(&d), "none");
        let r = Some(DescriptorRecord {
            descriptor: WavePacketDescriptor::decode(&[]),
            payload_len: 26,
        });
        d[1] = r;
        d[2] = r;
        assert_eq!(defined_list(&d), "1, 2");
        for s in d.iter_mut().take(101).skip(3) {
            *s = r;
        }
        d[200] = r;
        assert_eq!(defined_list(&d), "1-100, 200");
    }

    #[test]
    fn descriptor_decodes_what_the_writer_encodes() {
        let d = WavePacketDescriptor {
            bits_per_sample: 8,
            compression: 0,
            number_of_samples: 256,
            temporal_spacing_ps: 2000,
            digitizer_gain: 0.01,
            digitizer_offset: -0.5,
        };
        assert_eq!(WavePacketDescriptor::decode(&d.encode()), d);
    }

    #[test]
    fn point_formats_4_5_10_decode_their_waveform_fields() {
        let rec = PointRecord9 {
            core: PointRecord6 {
                xyz: [1, -2, 3],
                return_number: 2,
                number_of_returns: 3,
                gps_time: 7.5,
                ..Default::default()
            },
            wave_packet_index: 3,
            wave_offset: 600,
            wave_size: 120,
            wave_location_ps: 1234.5,
            xyz_t: [1.0, 2.0, -3.0],
        };
        let mut pf9 = [0u8; 59];
        rec.encode_into(&mut pf9);
        // Format 10: 8 bytes of RGB + NIR between the GPS time and the waveform fields.
        let mut pf10 = [0u8; 67];
        pf10[..30].copy_from_slice(&pf9[..30]);
        pf10[38..67].copy_from_slice(&pf9[30..59]);
        // Format 4: the legacy 20-byte core, GPS time at 20, waveform at 28; 5 adds RGB.
        let mut pf4 = [0u8; 57];
        pf4[..14].copy_from_slice(&pf9[..14]);
        pf4[14] = 2 | (3 << 3);
        pf4[16] = (-5i8) as u8;
        pf4[20..28].copy_from_slice(&7.5f64.to_le_bytes());
        pf4[28..57].copy_from_slice(&pf9[30..59]);
        let mut pf5 = [0u8; 63];
        pf5[..28].copy_from_slice(&pf4[..28]);
        pf5[34..63].copy_from_slice(&pf4[28..57]);
        for (b, f) in [(&pf9[..], 9), (&pf10[..], 10), (&pf4[..], 4), (&pf5[..], 5)] {
            let got = PointRecord9::decode(b, PointLayout::of(f).unwrap());
            assert_eq!(got.core.xyz, rec.core.xyz, "format {f}");
            assert_eq!((got.core.return_number, got.core.number_of_returns), (2, 3));
            assert_eq!(got.core.gps_time, 7.5);
            assert_eq!(
                (got.wave_packet_index, got.wave_offset, got.wave_size),
                (3, 600, 120),
                "format {f}"
            );
            assert_eq!(got.wave_location_ps, 1234.5);
            assert_eq!(got.xyz_t, rec.xyz_t);
        }
        let got = PointRecord9::decode(&pf4, PointLayout::of(4).unwrap());
        assert_eq!(f64::from(got.core.scan_angle) * 0.006, -4.998);
        // Short input reads as zeros, no panic.
        let got = PointRecord9::decode(&pf9[..10], PointLayout::of(9).unwrap());
        assert_eq!(got.wave_packet_index, 0);
    }
}
