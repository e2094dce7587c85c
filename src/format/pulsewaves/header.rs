//! The `.pls` header (352 bytes in version 0.3) and the `.wvs` header (60 bytes).

use super::error::PulseWavesError;
use super::le;

/// Size of the `.pls` header in version 0.3, bytes.
pub const PLS_HEADER_LEN: usize = 352;
/// Size of the `.wvs` header, bytes.
pub const WVS_HEADER_LEN: usize = 60;
/// Signature of a `.pls` file.
pub const PLS_SIGNATURE: &[u8; 16] = b"PulseWavesPulse\0";
/// Signature of a `.wvs` file.
pub const WVS_SIGNATURE: &[u8; 16] = b"PulseWavesWaves\0";

/// The `.pls` header as stored (scale and offset not applied).
#[derive(Clone, Debug, PartialEq)]
pub struct PlsHeader {
    /// Global parameters bit field (no bit is defined by the 0.3 draft).
    pub global_parameters: u32,
    /// File source ID (flight line number).
    pub file_source_id: u32,
    /// System identifier (sensor or process), text.
    pub system_identifier: String,
    /// Generating software, text.
    pub generating_software: String,
    /// File creation day of year (1 = January 1).
    pub creation_day: u16,
    /// File creation year.
    pub creation_year: u16,
    /// Version major.
    pub version_major: u8,
    /// Version minor.
    pub version_minor: u8,
    /// Header size, bytes.
    pub header_size: u16,
    /// Offset from the start of the file to the first pulse record, bytes.
    pub offset_to_pulse_data: i64,
    /// Number of pulse records.
    pub number_of_pulses: i64,
    /// Pulse record format (0 is the only one defined).
    pub pulse_format: u32,
    /// Pulse attributes bit mask (bit 0: 16-bit pulse source ID, bit 1: 32-bit one).
    pub pulse_attributes: u32,
    /// Size of one pulse record, bytes.
    pub pulse_size: u32,
    /// Pulse compression (0 = none).
    pub pulse_compression: u32,
    /// Number of VLRs before the pulse records.
    pub number_of_vlrs: u32,
    /// Number of AVLRs after the pulse records (negative: unknown, walk them from the end).
    pub number_of_avlrs: i32,
    /// GPS time scale, seconds per count.
    pub t_scale: f64,
    /// GPS time offset, seconds.
    pub t_offset: f64,
    /// Smallest stored GPS timestamp, counts.
    pub min_t: i64,
    /// Largest stored GPS timestamp, counts.
    pub max_t: i64,
    /// Coordinate scale factors `[x, y, z]`, CRS units per count.
    pub scale: [f64; 3],
    /// Coordinate offsets `[x, y, z]`, CRS units.
    pub offset: [f64; 3],
    /// Bounding box `[min_x, max_x, min_y, max_y, min_z, max_z]`, CRS units.
    pub bounds: [f64; 6],
}

/// Bytes of pulse attributes that follow the 48-byte format 0 record for `attributes`.
pub fn attribute_bytes(attributes: u32) -> u32 {
    (if attributes & 1 != 0 { 2 } else { 0 }) + (if attributes & 2 != 0 { 4 } else { 0 })
}

impl PlsHeader {
    /// Decodes and checks the header of `file` (its first [`PLS_HEADER_LEN`] bytes; `file_len`
    /// is the whole file's length, bytes).
    pub fn parse(b: &[u8], file: &str, file_len: u64) -> Result<PlsHeader, PulseWavesError> {
        if b.len() < PLS_HEADER_LEN {
            return Err(PulseWavesError::truncated(
                file,
                "the .pls header",
                0,
                PLS_HEADER_LEN as u64,
                file_len,
            ));
        }
        check_signature(b, PLS_SIGNATURE, file, ".pls")?;
        let h = PlsHeader {
            global_parameters: le::u32(b, 16),
            file_source_id: le::u32(b, 20),
            system_identifier: le::text(b, 40, 64),
            generating_software: le::text(b, 104, 64),
            creation_day: le::u16(b, 168),
            creation_year: le::u16(b, 170),
            version_major: le::u8(b, 172),
            version_minor: le::u8(b, 173),
            header_size: le::u16(b, 174),
            offset_to_pulse_data: le::i64(b, 176),
            number_of_pulses: le::i64(b, 184),
            pulse_format: le::u32(b, 192),
            pulse_attributes: le::u32(b, 196),
            pulse_size: le::u32(b, 200),
            pulse_compression: le::u32(b, 204),
            number_of_vlrs: le::u32(b, 216),
            number_of_avlrs: le::i32(b, 220),
            t_scale: le::f64(b, 224),
            t_offset: le::f64(b, 232),
            min_t: le::i64(b, 240),
            max_t: le::i64(b, 248),
            scale: [le::f64(b, 256), le::f64(b, 264), le::f64(b, 272)],
            offset: [le::f64(b, 280), le::f64(b, 288), le::f64(b, 296)],
            bounds: [
                le::f64(b, 304),
                le::f64(b, 312),
                le::f64(b, 320),
                le::f64(b, 328),
                le::f64(b, 336),
                le::f64(b, 344),
            ],
        };
        h.check(file, file_len)?;
        Ok(h)
    }

