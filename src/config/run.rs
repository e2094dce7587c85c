//! Run configuration for `fwlidar replay` (`config/replay.toml`) and the on-board daemon
//! (`config/onboard.toml`): the pipeline, its edges, outputs and recording policy.

use serde::{Deserialize, Serialize};

use crate::core::sensor::SensorFile;
use crate::core::toml_load::load_file;
use crate::core::validate::{Validate, Validator, field, index};
use crate::pipeline::edge::FullPolicy;
use crate::stages::StageConfig;

/// Smallest edge capacity, pulses (one in flight, one being filled).
pub const MIN_QUEUE_CAPACITY: usize = 2;
/// Largest edge capacity, pulses (pulses are pooled up front; more is a typo).
pub const MAX_QUEUE_CAPACITY: usize = 1_048_576;
/// Most worker threads accepted (more is a typo).
pub const MAX_WORKERS: usize = 1024;

/// The top level of a run configuration file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Sensor profile file, relative to this file's folder; used when the input does not carry
    /// its own sensor description (live input). Optional for replay (the capture header has it).
    #[serde(default)]
    pub sensor_profile: Option<String>,
    /// The per-pulse pipeline.
    #[serde(default)]
    pub pipeline: PipelineConfig,
    /// Outputs.
    #[serde(default)]
    pub output: OutputConfig,
    /// Georeferencing from the navigation stream (`src/source/georeferencing.rs`).
    #[serde(default)]
    pub georeference: crate::source::georeferencing::GeoreferenceConfig,
    /// Navigation inputs and their time handling.
    #[serde(default)]
    pub navigation: NavigationConfig,
    /// Voxel tiles (`src/voxel/`).
    #[serde(default)]
    pub voxels: crate::voxel::grid::VoxelConfig,
    /// The on-board daemon (`fwlidar run`): frame input, survey, recording, QC server, alarms
    /// (`src/daemon/config.rs`). Ignored by replay.
    #[serde(default)]
    pub daemon: crate::daemon::DaemonConfig,
}

/// `[navigation]`: the receivers' serial ports (live input) and date handling.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavigationConfig {
    /// Serial ports of GNSS/INS receivers (`[[navigation.serial]]`: device, baud, parity,
    /// port, reconnect_ms, read_timeout_ms; `src/source/serial.rs`). Default none.
    #[serde(default)]
    pub serial: Vec<crate::source::serial::SerialConfig>,
    /// Earliest date a receiver can report, `YYYY-MM-DD`: NMEA dates before it are taken for a
    /// 10-bit GPS week rollover and moved forward by 1024 weeks. Default none (dates as stated).
    #[serde(default)]
    pub earliest_date: Option<String>,
}

impl NavigationConfig {
    /// `earliest_date` as days since 1970-01-01, when given and valid.
    pub fn earliest_days(&self) -> Option<i64> {
        self.earliest_date.as_deref().and_then(parse_date)
    }
}

/// `YYYY-MM-DD` to days since 1970-01-01.
fn parse_date(s: &str) -> Option<i64> {
    let mut it = s.trim().split('-');
    let y: i64 = it.next()?.parse().ok()?;
    let m: u32 = it.next()?.parse().ok()?;
    let d: u32 = it.next()?.parse().ok()?;
    if it.next().is_some()
        || !(1980..=2200).contains(&y)
        || !(1..=12).contains(&m)
        || !(1..=31).contains(&d)
    {
        return None;
    }
    let days = crate::nav::nmea::days_from_civil(y, m, d);
    (crate::nav::dating::civil_of_days(days) == (y, m, d)).then_some(days)
}

