//! Discrete returns found by the decomposition stage, as `returns.csv`: one row per fitted
//! Gaussian, `pulse_id,gps_time,segment,position_bins,time_ns,amplitude_v,sigma_bins,residual_v,
//! x,y,z[,height_above_ground],backscatter`.
//!
//! - `segment`: index of the segment within its pulse (the `segment` column of `pulses.csv`);
//! - `position_bins`: centre in bins from the segment's first sample (fractional);
//! - `time_ns`: centre as time after the pulse's reference time, ns;
//! - `amplitude_v`: peak amplitude of the Gaussian, volts (of the signal the fit saw);
//! - `sigma_bins`: standard deviation, bins;
//! - `residual_v`: RMS residual of the whole segment's fit, volts;
//! - `x,y,z`: where the return lies, `anchor + time_ns · direction`, in the CRS of the pulse's
//!   geometry (the input file's for LAS and PulseWaves, the output CRS for georeferenced
//!   captures); empty for pulses without geometry;
//! - `height_above_ground` (only when a DEM is configured, `[georeference] dem`): `z` minus the
//!   DEM's bilinear height at `x, y`, metres; empty outside the DEM or next to its nodata;
//! - `backscatter` (always the last column): the return's calibrated backscatter from a
//!   `calibrate` stage (amplitude × calibration factor at `time_ns`, `docs/calibration.md`);
//!   empty when not calibrated (no such stage, or a return at or before the emission).
//!
//! Pulses without returns write nothing. The file appears atomically at the end of the run
//! (see [`AtomicFile`]); `returns.las` (`sink::las_wave`) holds the same returns for mapping.

use std::io::Write;
use std::path::Path;

use crate::core::atomic_file::AtomicFile;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::Pulse;
use crate::sink::SinkReport;

/// Header line of `returns.csv` up to `z`; then `height_above_ground` when a DEM is
/// configured, and `backscatter` last.
pub const RETURNS_HEADER: &str =
    "pulse_id,gps_time,segment,position_bins,time_ns,amplitude_v,sigma_bins,residual_v,x,y,z";

/// The returns CSV's report (`summary.json` → `sinks.returns_csv`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct ReturnsCsvReport {
    /// Rows (returns) written.
    pub rows: u64,
    /// Returns where the DEM has no height (with a DEM only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub returns_outside_dem: Option<u64>,
}

/// Writes `returns.csv` into a folder.
pub struct ReturnsCsvSink {
    file: AtomicFile,
    rows: u64,
    line: String,
    dem: Option<std::sync::Arc<crate::geo::dem::Dem>>,
    outside_dem: u64,
}

impl ReturnsCsvSink {
    /// Starts writing `returns.csv` into `dir` (which must exist).
    pub fn create(dir: &Path) -> Result<Self, SinkError> {
        ReturnsCsvSink::create_with_dem(dir, None)
    }

    /// As [`ReturnsCsvSink::create`], with a `height_above_ground` column from `dem` (which
    /// must be in the CRS of the pulses' geometry).
    pub fn create_with_dem(
        dir: &Path,
        dem: Option<std::sync::Arc<crate::geo::dem::Dem>>,
    ) -> Result<Self, SinkError> {
        let mut file = AtomicFile::create(dir.join("returns.csv"))?;
        let path = file.path().display().to_string();
        let extra = if dem.is_some() {
            ",height_above_ground,backscatter"
        } else {
            ",backscatter"
        };
        writeln!(file.writer()?, "{RETURNS_HEADER}{extra}")
            .map_err(|source| SinkError::Io { path, source })?;
        Ok(ReturnsCsvSink {
            file,
            rows: 0,
            line: String::with_capacity(1 << 12),
            dem,
            outside_dem: 0,
        })
    }

    /// Return rows written so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }
}

