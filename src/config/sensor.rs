//! Sensor profiles: the description of a LiDAR system (laser, digitizer, scanner, mounting) that
//! every capture carries in its header and that the stages read their physics from.
//!
//! A profile file is a TOML document with one `[sensor]` table; see `config/sensors/`.

use serde::{Deserialize, Serialize};

/// The top level of a sensor profile file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorFile {
    /// The sensor.
    pub sensor: SensorProfile,
}

/// A LiDAR system as flown.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorProfile {
    /// Human-readable name, e.g. "Optech ALTM 3100EA (Carnegie Airborne Observatory)".
    pub name: String,
    /// Laser wavelength, nanometres.
    pub wavelength_nm: f64,
    /// Outgoing pulse full width at half maximum, nanoseconds.
    pub pulse_fwhm_ns: f64,
    /// Pulse repetition rate, hertz.
    pub pulse_rate_hz: f64,
    /// Full-angle beam divergence (1/e²), milliradians.
    pub beam_divergence_mrad: f64,
    /// Digitizer sample interval, nanoseconds.
    pub sample_interval_ns: f64,
    /// Bits per digitized sample: 8 or 16.
    pub bits_per_sample: u8,
    /// Digitizer gain, volts per count (volts = offset + gain * counts). Default 1.
    #[serde(default = "one")]
    pub digitizer_gain_v_per_dn: f64,
    /// Digitizer offset, volts. Default 0.
    #[serde(default)]
    pub digitizer_offset_v: f64,
    /// Typical noise level of the recorded waveforms, counts (the seed shifted CAO data by
    /// 11 DN before filtering). Optional.
    #[serde(default)]
    pub noise_level_dn: Option<f64>,
    /// Nominal flying height above ground, metres (used to state the nominal footprint).
    #[serde(default)]
    pub nominal_altitude_m: Option<f64>,
    /// Maximum scan angle off nadir, degrees.
    #[serde(default)]
    pub max_scan_angle_deg: Option<f64>,
    /// Lever arm from the IMU reference point to the scanner origin in the body frame
    /// (x forward, y right, z down), metres. Default zero.
    #[serde(default)]
    pub lever_arm_m: [f64; 3],
    /// Boresight misalignment angles (roll, pitch, yaw) of the scanner relative to the IMU,
    /// degrees. Default zero.
    #[serde(default)]
    pub boresight_deg: [f64; 3],
}

fn one() -> f64 {
    1.0
}

impl SensorProfile {
    /// Footprint diameter at `range_m`, metres (small-angle: range × divergence).
    pub fn footprint_m(&self, range_m: f64) -> f64 {
        range_m * self.beam_divergence_mrad * 1e-3
    }
}