impl Validate for NavigationConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        let mut ports = std::collections::BTreeSet::new();
        for (i, s) in self.serial.iter().enumerate() {
            let at = index(&field(path, "serial"), i);
            v.require(
                !s.device.as_os_str().is_empty(),
                field(&at, "device"),
                "must name a device, e.g. /dev/ttyUSB0",
            );
            v.require(
                (50..=4_000_000).contains(&s.baud),
                field(&at, "baud"),
                format!("must be in 50..=4000000 bits/s, got {}", s.baud),
            );
            v.require(
                ports.insert(s.port),
                field(&at, "port"),
                format!("port number {} is used twice", s.port),
            );
            v.require(
                (1..=60_000).contains(&s.reconnect_ms),
                field(&at, "reconnect_ms"),
                format!("must be in 1..=60000 ms, got {}", s.reconnect_ms),
            );
            v.require(
                (1..=10_000).contains(&s.read_timeout_ms),
                field(&at, "read_timeout_ms"),
                format!("must be in 1..=10000 ms, got {}", s.read_timeout_ms),
            );
        }
        if let Some(d) = &self.earliest_date {
            v.require(
                parse_date(d).is_some(),
                field(path, "earliest_date"),
                format!("must be a date YYYY-MM-DD from 1980 on, got {d:?}"),
            );
        }
    }
}

/// The per-pulse pipeline: workers, edges and stages.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipelineConfig {
    /// Worker threads running the per-pulse stages; 0 = automatic: one per core for replay
    /// (measured best: the source and sink threads take a small share of a core), one per core
    /// less one on board (`fwlidar run`: a core for the receivers and the recorder), at least 1.
    /// Default 0.
    #[serde(default)]
    pub workers: usize,
    /// Capacity of every edge, pulses. Default 1024.
    #[serde(default = "default_queue_capacity")]
    pub queue_capacity: usize,
    /// Policy of the edge from the source into the workers. Default `block`.
    #[serde(default)]
    pub input_edge: FullPolicy,
    /// The stages, in order. Default: one `denoise` stage with its defaults.
    #[serde(default = "default_stages")]
    pub stages: Vec<StageConfig>,
}

fn default_queue_capacity() -> usize {
    1024
}

fn default_stages() -> Vec<StageConfig> {
    vec![StageConfig::Denoise(Default::default())]
}

impl Default for PipelineConfig {
    fn default() -> Self {
        PipelineConfig {
            workers: 0,
            queue_capacity: default_queue_capacity(),
            input_edge: FullPolicy::Block,
            stages: default_stages(),
        }
    }
}

/// Outputs of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// Output folder (the command line's `--out` takes precedence). Default `out`.
    #[serde(default = "default_out_dir")]
    pub dir: String,
    /// Write the processed waveforms, in `waveform_format`. Default true.
    #[serde(default = "yes")]
    pub waveforms: bool,
    /// Form of the processed waveforms: `npy` (`waveforms.npy` + `waveform_index.npy`, binary,
    /// what `numpy.load` reads; `sink::waveform_npy`) or `csv` (`waveforms.csv` + `pulses.csv`,
    /// text, ~3 times larger and slower). Default `npy`.
    #[serde(default)]
    pub waveform_format: WaveformFormat,
    /// Write the discrete returns of a `decompose` stage as text (`returns.csv`). Default false
    /// (`returns.las` holds them); the file is only written when the pipeline has a `decompose`
    /// stage.
    #[serde(default)]
    pub returns: bool,
    /// Write the discrete returns of a `decompose` stage as LAS 1.4 (`returns.las`; with point
    /// format 9 also `returns.wdp`), for the pulses that carry geometry (LAS, PulseWaves input,
    /// or georeferenced captures). Default true; written only when the pipeline has a
    /// `decompose` stage.
    #[serde(default = "yes")]
    pub las: bool,
    /// Point data record format of the LAS output: 6 (points) or 9 (points with their raw
    /// waveforms in a `.wdp`). Default 6.
    #[serde(default = "default_las_point_format")]
    pub las_point_format: u8,
    /// Start a new LAS file every this many seconds of pulse GPS time (`returns_0000.las`,
    /// `returns_0001.las`, …); 0 = one file, `returns.las`. Default 0.
    #[serde(default)]
    pub las_rotate_s: f64,
    /// Hand the open LAS file's buffered points to the operating system every this many
    /// seconds of pulse GPS time (what a crash can lose beyond the header `fwlidar repair`
    /// rebuilds); 0 = only when the 1 MiB buffer fills. Default 1.
    #[serde(default = "default_las_flush_s")]
    pub las_flush_s: f64,
    /// Write the "hyper point cloud" `hyper_points.las` (point format 6): every sample of every
    /// return segment whose processed signal exceeds `hyper_threshold_v`, for pulses with
    /// geometry. Default false.
    #[serde(default)]
    pub hyper_points: bool,
    /// Threshold of the hyper point cloud, V (processed signal above the baseline); required
    /// with `hyper_points = true`. Default none.
    #[serde(default)]
    pub hyper_threshold_v: Option<f32>,
    /// Write `pulse_metrics.csv` (forest structure metrics per pulse, `docs/forest.md`) when the
    /// chain has a `metrics` stage. Default true.
    #[serde(default = "yes")]
    pub metrics: bool,
    /// Write forest structure rasters (`rasters/chm.vrt`, `rasters/metrics.vrt`, Cloud-Optimized
    /// GeoTIFF tiles; `docs/forest.md`) when the chain has a `metrics` stage and the pulses
    /// have a projected CRS. Default true.
    #[serde(default = "yes")]
    pub rasters: bool,
    /// Cell of the canopy height model, m. Default 1.
    #[serde(default = "default_chm_cell")]
    pub chm_cell_m: f64,
    /// Cell of the other metrics rasters (RH, cover, PAI, FHD, herbaceous, density), m.
    /// Default 10.
    #[serde(default = "default_profile_cell")]
    pub profile_cell_m: f64,
    /// Side of a raster tile, m; a whole multiple of both cells. Default 1000.
    #[serde(default = "default_raster_tile")]
    pub raster_tile_m: f64,
}

