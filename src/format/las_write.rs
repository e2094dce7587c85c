//! Byte encoding of the LAS 1.4 (R15) structures fwlidar writes: the public header block, VLR
//! and EVLR headers, the waveform packet descriptor, Extra Bytes descriptors (with no-data), the
//! WKT CRS record and point data record formats 6 and 9. Plain encoders: they check only what cannot be represented (and say so with
//! [`LasWriteError`]); the sink (`sink::las_wave`) decides what goes in them.
//!
//! All multi-byte values are little-endian. Layouts and field meanings: `docs/formats.md`,
//! "Returns as LAS 1.4 (output)".

/// Size of the LAS 1.4 public header block, bytes.
pub const HEADER_SIZE: usize = 375;
/// Size of a variable length record header, bytes.
pub const VLR_HEADER_SIZE: usize = 54;
/// Size of an extended variable length record header, bytes.
pub const EVLR_HEADER_SIZE: usize = 60;
/// Size of a point data record format 9 without extra bytes, bytes (30 core + 29 wave packet).
pub const PF9_SIZE: usize = 59;
/// Size of a waveform packet descriptor VLR payload, bytes.
pub const DESCRIPTOR_SIZE: usize = 26;
/// Size of one Extra Bytes descriptor, bytes.
pub const EXTRA_BYTES_DESCRIPTOR_SIZE: usize = 192;
/// Most waveform packet descriptors a file can hold (indices 1..=255; 0 means "no waveform").
pub const MAX_DESCRIPTORS: usize = 255;
/// Record id of the first waveform packet descriptor (index 1 is record id 100).
pub const DESCRIPTOR_RECORD_ID_BASE: u16 = 99;
/// Record id of the waveform data packets EVLR (in the LAS file or at the start of a `.wdp`).
pub const WAVEFORM_DATA_RECORD_ID: u16 = 65535;
/// User id of the records the specification defines.
pub const LASF_SPEC: &str = "LASF_Spec";
/// User id of the coordinate reference system records.
pub const LASF_PROJECTION: &str = "LASF_Projection";
/// Record id of the OGC WKT coordinate system VLR.
pub const WKT_RECORD_ID: u16 = 2112;
/// Record id of the Extra Bytes VLR.
pub const EXTRA_BYTES_RECORD_ID: u16 = 4;

/// Global encoding bit 0: GPS time is Adjusted Standard GPS time (else GPS week seconds).
pub const GLOBAL_ADJUSTED_STANDARD_GPS: u16 = 1 << 0;
/// Global encoding bit 2: waveform data packets are in an external `.wdp` file.
pub const GLOBAL_WAVEFORM_EXTERNAL: u16 = 1 << 2;
/// Global encoding bit 4: the coordinate reference system is WKT (required for PDRF 6–10).
pub const GLOBAL_WKT: u16 = 1 << 4;

/// What cannot be written as LAS.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LasWriteError {
    /// A 256th distinct waveform packet descriptor was needed.
    #[error(
        "more than {MAX_DESCRIPTORS} distinct waveform packet descriptors (bits, samples, sample \
         interval, gain, offset) are needed; LAS point records index at most {MAX_DESCRIPTORS}"
    )]
    TooManyDescriptors,
    /// A VLR payload longer than a VLR can hold.
    #[error("{what} is {len} bytes; a LAS VLR holds at most 65535")]
    VlrTooLong {
        /// What the record holds.
        what: &'static str,
        /// Its length, bytes.
        len: usize,
    },
    /// A value that has no LAS representation.
    #[error("{0}")]
    Unrepresentable(String),
}

