//! LAS 1.3 / 1.4 files (plain or LAZ-compressed) with waveform packets as a [`Source`]: one
//! pulse per waveform packet (the consecutive points that name it are its returns), read by
//! [`crate::format::las_read::LasReader`]. Pulses carry their geometry (anchor at the first
//! sample, direction per ns), so they need no navigation.

use std::fs::File;
use std::path::Path;

use crate::core::facts::SourceFacts;
use crate::format::las_read::{LasReadError, LasReadStats, LasReader, WaveformLocation};
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;
use crate::source::report::{InputReport, SourceReport};

/// Reads a LAS or LAZ file (and its `.wdp`) as a [`Source`].
pub struct LasSource {
    reader: LasReader<File, File>,
}

impl LasSource {
    /// Opens `path` (LAS or LAZ) and its waveform data. Errors name the file and the field at
    /// fault; a missing `.wdp` names the paths looked for, a `.wdz` the command that decompresses
    /// it.
    pub fn open(path: &Path) -> Result<Self, LasReadError> {
        let reader = LasReader::open(path)?;
        let info = reader.info();
        tracing::info!(
            file = %info.file,
            version = %format!("{}.{}", info.version.0, info.version.1),
            point_format = info.header.point_format,
            laz = reader.is_laz(),
            points = info.header.number_of_points,
            descriptors = info.descriptors_defined(),
            "LAS input"
        );
        Ok(LasSource { reader })
    }

    /// The reader (header, descriptors, counts).
    pub fn reader(&self) -> &LasReader<File, File> {
        &self.reader
    }
}

/// A LAS source's report (`summary.json` → `source`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct LasReport {
    /// What was read.
    #[serde(flatten)]
    pub stats: LasReadStats,
    /// LAS version, `major.minor`.
    pub version: String,
    /// Point data record format.
    pub point_format: u8,
    /// `laz` or `none`.
    pub compression: &'static str,
    /// Points the header states.
    pub points_in_header: u64,
    /// Wave packet descriptors defined.
    pub descriptors: u64,
    /// The defined descriptors.
    pub wave_packet_descriptors: Vec<WavePacketDescriptorReport>,
    /// Where the waveforms are: `external` (`.wdp`), `internal` or `absent`.
    pub waveform_data: &'static str,
}

/// One wave packet descriptor as the report shows it.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct WavePacketDescriptorReport {
    /// Its index (1..=255).
    pub index: usize,
    /// Bits per sample.
    pub bits_per_sample: u8,
    /// Compression type (0: none).
    pub compression: u8,
    /// Samples per waveform.
    pub samples: u32,
    /// Sample spacing, ps.
    pub temporal_spacing_ps: u32,
    /// Volts per count.
    pub digitizer_gain: f64,
    /// Volts at count 0.
    pub digitizer_offset: f64,
    /// Bytes of the descriptor's record payload.
    pub payload_bytes: u64,
}

impl Source for LasSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        "las"
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        crate::source::next_pooled(pool, |p| self.reader.next_pulse(p)).map_err(SourceError::Fatal)
    }

    /// Bytes of the LAS file (header, VLRs, point records) covered.
    fn progress(&self) -> Option<(u64, u64)> {
        Some(self.reader.progress())
    }

    fn report(&self) -> SourceReport {
        let info = self.reader.info();
        let wave_packet_descriptors = info
            .descriptors
            .iter()
            .enumerate()
            .filter_map(|(index, d)| {
                let d = d.as_ref()?;
                let w = &d.descriptor;
                Some(WavePacketDescriptorReport {
                    index,
                    bits_per_sample: w.bits_per_sample,
                    compression: w.compression,
                    samples: w.number_of_samples,
                    temporal_spacing_ps: w.temporal_spacing_ps,
                    digitizer_gain: w.digitizer_gain,
                    digitizer_offset: w.digitizer_offset,
                    payload_bytes: d.payload_len,
                })
            })
            .collect();
        SourceReport::of(InputReport::Las(Box::new(LasReport {
            stats: self.reader.stats().clone(),
            version: format!("{}.{}", info.version.0, info.version.1),
            point_format: info.header.point_format,
            compression: if self.reader.is_laz() { "laz" } else { "none" },
            points_in_header: info.header.number_of_points,
            descriptors: info.descriptors_defined() as u64,
            wave_packet_descriptors,
            waveform_data: match info.waveform {
                WaveformLocation::External => "external",
                WaveformLocation::Internal { .. } => "internal",
                WaveformLocation::Absent => "absent",
            },
        })))
    }

    fn facts(&self) -> SourceFacts {
        let info = self.reader.info();
        SourceFacts {
            sensor: None,
            time_base: Some(info.time_base().to_string()),
            crs: info.crs(),
            // The time axis starts at the first digitised sample, not at emission.
            t0_is_emission: Some(false),
        }
    }
}