fn default_chm_cell() -> f64 {
    1.0
}
fn default_profile_cell() -> f64 {
    10.0
}
fn default_raster_tile() -> f64 {
    1000.0
}

/// The form of the processed waveforms written by `replay`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WaveformFormat {
    /// `waveforms.npy` + `waveform_index.npy` (NumPy binary).
    #[default]
    Npy,
    /// `waveforms.csv` + `pulses.csv` (text).
    Csv,
}

fn default_las_point_format() -> u8 {
    6
}
fn default_las_flush_s() -> f64 {
    1.0
}

fn default_out_dir() -> String {
    "out".to_string()
}
fn yes() -> bool {
    true
}

impl Default for OutputConfig {
    fn default() -> Self {
        OutputConfig {
            dir: default_out_dir(),
            waveforms: true,
            waveform_format: WaveformFormat::Npy,
            returns: false,
            las: true,
            las_point_format: default_las_point_format(),
            las_rotate_s: 0.0,
            las_flush_s: default_las_flush_s(),
            hyper_points: false,
            hyper_threshold_v: None,
            metrics: true,
            rasters: true,
            chm_cell_m: default_chm_cell(),
            profile_cell_m: default_profile_cell(),
            raster_tile_m: default_raster_tile(),
        }
    }
}

impl Validate for RunConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        if let Some(profile) = &self.sensor_profile {
            let at = field(path, "sensor_profile");
            if profile.trim().is_empty() {
                v.report(at, "must name a sensor profile file, or be left out");
            } else {
                let resolved = match v.base_dir() {
                    Some(dir) => dir.join(profile),
                    None => profile.into(),
                };
                match load_file::<SensorFile>(&resolved) {
                    Ok(file) => v.set_sample_interval_ns(Some(file.sensor.sample_interval_ns)),
                    Err(e) => {
                        let first = e.issues.first().map_or(String::new(), |i| {
                            if i.path.is_empty() {
                                i.reason.clone()
                            } else {
                                format!("{}: {}", i.path, i.reason)
                            }
                        });
                        v.report(
                            at,
                            format!(
                                "sensor profile {} is not usable ({} problem(s); first: {first})",
                                resolved.display(),
                                e.issues.len()
                            ),
                        );
                    }
                }
            }
        }
        self.pipeline.validate(&field(path, "pipeline"), v);
        self.output.validate(&field(path, "output"), v);
        self.georeference.validate(&field(path, "georeference"), v);
        self.navigation.validate(&field(path, "navigation"), v);
        self.voxels.validate(&field(path, "voxels"), v);
        self.daemon.validate(&field(path, "daemon"), v);
        for (i, stage) in self.pipeline.stages.iter().enumerate() {
            if let Some(key) = stage.as_kind().needs_dem()
                && self.georeference.dem.is_none()
            {
                v.report(
                    format!("{}.stages[{i}].{key}", field(path, "pipeline")),
                    "\"dem\" needs a DEM: set [georeference] dem",
                );
            }
        }
        if self.voxels.enabled
            && self.voxels.height == crate::voxel::grid::HeightMode::AboveDem
            && self.georeference.dem.is_none()
        {
            v.report(
                field(&field(path, "voxels"), "height"),
                "\"above_dem\" needs a DEM: set [georeference] dem",
            );
        }
    }
}