/// The LAS 1.4 public header block (375 bytes), the fields fwlidar sets.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// Global encoding bit field (`GLOBAL_*`).
    pub global_encoding: u16,
    /// System identifier (at most 32 bytes, zero-padded).
    pub system_identifier: String,
    /// Generating software (at most 32 bytes, zero-padded).
    pub generating_software: String,
    /// File creation day of year (1 = January 1, GMT).
    pub creation_day_of_year: u16,
    /// File creation year (four digits).
    pub creation_year: u16,
    /// Bytes from the start of the file to the first point record.
    pub offset_to_point_data: u32,
    /// Number of VLRs between the header and the points.
    pub number_of_vlrs: u32,
    /// Point data record format.
    pub point_format: u8,
    /// Point data record length, bytes (format size plus extra bytes).
    pub point_record_length: u16,
    /// X, Y, Z scale factors.
    pub scale: [f64; 3],
    /// X, Y, Z offsets.
    pub offset: [f64; 3],
    /// Largest X, Y, Z of the points (as stored, i.e. after scaling).
    pub max: [f64; 3],
    /// Smallest X, Y, Z of the points.
    pub min: [f64; 3],
    /// Start of the internal waveform data packet record (0 when external or absent).
    pub start_of_waveform_data: u64,
    /// Start of the first EVLR (0 when there is none).
    pub start_of_first_evlr: u64,
    /// Number of EVLRs.
    pub number_of_evlrs: u32,
    /// Number of point records.
    pub number_of_points: u64,
    /// Points by return number 1..=15.
    pub points_by_return: [u64; 15],
}

fn put_str(buf: &mut [u8], s: &str) {
    let b = s.as_bytes();
    let n = b.len().min(buf.len());
    buf[..n].copy_from_slice(&b[..n]);
    buf[n..].fill(0);
}

impl Header {
    /// Encodes the header. Point formats below 6 are not written by fwlidar, so the legacy point
    /// counts are zero as LAS 1.4 requires for formats 6–10.
    pub fn encode(&self) -> [u8; HEADER_SIZE] {
        let mut b = [0u8; HEADER_SIZE];
        b[0..4].copy_from_slice(b"LASF");
        // 4: file source id 0 (not assigned); 8..24: project GUID zero.
        b[6..8].copy_from_slice(&self.global_encoding.to_le_bytes());
        b[24] = 1;
        b[25] = 4;
        put_str(&mut b[26..58], &self.system_identifier);
        put_str(&mut b[58..90], &self.generating_software);
        b[90..92].copy_from_slice(&self.creation_day_of_year.to_le_bytes());
        b[92..94].copy_from_slice(&self.creation_year.to_le_bytes());
        b[94..96].copy_from_slice(&(HEADER_SIZE as u16).to_le_bytes());
        b[96..100].copy_from_slice(&self.offset_to_point_data.to_le_bytes());
        b[100..104].copy_from_slice(&self.number_of_vlrs.to_le_bytes());
        b[104] = self.point_format;
        b[105..107].copy_from_slice(&self.point_record_length.to_le_bytes());
        // 107..131: legacy number of points and points by return: zero for PDRF >= 6.
        let mut at = 131;
        for v in self.scale.iter().chain(&self.offset).chain(
            [
                self.max[0],
                self.min[0],
                self.max[1],
                self.min[1],
                self.max[2],
                self.min[2],
            ]
            .iter(),
        ) {
            b[at..at + 8].copy_from_slice(&v.to_le_bytes());
            at += 8;
        }
        debug_assert_eq!(at, 227);
        b[227..235].copy_from_slice(&self.start_of_waveform_data.to_le_bytes());
        b[235..243].copy_from_slice(&self.start_of_first_evlr.to_le_bytes());
        b[243..247].copy_from_slice(&self.number_of_evlrs.to_le_bytes());
        b[247..255].copy_from_slice(&self.number_of_points.to_le_bytes());
        for (i, n) in self.points_by_return.iter().enumerate() {
            b[255 + 8 * i..263 + 8 * i].copy_from_slice(&n.to_le_bytes());
        }
        b
    }
}

/// A VLR header (54 bytes): `user_id` (16 bytes), `record_id`, payload length, description.
pub fn vlr_header(
    user_id: &str,
    record_id: u16,
    payload_len: usize,
    description: &str,
) -> Result<[u8; VLR_HEADER_SIZE], LasWriteError> {
    let len = u16::try_from(payload_len).map_err(|_| LasWriteError::VlrTooLong {
        what: "a VLR payload",
        len: payload_len,
    })?;
    let mut b = [0u8; VLR_HEADER_SIZE];
    put_str(&mut b[2..18], user_id);
    b[18..20].copy_from_slice(&record_id.to_le_bytes());
    b[20..22].copy_from_slice(&len.to_le_bytes());
    put_str(&mut b[22..54], description);
    Ok(b)
}

