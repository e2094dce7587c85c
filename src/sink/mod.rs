//! Sinks: where processed pulses go, in arrival order (processed waveforms, fitted returns as CSV
//! and as LAS 1.4 with waveforms, the hyper point cloud, forest metrics and rasters, voxel
//! tiles), each with its typed report ([`SinkReport`]), and the [`FanOut`] that feeds a run's
//! sinks in turn.

pub mod hyper_points;
pub mod las_wave;
pub mod metrics_rasters;
pub mod pulse_metrics_csv;
pub mod returns_csv;
pub mod voxel_tiles;
pub mod waveform_csv;
pub mod waveform_npy;

use serde::Serialize;

use crate::pipeline::ports::{PulseSink, SinkError};
use crate::pulse::Pulse;
use hyper_points::HyperPointReport;
use las_wave::LasWaveReport;
use metrics_rasters::MetricsRastersReport;
use pulse_metrics_csv::PulseMetricsCsvReport;
use returns_csv::ReturnsCsvReport;
use voxel_tiles::VoxelReport;

/// One sink's report (`summary.json` → `sinks.<name>`).
#[derive(Clone, Debug, Default, Serialize)]
#[serde(untagged)]
pub enum SinkReport {
    /// Nothing to say (the sink is left out of `sinks`).
    #[default]
    None,
    /// `returns.las`.
    Las(LasWaveReport),
    /// `hyper_points.las`.
    HyperPoints(HyperPointReport),
    /// `voxels.zarr`.
    Voxels(Box<VoxelReport>),
    /// The metrics rasters.
    MetricsRasters(MetricsRastersReport),
    /// `pulse_metrics.csv`.
    PulseMetricsCsv(PulseMetricsCsvReport),
    /// `returns.csv`.
    ReturnsCsv(ReturnsCsvReport),
    /// `waveforms.npy`.
    Waveforms(WaveformsReport),
}

/// What the processed waveforms' file holds.
#[derive(Clone, Debug, Default, Serialize)]
pub struct WaveformsReport {
    /// Segments written.
    pub segments: u64,
    /// Samples written.
    pub samples: u64,
}

/// The reports of a run's sinks, by sink name (`summary.json` → `sinks`).
#[derive(Clone, Debug, Default)]
pub struct SinkReports(pub Vec<(&'static str, SinkReport)>);

impl SinkReports {
    fn find<T>(&self, f: impl Fn(&SinkReport) -> Option<&T>) -> Option<&T> {
        self.0.iter().find_map(|(_, r)| f(r))
    }

    /// `returns.las`'s report, when it was written.
    pub fn las(&self) -> Option<&LasWaveReport> {
        self.find(|r| match r {
            SinkReport::Las(x) => Some(x),
            _ => None,
        })
    }

    /// `hyper_points.las`'s report.
    pub fn hyper_points(&self) -> Option<&HyperPointReport> {
        self.find(|r| match r {
            SinkReport::HyperPoints(x) => Some(x),
            _ => None,
        })
    }

    /// The voxel store's report.
    pub fn voxels(&self) -> Option<&VoxelReport> {
        self.find(|r| match r {
            SinkReport::Voxels(x) => Some(x.as_ref()),
            _ => None,
        })
    }

    /// `returns.csv`'s report.
    pub fn returns_csv(&self) -> Option<&ReturnsCsvReport> {
        self.find(|r| match r {
            SinkReport::ReturnsCsv(x) => Some(x),
            _ => None,
        })
    }
}

impl Serialize for SinkReports {
    /// The sinks that have something to say, by name.
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let said: Vec<_> = self
            .0
            .iter()
            .filter(|(_, r)| !matches!(r, SinkReport::None))
            .collect();
        let mut m = s.serialize_map(Some(said.len()))?;
        for (name, r) in said {
            m.serialize_entry(name, r)?;
        }
        m.end()
    }
}

/// A sink of the runs this crate puts together: its report is a [`SinkReport`].
pub type DynSink = dyn PulseSink<Report = SinkReport>;

/// Several sinks fed the same pulses in turn.
pub struct FanOut(pub Vec<Box<DynSink>>);

impl PulseSink for FanOut {
    type Report = SinkReports;

    fn name(&self) -> &'static str {
        "fan_out"
    }
    fn write(&mut self, pulse: &Pulse) -> Result<(), SinkError> {
        self.0.iter_mut().try_for_each(|s| s.write(pulse))
    }
    fn flush(&mut self) -> Result<(), SinkError> {
        self.0.iter_mut().try_for_each(|s| s.flush())
    }
    fn finish(&mut self) -> Result<(), SinkError> {
        self.0.iter_mut().try_for_each(|s| s.finish())
    }
    /// The reports of the sinks, by name.
    fn report(&self) -> SinkReports {
        SinkReports(self.0.iter().map(|s| (s.name(), s.report())).collect())
    }
}