impl Validate for PipelineConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        v.require(
            self.workers <= MAX_WORKERS,
            field(path, "workers"),
            format!(
                "must be at most {MAX_WORKERS} (0 = automatic), got {}",
                self.workers
            ),
        );
        v.require(
            (MIN_QUEUE_CAPACITY..=MAX_QUEUE_CAPACITY).contains(&self.queue_capacity),
            field(path, "queue_capacity"),
            format!(
                "must be in {MIN_QUEUE_CAPACITY}..={MAX_QUEUE_CAPACITY} pulses, got {}",
                self.queue_capacity
            ),
        );
        let stages = field(path, "stages");
        v.require(
            !self.stages.is_empty(),
            &stages,
            "must list at least one stage (use type = \"passthrough\" for none)",
        );
        for (i, stage) in self.stages.iter().enumerate() {
            stage.validate(&index(&stages, i), v);
        }
    }
}

impl Validate for OutputConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        v.positive(self.chm_cell_m, field(path, "chm_cell_m"));
        v.positive(self.profile_cell_m, field(path, "profile_cell_m"));
        let whole = |tile: f64, cell: f64| {
            let k = tile / cell;
            k.is_finite() && k >= 1.0 && (k - k.round()).abs() < 1e-6 && k <= 16_384.0
        };
        v.require(
            whole(self.raster_tile_m, self.chm_cell_m) && whole(self.raster_tile_m, self.profile_cell_m),
            field(path, "raster_tile_m"),
            format!(
                "must be a whole multiple (1 to 16384) of chm_cell_m ({}) and profile_cell_m ({}), got {}",
                self.chm_cell_m, self.profile_cell_m, self.raster_tile_m
            ),
        );
        v.require(
            !self.dir.trim().is_empty(),
            field(path, "dir"),
            "must not be empty",
        );
        v.require(
            matches!(self.las_point_format, 6 | 9),
            field(path, "las_point_format"),
            format!("must be 6 or 9, got {}", self.las_point_format),
        );
        v.require(
            self.las_rotate_s.is_finite() && self.las_rotate_s >= 0.0,
            field(path, "las_rotate_s"),
            format!(
                "must be 0 (one file) or a positive number of seconds, got {}",
                self.las_rotate_s
            ),
        );
        v.require(
            self.las_flush_s.is_finite() && self.las_flush_s >= 0.0,
            field(path, "las_flush_s"),
            format!(
                "must be 0 (when the buffer fills) or a positive number of seconds, got {}",
                self.las_flush_s
            ),
        );
        match self.hyper_threshold_v {
            Some(t) => v.require(
                t.is_finite() && t > 0.0,
                field(path, "hyper_threshold_v"),
                format!("must be a positive number of volts, got {t}"),
            ),
            None => v.require(
                !self.hyper_points,
                field(path, "hyper_threshold_v"),
                "must be given (volts) when hyper_points = true",
            ),
        }
    }
}