    fn check(&self, file: &str, file_len: u64) -> Result<(), PulseWavesError> {
        let bad = |field: &str, reason: String| PulseWavesError::invalid(file, field, reason);
        if (self.header_size as usize) < PLS_HEADER_LEN {
            return Err(bad(
                "header_size",
                format!(
                    "{} bytes, less than the {PLS_HEADER_LEN} of version 0.3",
                    self.header_size
                ),
            ));
        }
        if self.offset_to_pulse_data < self.header_size as i64 {
            return Err(bad(
                "offset_to_pulse_data",
                format!(
                    "{} is inside the {}-byte header",
                    self.offset_to_pulse_data, self.header_size
                ),
            ));
        }
        if self.offset_to_pulse_data as u64 > file_len {
            return Err(PulseWavesError::truncated(
                file,
                "offset_to_pulse_data",
                self.header_size as u64,
                self.offset_to_pulse_data as u64,
                file_len,
            ));
        }
        if self.number_of_pulses < 0 {
            return Err(bad(
                "number_of_pulses",
                format!("{} is negative", self.number_of_pulses),
            ));
        }
        if self.pulse_format != 0 {
            return Err(PulseWavesError::unsupported(
                file,
                "pulse_format",
                format!("pulse format {}", self.pulse_format),
            ));
        }
        if self.pulse_compression != 0 {
            return Err(PulseWavesError::unsupported(
                file,
                "pulse_compression",
                format!(
                    "compressed pulse records (compression {})",
                    self.pulse_compression
                ),
            ));
        }
        let min_size = 48 + attribute_bytes(self.pulse_attributes);
        if self.pulse_size < min_size {
            return Err(bad(
                "pulse_size",
                format!(
                    "{} bytes, less than the {min_size} of format 0 with attributes {:#x}",
                    self.pulse_size, self.pulse_attributes
                ),
            ));
        }
        if !(self.t_scale.is_finite() && self.t_scale != 0.0 && self.t_offset.is_finite()) {
            return Err(bad(
                "t_scale_factor/t_offset",
                format!(
                    "{} / {} must be finite, the scale non-zero",
                    self.t_scale, self.t_offset
                ),
            ));
        }
        for (i, axis) in ["x", "y", "z"].iter().enumerate() {
            let (s, o) = (self.scale[i], self.offset[i]);
            if !(s.is_finite() && s != 0.0 && o.is_finite()) {
                return Err(bad(
                    &format!("{axis}_scale_factor/{axis}_offset"),
                    format!("{s} / {o} must be finite, the scale non-zero"),
                ));
            }
        }
        // The pulse table must lie inside the file: the count is untrusted.
        let table = (self.number_of_pulses as u64).checked_mul(self.pulse_size as u64);
        let end = table.and_then(|t| t.checked_add(self.offset_to_pulse_data as u64));
        match end {
            Some(end) if end <= file_len => Ok(()),
            _ => Err(PulseWavesError::truncated(
                file,
                format!(
                    "the pulse table (number_of_pulses {} × pulse_size {})",
                    self.number_of_pulses, self.pulse_size
                ),
                self.offset_to_pulse_data as u64,
                end.unwrap_or(u64::MAX),
                file_len,
            )),
        }
    }

    /// Offset of the first pulse record, bytes (checked non-negative by [`PlsHeader::parse`]).
    pub fn pulse_data_start(&self) -> u64 {
        self.offset_to_pulse_data.max(0) as u64
    }

    /// Number of pulse records (checked non-negative by [`PlsHeader::parse`]).
    #[inline]
    pub fn pulses(&self) -> u64 {
        self.number_of_pulses.max(0) as u64
    }

    /// One past the last byte of the pulse table.
    pub fn pulse_data_end(&self) -> u64 {
        self.pulse_data_start()
            .saturating_add(self.pulses().saturating_mul(self.pulse_size as u64))
    }
}

/// The `.wvs` header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WvsHeader {
    /// Compression of the waves (0 = none).
    pub compression: u32,
}

impl WvsHeader {
    /// Decodes and checks the header of `file`.
    pub fn parse(b: &[u8], file: &str, file_len: u64) -> Result<WvsHeader, PulseWavesError> {
        if b.len() < WVS_HEADER_LEN {
            return Err(PulseWavesError::truncated(
                file,
                "the .wvs header",
                0,
                WVS_HEADER_LEN as u64,
                file_len,
            ));
        }
        check_signature(b, WVS_SIGNATURE, file, ".wvs")?;
        let compression = le::u32(b, 16);
        if compression != 0 {
            return Err(PulseWavesError::unsupported(
                file,
                "compression",
                format!("compressed waves (compression {compression})"),
            ));
        }
        Ok(WvsHeader { compression })
    }
}

fn check_signature(
    b: &[u8],
    expected: &'static [u8; 16],
    file: &str,
    what: &'static str,
) -> Result<(), PulseWavesError> {
    let found = b.get(..16).unwrap_or(b);
    // The 15 letters decide; a writer may leave the terminating byte non-zero.
    if found.get(..15) == expected.get(..15) {
        return Ok(());
    }
    Err(PulseWavesError::Signature {
        file: file.to_string(),
        what,
        found: String::from_utf8_lossy(found).into_owned(),
        expected: if what == ".pls" {
            "PulseWavesPulse"
        } else {
            "PulseWavesWaves"
        },
    })
}
