//! What the QC server shows: one [`QcSnapshot`] per second (the daemon's sampler builds it from
//! the pipeline's live counters and reports), a [`HistoryPoint`] per snapshot for the charts, and
//! the last sampled waveform at every processing step ([`WaveformView`]).
//!
//! Everything here is plain data, serialised as-is to `/api/status`, `/api/history`,
//! `/api/waveform` and `/api/events`, and rendered as Prometheus text by `qc::metrics`.

use std::collections::BTreeMap;

use serde::Serialize;

/// The state of the daemon at one instant.
#[derive(Clone, Debug, Default, Serialize)]
pub struct QcSnapshot {
    /// When the snapshot was taken, seconds since the Unix epoch.
    pub time_unix_s: f64,
    /// Seconds since the daemon started.
    pub uptime_s: f64,
    /// fwlidar version.
    pub version: String,
    /// Survey name (`[daemon] survey`).
    pub survey: String,
    /// Snapshot number, from 0 (increases by one a snapshot).
    pub sequence: u64,
    /// Every input: the digitizer frame stream and each serial port.
    pub inputs: Vec<InputStatus>,
    /// Pulse counts and rates.
    pub pulses: PulseCounts,
    /// Pulses dropped from processing, by reason (`input_queue_full`, `georeference.…`,
    /// `<stage>.<reason>`); cumulative.
    pub drops: BTreeMap<String, u64>,
    /// Fill of every bounded queue.
    pub queues: Vec<QueueFill>,
    /// Per-stage service time, since the start.
    pub stages: Vec<StageLatency>,
    /// Frame arrival to the sink (voxel deposit and the other outputs done).
    pub end_to_end: StageLatency,
    /// Navigation, per serial port.
    pub nav: Vec<NavStatus>,
    /// Georeferencing: pulses placed and missed by reason.
    pub georeference: GeorefStatus,
    /// Voxel tiles.
    pub tiles: TilesStatus,
    /// The recording (capture segments).
    pub recording: RecordingStatus,
    /// Free space where the recording goes.
    pub disk: DiskStatus,
    /// Saturated pulses (a raw sample at the digitizer's full scale).
    pub saturation: SaturationStatus,
    /// Alerts in force now.
    pub alerts: Vec<Alert>,
}

/// One input of the daemon.
#[derive(Clone, Debug, Default, Serialize)]
pub struct InputStatus {
    /// `frames` or `serial:<port>`.
    pub name: String,
    /// What it is: `udp 127.0.0.1:5000`, `tcp-listen …`, `/dev/ttyUSB0 @ 115200`.
    pub detail: String,
    /// Whether it is connected and delivering (frames: a socket bound / a peer connected;
    /// serial: the device is open).
    pub up: bool,
    /// Seconds since its last data, when any came.
    pub last_data_age_s: Option<f64>,
    /// Bytes received so far.
    pub bytes: u64,
    /// Connections made (TCP peers accepted, serial device opens).
    pub connects: u64,
    /// Attempts that failed (device absent, connection refused); it keeps retrying.
    pub failed_attempts: u64,
    /// The last problem, if any (`device /dev/gnss0 absent`, `frame CRC mismatch`).
    pub last_error: Option<String>,
}

/// Pulse counts (cumulative) and rates (over the last snapshot interval, per second).
#[derive(Clone, Debug, Default, Serialize)]
pub struct PulseCounts {
    /// Frames received from the network.
    pub frames_received: u64,
    /// Frames written to the capture (every received frame is, or the recording failed).
    pub frames_recorded: u64,
    /// Frames lost on the network (sequence gaps), counted by the receiver.
    pub frames_lost: u64,
    /// Frames that are not valid digitizer frames (recorded, not processed).
    pub frames_bad: u64,
    /// Pulses that entered processing (after the recorder).
    pub pulses_in: u64,
    /// Pulses that left the sink (all outputs written).
    pub pulses_processed: u64,
    /// Sum of `drops`.
    pub dropped_total: u64,
    /// Frames received per second.
    pub rate_in_hz: f64,
    /// Pulses processed per second.
    pub rate_processed_hz: f64,
    /// Pulses dropped per second.
    pub rate_dropped_hz: f64,
}

/// Fill of one bounded queue.
#[derive(Clone, Debug, Default, Serialize)]
pub struct QueueFill {
    /// Queue name (`recorder`, `worker-0`, …).
    pub name: String,
    /// Items in it now.
    pub len: u64,
    /// Its capacity.
    pub capacity: u64,
}

/// Latency summary and cumulative histogram of one stage (or end to end).
#[derive(Clone, Debug, Default, Serialize)]
pub struct StageLatency {
    /// Stage name.
    pub name: String,
    /// Pulses measured.
    pub count: u64,
    /// Median, µs.
    pub p50_us: f64,
    /// 99th percentile, µs.
    pub p99_us: f64,
    /// 99.9th percentile, µs.
    pub p999_us: f64,
    /// Maximum, µs.
    pub max_us: f64,
    /// Sum of all latencies, seconds (Prometheus `_sum`).
    pub sum_s: f64,
    /// Cumulative histogram: `(upper bound in seconds, count ≤ bound)`, bounds increasing; the
    /// last bound is +∞ (serialised as `null`).
    pub buckets: Vec<(f64, u64)>,
}