/// An EVLR header (60 bytes): as a VLR header with a 64-bit payload length.
pub fn evlr_header(
    user_id: &str,
    record_id: u16,
    payload_len: u64,
    description: &str,
) -> [u8; EVLR_HEADER_SIZE] {
    let mut b = [0u8; EVLR_HEADER_SIZE];
    put_str(&mut b[2..18], user_id);
    b[18..20].copy_from_slice(&record_id.to_le_bytes());
    b[20..28].copy_from_slice(&payload_len.to_le_bytes());
    put_str(&mut b[28..60], description);
    b
}

/// A waveform packet descriptor (the payload of VLR `LASF_Spec` / 99 + index).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WavePacketDescriptor {
    /// Bits per sample (8 or 16 here).
    pub bits_per_sample: u8,
    /// Compression type: 0, none (the only one defined).
    pub compression: u8,
    /// Samples per packet.
    pub number_of_samples: u32,
    /// Time between samples, picoseconds.
    pub temporal_spacing_ps: u32,
    /// Volts per count: `volts = offset + gain · count`.
    pub digitizer_gain: f64,
    /// Volts at count 0.
    pub digitizer_offset: f64,
}

impl WavePacketDescriptor {
    /// Encodes the 26-byte payload.
    pub fn encode(&self) -> [u8; DESCRIPTOR_SIZE] {
        let mut b = [0u8; DESCRIPTOR_SIZE];
        b[0] = self.bits_per_sample;
        b[1] = self.compression;
        b[2..6].copy_from_slice(&self.number_of_samples.to_le_bytes());
        b[6..10].copy_from_slice(&self.temporal_spacing_ps.to_le_bytes());
        b[10..18].copy_from_slice(&self.digitizer_gain.to_le_bytes());
        b[18..26].copy_from_slice(&self.digitizer_offset.to_le_bytes());
        b
    }

    /// Bytes of one uncompressed packet.
    pub fn packet_size(&self) -> u32 {
        self.number_of_samples * u32::from(self.bits_per_sample).div_ceil(8)
    }
}

/// Extra Bytes `data_type` of a 4-byte float.
pub const EXTRA_BYTES_F32: u8 = 9;
/// Extra Bytes data type of a 4-byte signed integer ("long").
pub const EXTRA_BYTES_I32: u8 = 6;
/// Extra Bytes `data_type` of an 8-byte float.
pub const EXTRA_BYTES_F64: u8 = 10;
/// Extra Bytes options bit 0: the `no_data` field is meaningful.
pub const EXTRA_BYTES_OPTION_NO_DATA: u8 = 1 << 0;
/// The value fwlidar writes for "no data" in its floating-point extra bytes (declared in each
/// descriptor's `no_data` field with option bit 0 when the dimension can lack a value).
pub const EXTRA_BYTES_NO_DATA: f64 = -9999.0;

/// One Extra Bytes descriptor (192 bytes) of a plain (unscaled, no no-data) value.
pub fn extra_bytes_descriptor(
    data_type: u8,
    name: &str,
    description: &str,
) -> [u8; EXTRA_BYTES_DESCRIPTOR_SIZE] {
    ExtraDim {
        name: name.to_string(),
        description: description.to_string(),
        kind: if data_type == EXTRA_BYTES_F64 {
            ExtraKind::F64
        } else {
            ExtraKind::F32
        },
        no_data: None,
    }
    .descriptor()
}

/// Storage type of an extra dimension fwlidar writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExtraKind {
    /// 4-byte IEEE float (Extra Bytes data type 9).
    F32,
    /// 8-byte IEEE float (data type 10).
    F64,
    /// 4-byte signed integer (data type 6), e.g. a cluster number.
    I32,
}

