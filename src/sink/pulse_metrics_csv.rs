//! Forest structure metrics per pulse as `pulse_metrics.csv` (one row per pulse that went
//! through a `metrics` stage; definitions in `docs/forest.md`, computation in
//! `src/forest/pulse_metrics.rs`). Columns:
//!
//! - `pulse_id`, `gps_time` (s, the input's time base); `shot_number` (GEDI input only: the
//!   GEDI shot number, equal to `pulse_id`);
//! - `x`, `y`, `z`: the ground (centre of the lowest mode, or the beam's crossing of the DEM
//!   with `ground = "dem"`) in the CRS of the pulse's geometry (empty without geometry);
//! - `status`: `ok`, or why there are no metrics (`no_signal`, `no_ground`, `no_waveform`,
//!   `non_finite`; the other columns are then empty);
//! - `canopy_height` (m: the canopy top above the ground — the signal start, = `rh100`, or with
//!   `top = "leading_edge"` its leading edge), `rh0` … `rh100` (m above the ground);
//! - `energy_10_90_ns`, `modes`, `crown_thickness_m`;
//! - `energy_total`, `energy_ground`, `energy_canopy` (signal units × bins), `cover`, `pgap`,
//!   `pai` (m²/m²), `fhd`;
//! - `pavd_0_5` … (m²/m³ per profile bin, named by its height range in m);
//! - `ground_sigma_m`, `ground_skew`, `energy_lowest_m`, `ground_above_dem_m` (herbaceous
//!   metrics; the last the waveform's lowest mode above the run's DEM, `[georeference] dem`,
//!   where the beam met it: grass lifts the lowest mode; empty without a DEM or outside it);
//! - `zenith_deg`, `noise_mean`, `noise_sd` (signal units), `smoothing_ns`, `top_ns`,
//!   `ground_ns`, `bottom_ns`, `mode_ns` (the lowest mode; ns on the pulse's time axis);
//! - `ground_from`: `lowest_mode` or `dem`;
//! - `top_x`, `top_y`, `top_z`: the signal start (canopy top) along the beam — off nadir it
//!   lies `height × tan(zenith)` from the ground point, which is where the canopy height
//!   model places it (angular rectification).
//!
//! The file appears atomically at the end of the run.

use std::io::Write;
use std::path::Path;

use std::sync::Arc;

use crate::core::atomic_file::AtomicFile;
use crate::forest::products::{format_row, header};
use crate::geo::dem::Dem;
use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::Pulse;
use crate::pulse::waveform_metrics::{MetricsStatus, WaveformMetrics};
use crate::sink::SinkReport;

/// The report of `pulse_metrics.csv` (`summary.json` → `sinks.pulse_metrics_csv`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct PulseMetricsCsvReport {
    /// Rows written.
    pub rows: u64,
    /// Rows by metrics status.
    pub ok: u64,
    /// Rows with status `no_signal`.
    pub no_signal: u64,
    /// Rows with status `no_ground`.
    pub no_ground: u64,
    /// Rows with status `no_waveform`.
    pub no_waveform: u64,
    /// Rows with status `non_finite`.
    pub non_finite: u64,
    /// Height of the PAVD bins, m.
    pub profile_bin_m: f64,
}

/// Writes `pulse_metrics.csv` into a folder.
pub struct PulseMetricsCsvSink {
    file: AtomicFile,
    shot_number: bool,
    profile_bins: usize,
    profile_bin_m: f64,
    /// The run's DEM, for `ground_above_dem_m`.
    dem: Option<Arc<Dem>>,
    rows: u64,
    by_status: [u64; 5],
    line: String,
}

impl PulseMetricsCsvSink {
    /// Starts `pulse_metrics.csv` in `dir`; `shot_number` adds the GEDI column; the PAVD
    /// columns follow the metrics stage's profile; `dem` (the run's `[georeference] dem`, in
    /// the pulses' CRS) fills `ground_above_dem_m`.
    pub fn create(
        dir: &Path,
        shot_number: bool,
        profile_bins: usize,
        profile_bin_m: f64,
        dem: Option<Arc<Dem>>,
    ) -> Result<Self, SinkError> {
        let mut file = AtomicFile::create(dir.join("pulse_metrics.csv"))?;
        let path = file.path().display().to_string();
        writeln!(
            file.writer()?,
            "{}",
            header(shot_number, profile_bins, profile_bin_m)
        )
        .map_err(|source| SinkError::Io { path, source })?;
        Ok(PulseMetricsCsvSink {
            file,
            shot_number,
            profile_bins,
            profile_bin_m,
            dem,
            rows: 0,
            by_status: [0; 5],
            line: String::with_capacity(4096),
        })
    }

