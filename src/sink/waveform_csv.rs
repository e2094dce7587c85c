//! Processed waveforms as two CSV files that numpy, pandas or a spreadsheet read directly:
//!
//! - `pulses.csv`: one row per segment: `row,pulse_id,gps_time,segment,kind,channel,start_ns,
//!   sample_ns,n_samples,baseline_v,noise_v`;
//! - `waveforms.csv`: row `row` of `pulses.csv` is line `row` (0-based, no header) of this file:
//!   the segment's processed signal in volts, comma-separated, one value per sample.
//!
//! Segments a stage has not processed (empty `signal`) are written as raw counts converted to
//! volts. Both files appear atomically at the end of the run (see [`AtomicFile`]).

use std::io::Write;
use std::path::Path;

use crate::core::atomic_file::AtomicFile;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::{Pulse, SegmentKind};
use crate::sink::SinkReport;

/// Writes `pulses.csv` and `waveforms.csv` into a folder.
pub struct WaveformCsvSink {
    pulses: AtomicFile,
    waveforms: AtomicFile,
    row: u64,
    samples: u64,
    line: String,
}

/// Header line of `pulses.csv`.
pub const PULSES_HEADER: &str =
    "row,pulse_id,gps_time,segment,kind,channel,start_ns,sample_ns,n_samples,baseline_v,noise_v";

impl WaveformCsvSink {
    /// Starts writing into `dir` (which must exist).
    pub fn create(dir: &Path) -> Result<Self, SinkError> {
        let mut pulses = AtomicFile::create(dir.join("pulses.csv"))?;
        let waveforms = AtomicFile::create(dir.join("waveforms.csv"))?;
        let path = pulses.path().display().to_string();
        writeln!(pulses.writer()?, "{PULSES_HEADER}")
            .map_err(|source| SinkError::Io { path, source })?;
        Ok(WaveformCsvSink {
            pulses,
            waveforms,
            row: 0,
            samples: 0,
            line: String::with_capacity(1 << 16),
        })
    }

    /// Segment rows written so far.
    pub fn rows(&self) -> u64 {
        self.row
    }
}

impl PulseSink for WaveformCsvSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "waveform_csv"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        use std::fmt::Write as _;
        for (i, seg) in p.segments.iter().enumerate() {
            let kind = match seg.kind {
                SegmentKind::Outgoing => "outgoing",
                SegmentKind::Return => "return",
            };
            self.line.clear();
            let _ = writeln!(
                self.line,
                "{},{},{:.9},{},{},{},{},{},{},{},{}",
                self.row,
                p.pulse_id,
                p.gps_time,
                i,
                kind,
                seg.channel,
                seg.start_ns,
                p.sample_ns,
                seg.len,
                p.noise.baseline_v,
                p.noise.noise_v
            );
            let path = self.pulses.path().display().to_string();
            self.pulses
                .writer()?
                .write_all(self.line.as_bytes())
                .map_err(|source| SinkError::Io { path, source })?;

            self.line.clear();
            let signal = p.signal_of(i);
            if signal.len() == seg.len as usize {
                for (k, v) in signal.iter().enumerate() {
                    if k > 0 {
                        self.line.push(',');
                    }
                    let _ = write!(self.line, "{v}");
                }
            } else {
                for (k, c) in p.raw_of(i).iter().enumerate() {
                    if k > 0 {
                        self.line.push(',');
                    }
                    let _ = write!(self.line, "{}", p.counts_to_volts(*c));
                }
            }
            self.line.push('\n');
            let path = self.waveforms.path().display().to_string();
            self.waveforms
                .writer()?
                .write_all(self.line.as_bytes())
                .map_err(|source| SinkError::Io { path, source })?;
            self.row += 1;
            self.samples += u64::from(seg.len);
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        self.pulses.flush()?;
        Ok(self.waveforms.flush()?)
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        self.pulses.commit()?;
        Ok(self.waveforms.commit()?)
    }

    fn report(&self) -> SinkReport {
        SinkReport::Waveforms(crate::sink::WaveformsReport {
            segments: self.row,
            samples: self.samples,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::SegmentKind;

    #[test]
    fn rows_line_up_between_the_two_files() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = WaveformCsvSink::create(dir.path()).unwrap();
        let mut p = Pulse {
            pulse_id: 42,
            gain_v_per_dn: 0.5,
            ..Default::default()
        };
        p.push_segment(SegmentKind::Outgoing, 0, -3.0, [2, 4]);
        p.push_segment(SegmentKind::Return, 1, 100.0, [1, 2, 3]);
        p.signal = vec![0.0, 1.0, 0.25, 0.5, 0.75];
        sink.write(&p).unwrap();
        p.signal.clear();
        sink.write(&p).unwrap();
        assert!(
            !dir.path().join("pulses.csv").exists(),
            "appears only at finish"
        );
        sink.finish().unwrap();
        let pulses = std::fs::read_to_string(dir.path().join("pulses.csv")).unwrap();
        let waves = std::fs::read_to_string(dir.path().join("waveforms.csv")).unwrap();
        let prow: Vec<&str> = pulses.lines().collect();
        assert_eq!(prow[0], PULSES_HEADER);
        assert_eq!(prow.len(), 5);
        assert!(prow[2].starts_with("1,42,"));
        assert!(prow[2].contains(",return,1,100,"));
        let wrow: Vec<&str> = waves.lines().collect();
        assert_eq!(wrow, vec!["0,1", "0.25,0.5,0.75", "1,2", "0.5,1,1.5"]);
    }
}