impl PulseSink for ReturnsCsvSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "returns_csv"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        use std::fmt::Write as _;
        if p.returns.is_empty() {
            return Ok(());
        }
        self.line.clear();
        for r in &p.returns {
            let _ = writeln!(
                self.line,
                "{},{:.9},{},{},{},{},{},{}",
                p.pulse_id,
                p.gps_time,
                r.segment,
                r.position_bins,
                r.time_ns,
                r.amplitude,
                r.sigma_bins,
                r.residual
            );
            // Replace the newline just written with the position columns.
            self.line.pop();
            let at = p
                .geometry
                .map(|g| [0, 1, 2].map(|k| g.anchor[k] + r.time_ns * g.direction[k]));
            match at {
                Some([x, y, z]) => {
                    let _ = write!(self.line, ",{x:.4},{y:.4},{z:.4}");
                }
                None => self.line.push_str(",,,"),
            }
            if let Some(dem) = &self.dem {
                match at.and_then(|[x, y, z]| dem.height_at(x, y).map(|g| z - g)) {
                    Some(h) => {
                        let _ = write!(self.line, ",{h:.4}");
                    }
                    None => {
                        self.outside_dem += 1;
                        self.line.push(',');
                    }
                }
            }
            if r.backscatter.is_finite() {
                let _ = write!(self.line, ",{}", r.backscatter);
            } else {
                self.line.push(',');
            }
            self.line.push('\n');
        }
        let path = self.file.path().display().to_string();
        self.file
            .writer()?
            .write_all(self.line.as_bytes())
            .map_err(|source| SinkError::Io { path, source })?;
        self.rows += p.returns.len() as u64;
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        Ok(self.file.flush()?)
    }

    fn report(&self) -> SinkReport {
        SinkReport::ReturnsCsv(ReturnsCsvReport {
            rows: self.rows,
            returns_outside_dem: self.dem.is_some().then_some(self.outside_dem),
        })
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        Ok(self.file.commit()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pulse::FittedReturn;

    #[test]
    fn one_row_per_return_and_nothing_for_pulses_without() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = ReturnsCsvSink::create(dir.path()).unwrap();
        let mut p = Pulse {
            pulse_id: 7,
            gps_time: 12.5,
            ..Default::default()
        };
        sink.write(&p).unwrap();
        p.returns.push(FittedReturn {
            segment: 1,
            position_bins: 10.25,
            time_ns: 110.25,
            amplitude: 0.5,
            sigma_bins: 3.0,
            residual: 0.01,
            backscatter: f32::NAN,
        });
        p.returns.push(FittedReturn {
            segment: 1,
            position_bins: 40.0,
            time_ns: 140.0,
            amplitude: 0.125,
            sigma_bins: 2.5,
            residual: 0.01,
            backscatter: 0.75,
        });
        sink.write(&p).unwrap();
        assert_eq!(sink.rows(), 2);
        assert!(
            !dir.path().join("returns.csv").exists(),
            "appears at finish"
        );
        sink.finish().unwrap();
        let text = std::fs::read_to_string(dir.path().join("returns.csv")).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines,
            [
                format!("{RETURNS_HEADER},backscatter").as_str(),
                "7,12.500000000,1,10.25,110.25,0.5,3,0.01,,,,",
                "7,12.500000000,1,40,140,0.125,2.5,0.01,,,,0.75"
            ]
        );
    }

    #[test]
    fn a_pulse_with_geometry_gets_the_position_of_each_return() {
        use crate::pulse::PulseGeometry;
        let dir = tempfile::tempdir().unwrap();
        let mut sink = ReturnsCsvSink::create(dir.path()).unwrap();
        let mut p = Pulse {
            pulse_id: 3,
            geometry: Some(PulseGeometry {
                anchor: [500_000.0, 5_000_000.0, 1_000.0],
                direction: [0.01, 0.0, -0.15],
            }),
            ..Default::default()
        };
        p.returns.push(FittedReturn {
            segment: 0,
            time_ns: 100.0,
            ..Default::default()
        });
        sink.write(&p).unwrap();
        sink.finish().unwrap();
        let text = std::fs::read_to_string(dir.path().join("returns.csv")).unwrap();
        let row = text.lines().nth(1).unwrap();
        assert!(
            row.ends_with(",500001.0000,5000000.0000,985.0000,"),
            "{row}"
        );
    }
}