    fn row(&mut self, p: &Pulse, m: &WaveformMetrics) {
        let [x, y, z] = p.geometry.map_or([f64::NAN; 3], |g| g.at(m.mode_ns));
        let above = match &self.dem {
            Some(dem) if x.is_finite() && y.is_finite() => {
                dem.height_at(x, y).map_or(f32::NAN, |g| (z - g) as f32)
            }
            _ => f32::NAN,
        };
        format_row(
            &mut self.line,
            p.pulse_id,
            Some(p.gps_time),
            self.shot_number,
            m,
            self.profile_bins,
            above,
        );
    }
}

impl PulseSink for PulseMetricsCsvSink {
    type Report = SinkReport;

    fn name(&self) -> &'static str {
        "pulse_metrics_csv"
    }

    fn write(&mut self, p: &Pulse) -> Result<(), SinkError> {
        let Some(m) = p.metrics else {
            return Ok(());
        };
        self.row(p, &m);
        let path = self.file.path().display().to_string();
        self.file
            .writer()?
            .write_all(self.line.as_bytes())
            .map_err(|source| SinkError::Io { path, source })?;
        self.rows += 1;
        let i = match m.status {
            MetricsStatus::Ok => 0,
            MetricsStatus::NoSignal => 1,
            MetricsStatus::NoGround => 2,
            MetricsStatus::NoWaveform => 3,
            MetricsStatus::NonFinite => 4,
        };
        self.by_status[i] += 1;
        Ok(())
    }

    fn flush(&mut self) -> Result<(), SinkError> {
        Ok(self.file.flush()?)
    }

    fn report(&self) -> SinkReport {
        let s = &self.by_status;
        SinkReport::PulseMetricsCsv(PulseMetricsCsvReport {
            rows: self.rows,
            ok: s[0],
            no_signal: s[1],
            no_ground: s[2],
            no_waveform: s[3],
            non_finite: s[4],
            profile_bin_m: self.profile_bin_m,
        })
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        Ok(self.file.commit()?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_rows_have_the_same_columns() {
        let dir = tempfile::tempdir().unwrap();
        let mut sink = PulseMetricsCsvSink::create(dir.path(), true, 30, 5.0, None).unwrap();
        let mut p = Pulse {
            pulse_id: 42,
            ..Default::default()
        };
        sink.write(&p).unwrap(); // no metrics: no row
        p.metrics = Some(WaveformMetrics::default());
        sink.write(&p).unwrap();
        let mut m = WaveformMetrics {
            status: MetricsStatus::Ok,
            pavd_bins: 30,
            ..Default::default()
        };
        m.rh = [1.5; 101];
        m.canopy_height = 1.5;
        m.ground_xyz = [1.0, 2.0, 3.0];
        p.metrics = Some(m);
        sink.write(&p).unwrap();
        sink.finish().unwrap();
        let text = std::fs::read_to_string(dir.path().join("pulse_metrics.csv")).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 3);
        let n = lines[0].split(',').count();
        assert!(
            lines[0]
                .starts_with("pulse_id,gps_time,shot_number,x,y,z,status,canopy_height,rh0,rh1,")
        );
        assert!(lines[0].contains(",pavd_0_5,pavd_5_10,") && lines[0].contains(",pavd_145_150,"));
        for l in &lines[1..] {
            assert_eq!(l.split(',').count(), n, "{l}");
        }
        assert!(lines[1].contains(",no_waveform,"));
        assert!(lines[2].starts_with("42,0.000000000,42,1.000,2.000,3.000,ok,1.500,1.500,"));
        let SinkReport::PulseMetricsCsv(r) = sink.report() else {
            panic!("the CSV's report")
        };
        assert_eq!((r.ok, r.no_waveform), (1, 1));
    }
}