/// Navigation state of one serial port.
#[derive(Clone, Debug, Default, Serialize)]
pub struct NavStatus {
    /// Port number (`[[navigation.serial]] port`).
    pub port: u8,
    /// Fix quality as the last record coded it (GGA quality / NovAtel position type).
    pub fix: Option<u32>,
    /// The fix in words (`RTK fixed`, `INS + RTK`, `no fix`).
    pub fix_name: String,
    /// Satellites used.
    pub satellites: Option<u32>,
    /// INS status code (NovAtel INS status, PASHR IMU status).
    pub ins_status: Option<u32>,
    /// INS status in words (`solution good`, `aligning`).
    pub ins_name: String,
    /// Seconds since the last decoded record arrived (host clock).
    pub last_packet_age_s: Option<f64>,
    /// GPS seconds of week of the last record.
    pub last_gps_sow: Option<f64>,
    /// Last position: latitude, longitude (degrees), ellipsoidal height (m).
    pub position: Option<[f64; 3]>,
    /// Samples decoded.
    pub samples: u64,
    /// Records rejected (bad checksum, malformed).
    pub rejected: u64,
}

/// Georeferencing counters.
#[derive(Clone, Debug, Default, Serialize)]
pub struct GeorefStatus {
    /// Whether georeferencing is on.
    pub enabled: bool,
    /// Pulses placed.
    pub placed: u64,
    /// Pulses not placed, by reason (`navigation_gap`, `navigation_late`, …).
    pub missed: BTreeMap<String, u64>,
    /// Output CRS, once decided.
    pub crs: Option<String>,
}

/// Voxel tiles: counts and the coverage map.
#[derive(Clone, Debug, Default, Serialize)]
pub struct TilesStatus {
    /// Tiles open now.
    pub open: u64,
    /// Tiles closed (written) so far.
    pub closed: u64,
    /// Tile side `[x, y]`, metres (0 before the store exists).
    pub tile_m: [f64; 2],
    /// Every tile met: its index, state and pulse count.
    pub cells: Vec<TileCell>,
}

/// One tile of the coverage map.
#[derive(Clone, Debug, Default, Serialize)]
pub struct TileCell {
    /// Tile index east (global numbering: west edge = origin + tx · tile side).
    pub tx: i64,
    /// Tile index north.
    pub ty: i64,
    /// `open` or `closed`.
    pub state: String,
    /// Pulses whose footprint centre fell in it.
    pub pulses: u64,
    /// Pulses per square metre.
    pub density_per_m2: f64,
    /// Highest canopy height (RH100 of the forest metrics) of its pulses, m; none without a
    /// `metrics` stage in the chain.
    pub canopy_height_m: Option<f64>,
}

/// The recording.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RecordingStatus {
    /// The capture segment being written.
    pub segment: String,
    /// Bytes written to it.
    pub bytes: u64,
    /// Records written to it.
    pub records: u64,
    /// Navigation records written to it.
    pub nav_records: u64,
    /// The last write error (the recording stops on it; alert `recording`).
    pub error: Option<String>,
}

/// Free space on the recording's file system.
#[derive(Clone, Debug, Default, Serialize)]
pub struct DiskStatus {
    /// The folder measured.
    pub path: String,
    /// Bytes available.
    pub free_bytes: u64,
    /// Bytes in the file system.
    pub total_bytes: u64,
    /// Seconds of recording left at the current rate (when recording).
    pub seconds_left: Option<f64>,
    /// Whether the free space is below the alarm threshold.
    pub alarm: bool,
}

/// Saturation.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SaturationStatus {
    /// Pulses with a saturated sample, cumulative.
    pub pulses: u64,
    /// Fraction of the pulses in the last interval that were saturated.
    pub recent_fraction: f64,
}

/// An alert in force.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Alert {
    /// `navigation_gap`, `saturation`, `overrun`, `disk`, `input_down`, `recording`.
    pub kind: String,
    /// `warning` or `critical`.
    pub severity: String,
    /// What is wrong, for the operator.
    pub message: String,
}

/// One point of the charts (one per snapshot).
#[derive(Clone, Debug, Default, Serialize)]
pub struct HistoryPoint {
    /// Seconds since the Unix epoch.
    pub t: f64,
    /// Frames received per second.
    pub rate_in_hz: f64,
    /// Pulses processed per second.
    pub rate_processed_hz: f64,
    /// Pulses dropped per second.
    pub rate_dropped_hz: f64,
    /// Fullest queue, fraction 0..1.
    pub queue_fill: f64,
    /// End-to-end latency over the interval: median and 99th percentile, µs.
    pub e2e_p50_us: f64,
    /// See `e2e_p50_us`.
    pub e2e_p99_us: f64,
    /// Each stage's 99th percentile service time over the interval, µs, in `stages` order.
    pub stage_p99_us: Vec<f64>,
}

/// The last sampled pulse's first return segment at every processing step.
#[derive(Clone, Debug, Default, Serialize)]
pub struct WaveformView {
    /// Pulse id (digitizer).
    pub pulse_id: u64,
    /// GPS time of the pulse, seconds.
    pub gps_time: f64,
    /// Sample interval, ns.
    pub sample_ns: f64,
    /// Time of the segment's first sample after the pulse's reference time, ns.
    pub start_ns: f64,
    /// `raw` (V), then the signal after each stage in order (`denoise`, `deconvolve`, …).
    pub steps: Vec<WaveformStep>,
    /// The Gaussians fitted by a `decompose` stage.
    pub returns: Vec<FittedView>,
}

/// The segment after one step.
#[derive(Clone, Debug, Default, Serialize)]
pub struct WaveformStep {
    /// Step name.
    pub name: String,
    /// Samples, in the step's unit.
    pub values: Vec<f32>,
}

/// A fitted Gaussian return.
#[derive(Clone, Debug, Default, Serialize)]
pub struct FittedView {
    /// Peak time after the pulse's reference time, ns.
    pub time_ns: f64,
    /// Amplitude, V.
    pub amplitude: f32,
    /// Standard deviation, ns.
    pub sigma_ns: f64,
}