impl ExtraKind {
    /// Bytes per value.
    pub fn size(self) -> usize {
        match self {
            ExtraKind::F32 | ExtraKind::I32 => 4,
            ExtraKind::F64 => 8,
        }
    }
    /// The Extra Bytes `data_type` code.
    pub fn data_type(self) -> u8 {
        match self {
            ExtraKind::F32 => EXTRA_BYTES_F32,
            ExtraKind::F64 => EXTRA_BYTES_F64,
            ExtraKind::I32 => EXTRA_BYTES_I32,
        }
    }
}

/// One extra dimension appended to every point record, declared by an Extra Bytes descriptor
/// (VLR `LASF_Spec` / 4).
#[derive(Clone, Debug, PartialEq)]
pub struct ExtraDim {
    /// Name (at most 32 bytes), e.g. `amplitude`.
    pub name: String,
    /// Description with its unit (at most 32 bytes), e.g. `Gaussian peak amplitude (V)`.
    pub description: String,
    /// Storage type.
    pub kind: ExtraKind,
    /// The value written in place of a missing one (NaN), declared with options bit 0; `None`:
    /// the dimension always has a value (NaN is written as NaN).
    pub no_data: Option<f64>,
}

impl ExtraDim {
    /// A 4-byte float dimension without no-data.
    pub fn f32(name: &str, description: &str) -> Self {
        ExtraDim {
            name: name.to_string(),
            description: description.to_string(),
            kind: ExtraKind::F32,
            no_data: None,
        }
    }

    /// A 4-byte signed integer dimension (values are rounded toward zero; NaN is written 0).
    pub fn i32(name: &str, description: &str) -> Self {
        ExtraDim {
            name: name.to_string(),
            description: description.to_string(),
            kind: ExtraKind::I32,
            no_data: None,
        }
    }

    /// The same with a declared no-data value ([`EXTRA_BYTES_NO_DATA`]) written for NaN.
    pub fn with_no_data(mut self) -> Self {
        self.no_data = Some(EXTRA_BYTES_NO_DATA);
        self
    }

    /// The 192-byte descriptor: data type at 2, options at 3, name at 4, no_data at 40 (as the
    /// data type's "anytype": a double for floats), description at 160.
    pub fn descriptor(&self) -> [u8; EXTRA_BYTES_DESCRIPTOR_SIZE] {
        let mut b = [0u8; EXTRA_BYTES_DESCRIPTOR_SIZE];
        b[2] = self.kind.data_type();
        if let Some(v) = self.no_data {
            b[3] = EXTRA_BYTES_OPTION_NO_DATA;
            b[40..48].copy_from_slice(&v.to_le_bytes());
        }
        put_str(&mut b[4..36], &self.name);
        put_str(&mut b[160..192], &self.description);
        b
    }

    /// Encodes `v` into the first [`ExtraKind::size`] bytes of `b` (the no-data value for NaN
    /// when one is declared).
    pub fn encode_into(&self, v: f64, b: &mut [u8]) {
        let v = match self.no_data {
            Some(nd) if v.is_nan() => nd,
            _ => v,
        };
        match self.kind {
            ExtraKind::F32 => b[..4].copy_from_slice(&(v as f32).to_le_bytes()),
            ExtraKind::F64 => b[..8].copy_from_slice(&v.to_le_bytes()),
            ExtraKind::I32 => b[..4].copy_from_slice(&(v as i32).to_le_bytes()),
        }
    }
}

/// Bytes per point of `dims`.
pub fn extra_bytes_len(dims: &[ExtraDim]) -> usize {
    dims.iter().map(|d| d.kind.size()).sum()
}

/// Encodes `values` (one per dimension, in order) into `b`, which holds at least
/// [`extra_bytes_len`] bytes.
pub fn encode_extras(dims: &[ExtraDim], values: &[f64], b: &mut [u8]) {
    let mut at = 0;
    for (d, &v) in dims.iter().zip(values) {
        d.encode_into(v, &mut b[at..]);
        at += d.kind.size();
    }
}

