//! Sensor profiles: the description of a LiDAR system (laser, digitizer, scanner, mounting) that
//! every capture carries in its header and that the stages read their physics from.
//!
//! A profile file is a TOML document with one `[sensor]` table; see `config/sensors/`.

use serde::{Deserialize, Serialize};

use super::validate::{Validate, Validator, field, index};

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
    /// System constant C of the radiometric calibration (`calibrate` stage,
    /// `docs/calibration.md`): calibrated backscatter = C × volts × (R / R_ref)² / (E / E_ref).
    /// Its unit is the calibrated unit per volt (e.g. per volt for a reflectance-like, unitless
    /// result, from a flight over a target of known reflectance); the default 1 leaves the
    /// result in volts at the reference range and energy. Left out of the capture header when
    /// it is 1, so captures stay readable by earlier versions.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub calibration_constant: f64,
}

fn one() -> f64 {
    1.0
}

fn is_one(x: &f64) -> bool {
    *x == 1.0
}

impl SensorProfile {
    /// Footprint diameter at `range_m`, metres (small-angle: range × divergence).
    pub fn footprint_m(&self, range_m: f64) -> f64 {
        range_m * self.beam_divergence_mrad * 1e-3
    }
}

impl Validate for SensorFile {
    fn validate(&self, path: &str, v: &mut Validator) {
        self.sensor.validate(&field(path, "sensor"), v);
    }
}

impl Validate for SensorProfile {
    fn validate(&self, path: &str, v: &mut Validator) {
        let at = |name: &str| field(path, name);
        v.require(
            !self.name.trim().is_empty(),
            at("name"),
            "must not be empty",
        );
        v.positive(self.wavelength_nm, at("wavelength_nm"));
        v.positive(self.pulse_fwhm_ns, at("pulse_fwhm_ns"));
        v.positive(self.pulse_rate_hz, at("pulse_rate_hz"));
        v.positive(self.beam_divergence_mrad, at("beam_divergence_mrad"));
        v.positive(self.sample_interval_ns, at("sample_interval_ns"));
        v.require(
            matches!(self.bits_per_sample, 8 | 16),
            at("bits_per_sample"),
            format!("must be 8 or 16, got {}", self.bits_per_sample),
        );
        v.require(
            self.digitizer_gain_v_per_dn.is_finite() && self.digitizer_gain_v_per_dn != 0.0,
            at("digitizer_gain_v_per_dn"),
            format!(
                "must be a finite, non-zero number, got {}",
                self.digitizer_gain_v_per_dn
            ),
        );
        v.require(
            self.digitizer_offset_v.is_finite(),
            at("digitizer_offset_v"),
            format!("must be finite, got {}", self.digitizer_offset_v),
        );
        if let Some(noise) = self.noise_level_dn {
            v.require(
                noise.is_finite() && noise >= 0.0,
                at("noise_level_dn"),
                format!("must be zero or positive, got {noise}"),
            );
        }
        if let Some(h) = self.nominal_altitude_m {
            v.positive(h, at("nominal_altitude_m"));
        }
        if let Some(a) = self.max_scan_angle_deg {
            v.require(
                (0.0..90.0).contains(&a),
                at("max_scan_angle_deg"),
                format!("must be in [0, 90) degrees off nadir, got {a}"),
            );
        }
        v.require(
            self.calibration_constant.is_finite() && self.calibration_constant > 0.0,
            at("calibration_constant"),
            format!(
                "must be a positive finite number (calibrated units per volt), got {}",
                self.calibration_constant
            ),
        );
        for (name, values) in [
            ("lever_arm_m", self.lever_arm_m),
            ("boresight_deg", self.boresight_deg),
        ] {
            for (i, x) in values.iter().enumerate() {
                v.require(
                    x.is_finite(),
                    index(&at(name), i),
                    format!("must be finite, got {x}"),
                );
            }
        }
    }
}
/// A CAO-like inline sensor (the real profile file is maintained elsewhere): 16 ns FWHM,
/// 1 ns sampling, 8-bit, 50 kHz.
#[cfg(test)]
pub(crate) fn test_sensor() -> SensorProfile {
    SensorProfile {
        name: "test sensor (CAO-like)".into(),
        wavelength_nm: 1064.0,
        pulse_fwhm_ns: 16.0,
        pulse_rate_hz: 50_000.0,
        beam_divergence_mrad: 0.56,
        sample_interval_ns: 1.0,
        bits_per_sample: 8,
        digitizer_gain_v_per_dn: 1.0,
        digitizer_offset_v: 0.0,
        noise_level_dn: Some(11.0),
        nominal_altitude_m: Some(1000.0),
        max_scan_angle_deg: None,
        lever_arm_m: [0.1, 0.0, -0.2],
        boresight_deg: [0.0; 3],
        calibration_constant: 1.0,
    }
}
