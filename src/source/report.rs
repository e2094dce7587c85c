//! What a run's source says in `summary.json` (`source`): the input reader's own report, typed
//! per format, and what the wrappers around it add (the georeferencing, a shard of the pulses,
//! several inputs in sequence). Readers of the report (the one-screen summary, the warnings,
//! the daemon's QC) read these fields; the summary's JSON is made from them.

use std::collections::BTreeMap;

use serde::Serialize;

use crate::format::SkipReport;
use crate::nav::trajectory::TrajectoryStats;

/// The source's report: the input's own, and what the wrappers add. Serialised as one object
/// (the input's keys, then `georeference` and `shard` beside them; an input without a report
/// of its own is `{"input": …}`-free and holds the wrappers' keys alone).
#[derive(Clone, Debug, Default)]
pub struct SourceReport {
    /// The input reader's report.
    pub input: InputReport,
    /// The georeferencing's, when it wraps the input.
    pub georeference: Option<GeoreferenceReport>,
    /// The shard's, when only a range of the input's pulses is replayed.
    pub shard: Option<ShardReport>,
}

/// An input reader's report, by format.
#[derive(Clone, Debug, Default)]
pub enum InputReport {
    /// A source with nothing to say (`null`).
    #[default]
    None,
    /// An fwlidar capture.
    Capture(crate::source::capture::CaptureReport),
    /// A LAS/LAZ file with waveforms.
    Las(Box<crate::source::las::LasReport>),
    /// A PulseWaves file.
    PulseWaves(Box<crate::source::pulsewaves::PulseWavesReport>),
    /// A GEDI Level 1B granule.
    Gedi(Box<crate::source::gedi::GediReport>),
    /// The daemon's recording of live frames and navigation.
    Live(LiveReport),
    /// Several inputs in sequence: each one's whole report, in order, with its file name.
    Sequence(Vec<(String, SourceReport)>),
}

/// The daemon's recorder: what it recorded into the capture segment.
#[derive(Clone, Debug, Default, Serialize)]
pub struct LiveReport {
    /// The capture segment being written.
    pub segment: String,
    /// Frames recorded.
    pub frames_recorded: u64,
    /// Navigation records recorded.
    pub nav_records: u64,
    /// Bytes recorded.
    pub bytes: u64,
    /// Frames received that could not be decoded (recorded anyway).
    pub bad_frames: u64,
    /// Frames recorded but not processed (the input edge was full).
    pub recorded_unprocessed: u64,
    /// Pulses with a saturated sample.
    pub saturated_pulses: u64,
    /// The recorder's last error, if any.
    pub error: Option<String>,
}

/// The georeferencing's report (`source.georeference`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct GeoreferenceReport {
    /// Pulses placed from the trajectory.
    pub georeferenced: u64,
    /// Pulses that carried their own geometry (LAS, PulseWaves, GEDI), passed as they were.
    pub with_own_geometry: u64,
    /// Pulses the trajectory could not place, by reason.
    pub missed: BTreeMap<String, u64>,
    /// Most pulses held at once waiting for navigation.
    pub largest_wait_pulses: u64,
    /// The output CRS (`EPSG:<code>`), once decided.
    pub output_crs: Option<String>,
    /// What the trajectory buffer took and refused.
    pub trajectory: TrajectoryStats,
}

impl GeoreferenceReport {
    /// Adds `other`'s counts (the inputs of a sequence, each with its own trajectory): counts
    /// summed, the largest wait the larger, the CRS kept where they agree.
    pub fn add(&mut self, other: &GeoreferenceReport) {
        self.georeferenced += other.georeferenced;
        self.with_own_geometry += other.with_own_geometry;
        for (k, n) in &other.missed {
            *self.missed.entry(k.clone()).or_insert(0) += n;
        }
        self.largest_wait_pulses = self.largest_wait_pulses.max(other.largest_wait_pulses);
        if self.output_crs != other.output_crs {
            self.output_crs = None;
        }
        self.trajectory.add(&other.trajectory);
    }
}

/// A shard's range of the input's pulses (`source.shard`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct ShardReport {
    /// First pulse of the range (by number in the input).
    pub first_pulse: u64,
    /// One past the last pulse of the range.
    pub end_pulse: u64,
    /// Pulses read to reach and cover the range.
    pub pulses_read: u64,
}

impl SourceReport {
    /// A report of the input reader's own.
    pub fn of(input: InputReport) -> Self {
        SourceReport {
            input,
            ..SourceReport::default()
        }
    }

    /// The georeferencing's report, the inputs of a sequence added up.
    pub fn georeference(&self) -> Option<GeoreferenceReport> {
        match &self.input {
            InputReport::Sequence(inputs) => {
                let mut sum: Option<GeoreferenceReport> = self.georeference.clone();
                for (_, r) in inputs {
                    if let Some(g) = r.georeference() {
                        match &mut sum {
                            Some(s) => s.add(&g),
                            None => sum = Some(g),
                        }
                    }
                }
                sum
            }
            _ => self.georeference.clone(),
        }
    }

    /// What the capture reader skipped, when the input is a capture (the first skipping one
    /// of a sequence).
    pub fn capture_damage(&self) -> Option<SkipReport> {
        match &self.input {
            InputReport::Capture(c) => Some(c.skipped),
            InputReport::Sequence(inputs) => inputs.iter().find_map(|(_, r)| r.capture_damage()),
            _ => None,
        }
    }

    /// The report as `summary.json` holds it.
    pub fn to_json(&self) -> serde_json::Value {
        use serde_json::Value;
        let input = match &self.input {
            InputReport::None => Value::Null,
            InputReport::Capture(r) => to_json(r),
            InputReport::Las(r) => to_json(r),
            InputReport::PulseWaves(r) => to_json(r),
            InputReport::Gedi(r) => to_json(r),
            InputReport::Live(r) => to_json(r),
            InputReport::Sequence(inputs) => crate::source::chain::sequence_json(inputs),
        };
        if self.georeference.is_none() && self.shard.is_none() {
            return input;
        }
        let mut m = match input {
            Value::Object(m) => m,
            Value::Null => serde_json::Map::new(),
            other => {
                let mut m = serde_json::Map::new();
                m.insert("input".into(), other);
                m
            }
        };
        if let Some(s) = &self.shard {
            m.insert("shard".into(), to_json(s));
        }
        if let Some(g) = &self.georeference {
            m.insert("georeference".into(), to_json(g));
        }
        Value::Object(m)
    }
}

fn to_json(v: &impl Serialize) -> serde_json::Value {
    serde_json::to_value(v).unwrap_or(serde_json::Value::Null)
}

impl Serialize for SourceReport {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.to_json().serialize(s)
    }
}