/// The Extra Bytes VLR (header and payload) declaring `dims`; empty when `dims` is.
pub fn extra_bytes_vlr(dims: &[ExtraDim], description: &str) -> Result<Vec<u8>, LasWriteError> {
    if dims.is_empty() {
        return Ok(Vec::new());
    }
    for d in dims {
        if d.name.is_empty() || d.name.len() > 32 || d.description.len() > 32 {
            return Err(LasWriteError::Unrepresentable(format!(
                "extra dimension {:?}: the name must be 1 to 32 bytes and the description at \
                 most 32",
                d.name
            )));
        }
    }
    let len = dims.len() * EXTRA_BYTES_DESCRIPTOR_SIZE;
    let mut b = vlr_header(LASF_SPEC, EXTRA_BYTES_RECORD_ID, len, description)?.to_vec();
    for d in dims {
        b.extend_from_slice(&d.descriptor());
    }
    Ok(b)
}

/// The OGC WKT coordinate system VLR (`LASF_Projection` / 2112, NUL-terminated payload).
pub fn wkt_vlr(wkt: &str) -> Result<Vec<u8>, LasWriteError> {
    if wkt.as_bytes().contains(&0) {
        return Err(LasWriteError::Unrepresentable(
            "the CRS WKT contains a NUL byte".into(),
        ));
    }
    let mut b = vlr_header(LASF_PROJECTION, WKT_RECORD_ID, wkt.len() + 1, "OGC WKT CRS")?.to_vec();
    b.extend_from_slice(wkt.as_bytes());
    b.push(0);
    Ok(b)
}

/// Size of a point data record format 6, bytes.
pub const PF6_SIZE: usize = 30;

/// One point data record of format 6 (the fields fwlidar fills); also the first 30 bytes of
/// formats 7 to 10.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PointRecord6 {
    /// X, Y, Z as stored (scaled integers).
    pub xyz: [i32; 3],
    /// Intensity (16-bit normalised).
    pub intensity: u16,
    /// Return number, 1..=15.
    pub return_number: u8,
    /// Number of returns of the pulse, 1..=15.
    pub number_of_returns: u8,
    /// Scanner channel, 0..=3.
    pub scanner_channel: u8,
    /// Classification (0: never classified).
    pub classification: u8,
    /// Scan angle, units of 0.006°.
    pub scan_angle: i16,
    /// GPS time, s.
    pub gps_time: f64,
}

impl PointRecord6 {
    /// Encodes the record into the first [`PF6_SIZE`] bytes of `b` (scan direction, edge of
    /// flight line, classification flags, user data and point source id are zero).
    pub fn encode_into(&self, b: &mut [u8]) {
        let b = &mut b[..PF6_SIZE];
        b[0..4].copy_from_slice(&self.xyz[0].to_le_bytes());
        b[4..8].copy_from_slice(&self.xyz[1].to_le_bytes());
        b[8..12].copy_from_slice(&self.xyz[2].to_le_bytes());
        b[12..14].copy_from_slice(&self.intensity.to_le_bytes());
        b[14] = (self.return_number & 0x0f) | ((self.number_of_returns & 0x0f) << 4);
        b[15] = (self.scanner_channel & 0x03) << 4;
        b[16] = self.classification;
        b[17] = 0;
        b[18..20].copy_from_slice(&self.scan_angle.to_le_bytes());
        b[20..22].copy_from_slice(&0u16.to_le_bytes());
        b[22..30].copy_from_slice(&self.gps_time.to_le_bytes());
    }
}

/// One point data record of format 9 (the fields fwlidar fills): the format 6 record and the
/// wave packet fields.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PointRecord9 {
    /// The first 30 bytes, shared with format 6.
    pub core: PointRecord6,
    /// Wave packet descriptor index (0: no waveform).
    pub wave_packet_index: u8,
    /// Byte offset of the packet in the waveform data (the `.wdp` file, from its start).
    pub wave_offset: u64,
    /// Packet size, bytes.
    pub wave_size: u32,
    /// Return point waveform location, ps.
    pub wave_location_ps: f32,
    /// Parametric line `x(t), y(t), z(t)`, CRS units per ps.
    pub xyz_t: [f32; 3],
}

