//! A PulseWaves `.pls` + `.wvs` pair as a [`Source`]: every pulse record becomes a pooled pulse
//! with its geometry (anchor, direction) and its outgoing and returning segments as raw counts.

use crate::format::pulsewaves::{SamplingType, Scanner};
use crate::source::report::{InputReport, SourceReport};
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

/// A PulseWaves source's report (`summary.json` → `source`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct PulseWavesReport {
    /// The `.pls` file.
    pub file: String,
    /// The `.wvs` file.
    pub waves_file: String,
    /// Format version, `major.minor`.
    pub version: String,
    /// The header's system identifier.
    pub system_identifier: String,
    /// The header's generating software.
    pub generating_software: String,
    /// Pulses in the file.
    pub pulses: u64,
    /// Pulses read.
    pub pulses_read: u64,
    /// Bytes of waves read.
    pub wave_bytes_read: u64,
    /// The pulse descriptors (compositions and their samplings).
    pub descriptors: Vec<PulseDescriptorReport>,
    /// The scanner records.
    pub scanners: Vec<Scanner>,
    /// The CRS the file states (WKT or `EPSG:<code>`).
    pub crs: Option<String>,
    /// Time base of the GPS times, when stated.
    pub time_base: Option<&'static str>,
    /// Lookup tables present and not applied.
    pub lookup_tables_not_applied: u64,
    /// Pulse records skipped (damaged).
    pub records_skipped: u64,
    /// What was doubtful but not fatal.
    pub warnings: Vec<String>,
    /// The error that ended reading, if any.
    pub error: Option<String>,
}

/// One pulse descriptor as the report shows it.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PulseDescriptorReport {
    /// Its index.
    pub index: u8,
    /// Its description.
    pub description: String,
    /// Sample unit, ns.
    pub sample_units_ns: f32,
    /// The scanner it belongs to.
    pub scanner_index: u32,
    /// Its samplings.
    pub samplings: Vec<SamplingReport>,
}

/// One sampling of a pulse descriptor.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SamplingReport {
    /// What it records (`outgoing`, `returning`).
    #[serde(rename = "type")]
    pub kind: SamplingType,
    /// Receiver channel.
    pub channel: u8,
    /// Bits per sample.
    pub bits_per_sample: u16,
    /// Segments per wave, or `variable`.
    pub segments: SamplingCount,
    /// Samples per segment, or `variable`.
    pub samples: SamplingCount,
    /// Sample unit, ns.
    pub sample_units_ns: f32,
    /// Lookup table (0: none).
    pub lookup_table_index: u16,
    /// Its description.
    pub description: String,
}

/// A count a sampling fixes, or `"variable"` when each wave states its own.
#[derive(Clone, Copy, Debug, serde::Serialize)]
#[serde(untagged)]
pub enum SamplingCount {
    /// The same for every wave.
    Fixed(u64),
    /// Stated by each wave (`"variable"`).
    Variable(&'static str),
}

impl Source for PulseWavesSource {
    type Report = SourceReport;

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

    fn report(&self) -> SourceReport {
        let h = self.reader.header();
        let count = |bits: u8, n: u64| {
            if bits > 0 {
                SamplingCount::Variable("variable")
            } else {
                SamplingCount::Fixed(n)
            }
        };
        let descriptors = self
            .reader
            .descriptors()
            .map(|d| PulseDescriptorReport {
                index: d.index,
                description: d.composition.description.clone(),
                sample_units_ns: d.composition.sample_units_ns,
                scanner_index: d.composition.scanner_index,
                samplings: d
                    .samplings
                    .iter()
                    .map(|s| SamplingReport {
                        kind: s.kind,
                        channel: s.channel,
                        bits_per_sample: s.bits_per_sample,
                        segments: count(s.bits_for_number_of_segments, s.number_of_segments.into()),
                        samples: count(s.bits_for_number_of_samples, s.number_of_samples.into()),
                        sample_units_ns: s.sample_units_ns,
                        lookup_table_index: s.lookup_table_index,
                        description: s.description.clone(),
                    })
                    .collect(),
            })
            .collect();
        SourceReport::of(InputReport::PulseWaves(Box::new(PulseWavesReport {
            file: self.path.display().to_string(),
            waves_file: self.wvs_path.display().to_string(),
            version: format!("{}.{}", h.version_major, h.version_minor),
            system_identifier: h.system_identifier.clone(),
            generating_software: h.generating_software.clone(),
            pulses: self.reader.number_of_pulses(),
            pulses_read: self.reader.pulses_read(),
            wave_bytes_read: self.reader.wave_bytes_read(),
            descriptors,
            scanners: self.reader.scanners().to_vec(),
            crs: self.reader.crs().map(str::to_string),
            time_base: self.reader.time_base().as_str(),
            lookup_tables_not_applied: self.reader.lookup_tables(),
            records_skipped: self.reader.skipped_records(),
            warnings: self.reader.warnings().to_vec(),
            error: self.failed.clone(),
        })))
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
