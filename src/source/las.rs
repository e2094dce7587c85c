//! LAS 1.3 / 1.4 files (plain or LAZ-compressed) with waveform packets as a [`Source`]: one
//! pulse per waveform packet (the consecutive points that name it are its returns), read by
//! [`crate::format::las_read::LasReader`]. Pulses carry their geometry (anchor at the first
//! sample, direction per ns), so they need no navigation.

use std::fs::File;
use std::path::Path;

use crate::core::facts::SourceFacts;
use crate::format::las_read::{LasReadError, LasReader, WaveformLocation};
use crate::pipeline::ports::{Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;

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

impl Source for LasSource {
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

    fn report(&self) -> serde_json::Value {
        let info = self.reader.info();
        let mut v = serde_json::to_value(self.reader.stats()).unwrap_or_default();
        if let Some(o) = v.as_object_mut() {
            o.insert(
                "version".into(),
                format!("{}.{}", info.version.0, info.version.1).into(),
            );
            o.insert("point_format".into(), info.header.point_format.into());
            let compression = if self.reader.is_laz() { "laz" } else { "none" };
            o.insert("compression".into(), compression.into());
            o.insert(
                "points_in_header".into(),
                info.header.number_of_points.into(),
            );
            o.insert(
                "descriptors".into(),
                (info.descriptors_defined() as u64).into(),
            );
            let defined = info
                .descriptors
                .iter()
                .enumerate()
                .filter_map(|(index, d)| {
                    let d = d.as_ref()?;
                    let w = &d.descriptor;
                    Some(serde_json::json!({
                        "index": index,
                        "bits_per_sample": w.bits_per_sample,
                        "compression": w.compression,
                        "samples": w.number_of_samples,
                        "temporal_spacing_ps": w.temporal_spacing_ps,
                        "digitizer_gain": w.digitizer_gain,
                        "digitizer_offset": w.digitizer_offset,
                        "payload_bytes": d.payload_len,
                    }))
                });
            o.insert(
                "wave_packet_descriptors".into(),
                defined.collect::<Vec<_>>().into(),
            );
            let location = match info.waveform {
                WaveformLocation::External => "external",
                WaveformLocation::Internal { .. } => "internal",
                WaveformLocation::Absent => "absent",
            };
            o.insert("waveform_data".into(), location.into());
        }
        v
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
