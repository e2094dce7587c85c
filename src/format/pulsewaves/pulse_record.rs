//! The pulse record, format 0 (48 bytes; attributes and extra bytes may follow and are skipped).

use super::le;

/// Size of a format 0 pulse record without attributes, bytes.
pub const PULSE_RECORD_LEN: usize = 48;

/// One pulse record as stored (scale and offset not applied).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PulseRecord {
    /// GPS timestamp T, counts of the header's T scale.
    pub gps_timestamp: i64,
    /// Offset of the pulse's waves from the start of the `.wvs` file, bytes.
    pub offset_to_waves: i64,
    /// Anchor point `[X, Y, Z]`, counts of the header's coordinate scale.
    pub anchor: [i32; 3],
    /// Target point `[X, Y, Z]` (1000 sampling units from the anchor along the beam), counts.
    pub target: [i32; 3],
    /// Duration from the anchor to the first returning sample, sampling units.
    pub first_returning_sample: i16,
    /// Duration from the anchor to the last returning sample, sampling units.
    pub last_returning_sample: i16,
    /// Pulse descriptor index: the descriptor is record ID `200000 + index`.
    pub descriptor_index: u8,
    /// Edge of scan line flag (bit 12 of the 16-bit field).
    pub edge_of_scan_line: bool,
    /// Scan direction flag (bit 13).
    pub scan_direction: bool,
    /// Mirror facet (bits 14-15).
    pub mirror_facet: u8,
    /// Intensity, for previews (no physical unit).
    pub intensity: u8,
    /// Classification of the whole pulse.
    pub classification: u8,
}

impl PulseRecord {
    /// Decodes a record from its first [`PULSE_RECORD_LEN`] bytes (missing bytes read as zero;
    /// the reader passes whole records).
    #[inline]
    pub fn parse(b: &[u8]) -> PulseRecord {
        // Bits 0-7 descriptor index, 8-11 reserved, 12 edge of scan line, 13 scan direction,
        // 14-15 mirror facet.
        let bits = le::u16(b, 44);
        PulseRecord {
            gps_timestamp: le::i64(b, 0),
            offset_to_waves: le::i64(b, 8),
            anchor: [le::i32(b, 16), le::i32(b, 20), le::i32(b, 24)],
            target: [le::i32(b, 28), le::i32(b, 32), le::i32(b, 36)],
            first_returning_sample: le::i16(b, 40),
            last_returning_sample: le::i16(b, 42),
            descriptor_index: (bits & 0xff) as u8,
            edge_of_scan_line: bits & (1 << 12) != 0,
            scan_direction: bits & (1 << 13) != 0,
            mirror_facet: ((bits >> 14) & 3) as u8,
            intensity: le::u8(b, 46),
            classification: le::u8(b, 47),
        }
    }
}
