//! Replay of a recorded capture: digitizer frames become pooled pulses, navigation records go
//! to the navigation consumer as the very bytes that came off the port.

use std::fs::File;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::format::{CaptureError, CaptureHeader, CaptureReader, Record, SkipReport};
use crate::pipeline::ports::{NavChunk, Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;
use crate::source::report::{InputReport, SourceReport};

/// Reads a capture file as a [`Source`].
pub struct CaptureSource {
    reader: CaptureReader<File>,
    path: PathBuf,
    total_bytes: u64,
    header: Option<CaptureHeader>,
    stats: CaptureStats,
}

/// A capture source's report (`summary.json` → `source`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct CaptureReport {
    /// The capture file.
    pub file: String,
    /// Its format version, `major.minor`.
    pub version: String,
    /// The sensor its first header names.
    pub sensor: Option<String>,
    /// What it held.
    pub records: CaptureStats,
    /// What the reader skipped (damage).
    pub skipped: SkipReport,
}

/// What the capture held, for `summary.json`.
#[derive(Clone, Debug, Default, Serialize)]
pub struct CaptureStats {
    /// Header records (recording segments) seen.
    pub headers: u64,
    /// Header records whose text could not be parsed.
    pub bad_headers: u64,
    /// Digitizer frames read.
    pub frames: u64,
    /// Frames that passed the checksum but could not be decoded.
    pub bad_frames: u64,
    /// Navigation records read.
    pub nav_records: u64,
}

impl CaptureSource {
    /// Opens a capture for replay (checks the preamble and version).
    pub fn open(path: &Path) -> Result<Self, CaptureError> {
        let reader = CaptureReader::open(path)?;
        let total_bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
        Ok(CaptureSource {
            reader,
            path: path.to_path_buf(),
            total_bytes,
            header: first_header(path),
            stats: CaptureStats::default(),
        })
    }

    /// The first header read so far, if any.
    pub fn header(&self) -> Option<&CaptureHeader> {
        self.header.as_ref()
    }

    /// What was skipped so far.
    pub fn skipped(&self) -> &SkipReport {
        self.reader.skipped()
    }
}

/// The capture's first record when it is a readable header (read by a second reader, so that
/// [`Source::facts`] is known before the first event: the stages are configured from it). The
/// source's own reading counts and checks it as usual.
fn first_header(path: &Path) -> Option<CaptureHeader> {
    let mut reader = CaptureReader::open(path).ok()?;
    match reader.next_record()? {
        Ok(Record::Header(text)) => CaptureHeader::parse(text).ok(),
        _ => None,
    }
}

impl Source for CaptureSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        "capture"
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        loop {
            let rec = match self.reader.next_record() {
                None => return Ok(SourceEvent::End),
                Some(Err(e)) => return Err(SourceError::Fatal(e.to_string())),
                Some(Ok(r)) => r,
            };
            match rec {
                Record::Header(text) => {
                    self.stats.headers += 1;
                    match CaptureHeader::parse(text) {
                        Ok(h) => {
                            // The first one was read when the source was opened.
                            if self.header.is_none() || self.stats.headers == 1 {
                                tracing::info!(
                                    "capture of the {} ({})",
                                    h.sensor.name,
                                    h.capture.origin
                                );
                                self.header = Some(h);
                            }
                        }
                        Err(e) => {
                            self.stats.bad_headers += 1;
                            tracing::warn!(file = %self.path.display(), "unreadable capture header: {e}");
                        }
                    }
                }
                Record::Frame(frame) => {
                    let mut pulse = pool.take();
                    match frame.decode_into(&mut pulse) {
                        Ok(()) => {
                            self.stats.frames += 1;
                            return Ok(SourceEvent::Pulse(pulse));
                        }
                        Err(e) => {
                            self.stats.bad_frames += 1;
                            tracing::debug!(pulse_id = frame.pulse_id(), "undecodable frame: {e}");
                            pool.give(pulse);
                        }
                    }
                }
                Record::Nav {
                    port,
                    receive_time_ns,
                    bytes,
                } => {
                    self.stats.nav_records += 1;
                    return Ok(SourceEvent::Nav(NavChunk {
                        port,
                        receive_time_ns,
                        bytes: bytes.to_vec(),
                    }));
                }
            }
        }
    }

    fn progress(&self) -> Option<(u64, u64)> {
        Some((self.reader.position(), self.total_bytes))
    }

    fn facts(&self) -> crate::core::facts::SourceFacts {
        match &self.header {
            Some(h) => crate::core::facts::SourceFacts {
                sensor: Some(h.sensor.clone()),
                time_base: Some(h.capture.time_base.clone()),
                crs: h.capture.crs.clone(),
                // Recorded and simulated frames time from the outgoing pulse's peak; imported
                // ones keep their input's t0 (LAS: first sample, PulseWaves: anchor).
                t0_is_emission: Some(h.capture.origin != "imported"),
            },
            None => crate::core::facts::SourceFacts::default(),
        }
    }

    fn report(&self) -> SourceReport {
        SourceReport::of(InputReport::Capture(CaptureReport {
            file: self.path.display().to_string(),
            version: format!("{}.{}", self.reader.version().0, self.reader.version().1),
            sensor: self.header.as_ref().map(|h| h.sensor.name.clone()),
            records: self.stats.clone(),
            skipped: *self.reader.skipped(),
        }))
    }
}