impl PointRecord9 {
    /// Encodes the record into the first [`PF9_SIZE`] bytes of `b` (scan direction, edge of
    /// flight line, classification flags, user data and point source id are zero).
    pub fn encode_into(&self, b: &mut [u8]) {
        let b = &mut b[..PF9_SIZE];
        self.core.encode_into(b);
        b[30] = self.wave_packet_index;
        b[31..39].copy_from_slice(&self.wave_offset.to_le_bytes());
        b[39..43].copy_from_slice(&self.wave_size.to_le_bytes());
        b[43..47].copy_from_slice(&self.wave_location_ps.to_le_bytes());
        b[47..51].copy_from_slice(&self.xyz_t[0].to_le_bytes());
        b[51..55].copy_from_slice(&self.xyz_t[1].to_le_bytes());
        b[55..59].copy_from_slice(&self.xyz_t[2].to_le_bytes());
    }
}

/// (year, day of year with January 1 = 1) of a time given in seconds since the Unix epoch (GMT).
pub fn year_and_day(unix_s: u64) -> (u16, u16) {
    let mut days = unix_s / 86_400;
    let mut year = 1970u64;
    loop {
        let leap =
            (year.is_multiple_of(4) && !year.is_multiple_of(100)) || year.is_multiple_of(400);
        let len = if leap { 366 } else { 365 };
        if days < len {
            return (year.min(u64::from(u16::MAX)) as u16, days as u16 + 1);
        }
        days -= len;
        year += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_fields_at_their_offsets() {
        let h = Header {
            global_encoding: GLOBAL_WAVEFORM_EXTERNAL | GLOBAL_WKT,
            system_identifier: "OTHER".into(),
            generating_software: "fwlidar 0.1.0".into(),
            creation_day_of_year: 326,
            creation_year: 2026,
            offset_to_point_data: 1000,
            number_of_vlrs: 3,
            point_format: 9,
            point_record_length: 67,
            scale: [0.001; 3],
            offset: [500_000.0, 4_000_000.0, 0.0],
            max: [1.0, 2.0, 3.0],
            min: [-1.0, -2.0, -3.0],
            start_of_waveform_data: 0,
            start_of_first_evlr: 0,
            number_of_evlrs: 0,
            number_of_points: 7,
            points_by_return: [4, 2, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
        };
        let b = h.encode();
        let u16_at = |o: usize| u16::from_le_bytes([b[o], b[o + 1]]);
        let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        let u64_at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().unwrap());
        let f64_at = |o: usize| f64::from_le_bytes(b[o..o + 8].try_into().unwrap());
        assert_eq!(&b[0..4], b"LASF");
        assert_eq!(u16_at(6), 0b10100);
        assert_eq!((b[24], b[25]), (1, 4));
        assert_eq!(&b[26..31], b"OTHER");
        assert!(b[31..58].iter().all(|&c| c == 0));
        assert_eq!(u16_at(90), 326);
        assert_eq!(u16_at(92), 2026);
        assert_eq!(u16_at(94), 375);
        assert_eq!(u32_at(96), 1000);
        assert_eq!(u32_at(100), 3);
        assert_eq!(b[104], 9);
        assert_eq!(u16_at(105), 67);
        assert!(b[107..131].iter().all(|&c| c == 0), "legacy counts zero");
        assert_eq!(f64_at(131), 0.001);
        assert_eq!(f64_at(155), 500_000.0);
        assert_eq!(f64_at(163), 4_000_000.0);
        assert_eq!(f64_at(179), 1.0); // max x
        assert_eq!(f64_at(187), -1.0); // min x
        assert_eq!(f64_at(211), 3.0); // max z
        assert_eq!(f64_at(219), -3.0); // min z
        assert_eq!(u64_at(247), 7);
        assert_eq!(u64_at(255), 4);
        assert_eq!(u64_at(263), 2);
        assert_eq!(u64_at(271), 1);
        assert_eq!(u64_at(367), 0);
    }

    #[test]
    fn record_headers_and_descriptor() {
        let v = vlr_header(LASF_SPEC, 100, 26, "waveform").unwrap();
        assert_eq!(&v[2..11], b"LASF_Spec");
        assert_eq!(u16::from_le_bytes([v[18], v[19]]), 100);
        assert_eq!(u16::from_le_bytes([v[20], v[21]]), 26);
        assert_eq!(
            vlr_header(LASF_SPEC, 1, 70_000, ""),
            Err(LasWriteError::VlrTooLong {
                what: "a VLR payload",
                len: 70_000
            })
        );
        let e = evlr_header(LASF_SPEC, WAVEFORM_DATA_RECORD_ID, 1 << 40, "x");
        assert_eq!(u16::from_le_bytes([e[18], e[19]]), 65535);
        assert_eq!(u64::from_le_bytes(e[20..28].try_into().unwrap()), 1 << 40);
        assert_eq!(e[28], b'x');
        let d = WavePacketDescriptor {
            bits_per_sample: 16,
            compression: 0,
            number_of_samples: 300,
            temporal_spacing_ps: 1000,
            digitizer_gain: 0.5,
            digitizer_offset: -1.0,
        };
        assert_eq!(d.packet_size(), 600);
        let b = d.encode();
        assert_eq!(b[0], 16);
        assert_eq!(u32::from_le_bytes(b[2..6].try_into().unwrap()), 300);
        assert_eq!(u32::from_le_bytes(b[6..10].try_into().unwrap()), 1000);
        assert_eq!(f64::from_le_bytes(b[10..18].try_into().unwrap()), 0.5);
        assert_eq!(f64::from_le_bytes(b[18..26].try_into().unwrap()), -1.0);
        let x = extra_bytes_descriptor(EXTRA_BYTES_F32, "amplitude_v", "peak");
        assert_eq!((x[2], &x[4..15]), (9, &b"amplitude_v"[..]));
        assert_eq!(&x[160..164], b"peak");
    }

    #[test]
    fn point_record_layout() {
        let p = PointRecord9 {
            core: PointRecord6 {
                xyz: [1, -2, 3],
                intensity: 513,
                return_number: 2,
                number_of_returns: 3,
                scanner_channel: 1,
                classification: 0,
                scan_angle: -5,
                gps_time: 12.5,
            },
            wave_packet_index: 4,
            wave_offset: 60,
            wave_size: 600,
            wave_location_ps: 1500.0,
            xyz_t: [0.25, -0.5, 1.0],
        };
        let mut b = [0xAAu8; PF9_SIZE + 8];
        p.encode_into(&mut b);
        assert_eq!(i32::from_le_bytes(b[4..8].try_into().unwrap()), -2);
        assert_eq!(b[14], 0x32);
        assert_eq!(b[15], 0x10);
        assert_eq!(i16::from_le_bytes([b[18], b[19]]), -5);
        assert_eq!(f64::from_le_bytes(b[22..30].try_into().unwrap()), 12.5);
        assert_eq!(b[30], 4);
        assert_eq!(u64::from_le_bytes(b[31..39].try_into().unwrap()), 60);
        assert_eq!(u32::from_le_bytes(b[39..43].try_into().unwrap()), 600);
        assert_eq!(f32::from_le_bytes(b[43..47].try_into().unwrap()), 1500.0);
        assert_eq!(f32::from_le_bytes(b[55..59].try_into().unwrap()), 1.0);
        assert_eq!(b[59], 0xAA, "extra bytes untouched");
    }

    #[test]
    fn creation_date() {
        assert_eq!(year_and_day(0), (1970, 1));
        // 2024-03-01 00:00 UTC = 1709251200 (2024 is a leap year: day 61).
        assert_eq!(year_and_day(1_709_251_200), (2024, 61));
        // 2023-12-31 12:00 UTC.
        assert_eq!(year_and_day(1_704_024_000), (2023, 365));
    }
}
