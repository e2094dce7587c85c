//! Scanner records (`PulseWaves_Spec` records 100001..100255).

use serde::Serialize;

use super::error::PulseWavesError;
use super::le;

/// Bytes of a scanner record in version 0.3 (description included).
pub const SCANNER_LEN: u32 = 248;

/// A scanner record, units as the file states them.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Scanner {
    /// Index (record ID − 100000).
    pub index: u8,
    /// Instrument, text (e.g. `Q680i`).
    pub instrument: String,
    /// Serial number, text.
    pub serial: String,
    /// Laser wavelength, nm.
    pub wavelength_nm: f32,
    /// Outgoing pulse width (FWHM), ns. (The 0.3 draft says nanometres; the real files hold
    /// nanoseconds: 4 for the RIEGL Q680i, 10 for LVIS.)
    pub outgoing_pulse_width_ns: f32,
    /// Scan pattern: 0 undefined, 1 oscillating, 2 line, 3 conic.
    pub scan_pattern: u32,
    /// Number of mirror facets.
    pub number_of_mirror_facets: u32,
    /// Scan frequency, Hz.
    pub scan_frequency_hz: f32,
    /// Smallest scan angle, degrees.
    pub scan_angle_min_deg: f32,
    /// Largest scan angle, degrees.
    pub scan_angle_max_deg: f32,
    /// Pulse repetition frequency, kHz.
    pub pulse_frequency_khz: f32,
    /// Beam diameter at the exit aperture, mm.
    pub beam_diameter_at_exit_aperture_mm: f32,
    /// Beam divergence (1/e²), mrad.
    pub beam_divergence_mrad: f32,
    /// Minimal range, m.
    pub minimal_range_m: f32,
    /// Maximal range, m.
    pub maximal_range_m: f32,
    /// Description, text.
    pub description: String,
}

impl Scanner {
    /// Decodes the payload of record `100000 + index` of `file`.
    pub fn parse(payload: &[u8], index: u8, file: &str) -> Result<Scanner, PulseWavesError> {
        let size = le::u32(payload, 0);
        if size < SCANNER_LEN || size as usize > payload.len() {
            return Err(PulseWavesError::invalid(
                file,
                format!(
                    "scanner {index} (record {}): size",
                    100_000 + u32::from(index)
                ),
                format!(
                    "{size} bytes; must be at least {SCANNER_LEN} and fit the record's {} bytes",
                    payload.len()
                ),
            ));
        }
        Ok(Scanner {
            index,
            instrument: le::text(payload, 8, 64),
            serial: le::text(payload, 72, 64),
            wavelength_nm: le::f32(payload, 136),
            outgoing_pulse_width_ns: le::f32(payload, 140),
            scan_pattern: le::u32(payload, 144),
            number_of_mirror_facets: le::u32(payload, 148),
            scan_frequency_hz: le::f32(payload, 152),
            scan_angle_min_deg: le::f32(payload, 156),
            scan_angle_max_deg: le::f32(payload, 160),
            pulse_frequency_khz: le::f32(payload, 164),
            beam_diameter_at_exit_aperture_mm: le::f32(payload, 168),
            beam_divergence_mrad: le::f32(payload, 172),
            minimal_range_m: le::f32(payload, 176),
            maximal_range_m: le::f32(payload, 180),
            description: le::text(payload, size as usize - 64, 64),
        })
    }

    /// A name for the sensor: instrument, serial and description as far as given.
    pub fn name(&self) -> String {
        let mut name = if self.instrument.is_empty() {
            format!("PulseWaves scanner {}", self.index)
        } else {
            self.instrument.clone()
        };
        if !self.serial.is_empty() {
            name.push_str(&format!(" (serial {})", self.serial));
        }
        name
    }
}
