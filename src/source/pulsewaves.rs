//! A PulseWaves `.pls` + `.wvs` pair as a [`Source`]: every pulse record becomes a pooled pulse
//! with its geometry (anchor, direction) and its outgoing and returning segments as raw counts.

use std::fs::File;
use std::path::{Path, PathBuf};

use crate::core::facts::SourceFacts;
use crate::core::sensor::SensorProfile;
use crate::format::pulsewaves::{PulseWavesError, PulseWavesReader, waves_path_for};
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;

/// Reads a PulseWaves file pair as a [`Source`].
pub struct PulseWavesSource {
    reader: PulseWavesReader<File, File>,
    path: PathBuf,
    wvs_path: PathBuf,
    failed: Option<String>,
}

impl PulseWavesSource {
    /// Opens `pls` and the `.wvs` file beside it (same stem; `.wvs`, else `.WVS`).
    pub fn open(pls: &Path) -> Result<Self, PulseWavesError> {
        let wvs_path = waves_path_for(pls)?;
        let reader = PulseWavesReader::open(pls)?;
        Ok(PulseWavesSource {
            reader,
            path: pls.to_path_buf(),
            wvs_path,
            failed: None,
        })
    }

    /// The reader underneath (header, descriptors, scanners).
    pub fn reader(&self) -> &PulseWavesReader<File, File> {
        &self.reader
    }

    /// A complete sensor description from the scanner record of the first descriptor (or the
    /// first scanner), when it states wavelength, pulse width, pulse frequency and divergence.
    pub fn sensor(&self) -> Option<SensorProfile> {
        sensor_of(&self.reader)
    }
}

/// See [`PulseWavesSource::sensor`].
pub fn sensor_of<P, W>(reader: &PulseWavesReader<P, W>) -> Option<SensorProfile>
where
    P: std::io::Read + std::io::Seek,
    W: std::io::Read + std::io::Seek,
{
    let first = reader.descriptors().next()?;
    let scanners = reader.scanners();
    let scanner = scanners
        .iter()
        .find(|s| u32::from(s.index) == first.composition.scanner_index)
        .or_else(|| scanners.first())?;
    let positive = |v: f32| v.is_finite() && v > 0.0;
    if !(positive(scanner.wavelength_nm)
        && positive(scanner.outgoing_pulse_width_ns)
        && positive(scanner.pulse_frequency_khz)
        && positive(scanner.beam_divergence_mrad))
    {
        return None;
    }
    let max_angle = scanner
        .scan_angle_min_deg
        .abs()
        .max(scanner.scan_angle_max_deg.abs());
    Some(SensorProfile {
        name: scanner.name(),
        wavelength_nm: f64::from(scanner.wavelength_nm),
        pulse_fwhm_ns: f64::from(scanner.outgoing_pulse_width_ns),
        pulse_rate_hz: f64::from(scanner.pulse_frequency_khz) * 1e3,
        beam_divergence_mrad: f64::from(scanner.beam_divergence_mrad),
        sample_interval_ns: first.sample_ns(),
        bits_per_sample: first.bits(),
        digitizer_gain_v_per_dn: 1.0,
        digitizer_offset_v: 0.0,
        noise_level_dn: None,
        nominal_altitude_m: None,
        max_scan_angle_deg: (max_angle.is_finite() && max_angle > 0.0)
            .then_some(f64::from(max_angle)),
        lever_arm_m: [0.0; 3],
        boresight_deg: [0.0; 3],
        calibration_constant: 1.0,
    })
}

impl Source for PulseWavesSource {
    fn name(&self) -> &'static str {
        "pulsewaves"
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        crate::source::next_pooled(pool, |p| self.reader.read_pulse(p)).map_err(|msg| {
            self.failed = Some(msg.clone());
            SourceError::Fatal(msg)
        })
    }

    /// Pulses read of the pulses in the file.
    fn progress(&self) -> Option<(u64, u64)> {
        Some((self.reader.pulses_read(), self.reader.number_of_pulses()))
    }

    fn report(&self) -> serde_json::Value {
        let h = self.reader.header();
        let descriptors: Vec<serde_json::Value> = self
            .reader
            .descriptors()
            .map(|d| {
                serde_json::json!({
                    "index": d.index,
                    "description": d.composition.description,
                    "sample_units_ns": d.composition.sample_units_ns,
                    "scanner_index": d.composition.scanner_index,
                    "samplings": d.samplings.iter().map(|s| serde_json::json!({
                        "type": s.kind,
                        "channel": s.channel,
                        "bits_per_sample": s.bits_per_sample,
                        "segments": if s.bits_for_number_of_segments > 0 {
                            serde_json::Value::from("variable")
                        } else {
                            serde_json::Value::from(s.number_of_segments)
                        },
                        "samples": if s.bits_for_number_of_samples > 0 {
                            serde_json::Value::from("variable")
                        } else {
                            serde_json::Value::from(s.number_of_samples)
                        },
                        "sample_units_ns": s.sample_units_ns,
                        "lookup_table_index": s.lookup_table_index,
                        "description": s.description,
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        serde_json::json!({
            "file": self.path.display().to_string(),
            "waves_file": self.wvs_path.display().to_string(),
            "version": format!("{}.{}", h.version_major, h.version_minor),
            "system_identifier": h.system_identifier,
            "generating_software": h.generating_software,
            "pulses": self.reader.number_of_pulses(),
            "pulses_read": self.reader.pulses_read(),
            "wave_bytes_read": self.reader.wave_bytes_read(),
            "descriptors": descriptors,
            "scanners": self.reader.scanners(),
            "crs": self.reader.crs(),
            "time_base": self.reader.time_base().as_str(),
            "lookup_tables_not_applied": self.reader.lookup_tables(),
            "records_skipped": self.reader.skipped_records(),
            "warnings": self.reader.warnings(),
            "error": self.failed,
        })
    }

    fn facts(&self) -> SourceFacts {
        SourceFacts {
            sensor: self.sensor(),
            time_base: self.reader.time_base().as_str().map(str::to_string),
            crs: self.reader.crs().map(str::to_string),
            // t0 is the anchor, which the format lets lie anywhere on the beam.
            t0_is_emission: Some(false),
        }
    }
}
