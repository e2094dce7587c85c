//! The QC sampler: once a second it reads the pipeline's live counters and what every thread
//! published (`pipeline::LivePublish`), the inputs' and the recorder's state and the disk, and
//! publishes a [`QcSnapshot`] with its chart point to the [`QcHub`]; it raises the alerts. It
//! also runs the last sampled pulse through the configured stages one at a time, keeping the
//! signal after each, for the operator's waveform viewer — off the hot path, on its own copy.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Instant;

use super::recorder::RecorderState;
use super::{DaemonConfig, InputState, disk, now_ns};
use crate::nav::consumer::NavReport;
use crate::pipeline::stage::{DropCounts, Emitter, Stage};
use crate::pipeline::telemetry::{LatencyHistogram, StageTelemetry};
use crate::sink::SinkReports;
use crate::source::report::SourceReport;

/// The controls of the daemon's run.
type RunControl = crate::pipeline::RunControl<SourceReport, SinkReports, NavReport>;
/// What the daemon's run publishes.
type LivePublish = crate::pipeline::LivePublish<SourceReport, SinkReports, NavReport>;
use crate::pulse::{Pulse, PulsePool, SegmentKind};
use crate::qc::*;
use crate::stages::StageConfig;

/// Upper bounds of the latency histogram buckets, seconds (1 µs … 1 s, then +∞).
pub const BUCKETS_S: [f64; 20] = [
    1e-6,
    2.5e-6,
    5e-6,
    1e-5,
    2.5e-5,
    5e-5,
    1e-4,
    2.5e-4,
    5e-4,
    1e-3,
    2.5e-3,
    5e-3,
    1e-2,
    2.5e-2,
    5e-2,
    0.1,
    0.25,
    0.5,
    1.0,
    f64::INFINITY,
];

/// One input as the sampler sees it.
pub struct InputView {
    /// `frames` or `serial:<port>`.
    pub name: String,
    /// What it is (address, device).
    pub detail: String,
    /// Its live state.
    pub state: Arc<InputState>,
}

/// Builds and publishes the snapshots (see the module documentation).
pub struct Sampler {
    hub: Arc<QcHub>,
    control: RunControl,
    publish: Arc<LivePublish>,
    cfg: DaemonConfig,
    inputs: Vec<InputView>,
    serial_ports: Vec<u8>,
    recorder: Arc<RecorderState>,
    recorder_queue: Option<(crossbeam_channel::Receiver<super::frames::FrameMsg>, u64)>,
    capture_dir: PathBuf,
    segment: String,
    georeference: bool,
    drop_missed: bool,
    started: Instant,
    sequence: u64,
    last: Option<Counts>,
    prev_e2e: LatencyHistogram,
    prev_stages: Vec<LatencyHistogram>,
    viewer: WaveformViewer,
}

#[derive(Clone, Copy)]
struct Counts {
    at: Instant,
    frames: u64,
    processed: u64,
    dropped: u64,
    decoded: u64,
    saturated: u64,
    bytes: u64,
}

/// What the daemon tells the sampler about itself.
pub struct SamplerSetup {
    /// The daemon's configuration.
    pub cfg: DaemonConfig,
    /// Inputs.
    pub inputs: Vec<InputView>,
    /// Configured serial port numbers.
    pub serial_ports: Vec<u8>,
    /// The recorder's counters.
    pub recorder: Arc<RecorderState>,
    /// The frame channel into the recorder and its capacity (queue fill).
    pub recorder_queue: Option<(crossbeam_channel::Receiver<super::frames::FrameMsg>, u64)>,
    /// Folder of the capture segments.
    pub capture_dir: PathBuf,
    /// The current segment's file name.
    pub segment: String,
    /// Whether pulses are georeferenced, and whether missed ones are dropped.
    pub georeference: bool,
    /// `[georeference] on_missing = "drop"`.
    pub drop_missed: bool,
    /// The configured stages (for the waveform viewer).
    pub stages: Vec<StageConfig>,
}

impl Sampler {
    /// A sampler publishing into `hub` from `control` (whose `publish` must be set).
    pub fn new(hub: Arc<QcHub>, control: RunControl, setup: SamplerSetup) -> Self {
        let publish = control.publish.clone().unwrap_or_default();
        Sampler {
            hub,
            control,
            publish,
            cfg: setup.cfg,
            inputs: setup.inputs,
            serial_ports: setup.serial_ports,
            recorder: setup.recorder,
            recorder_queue: setup.recorder_queue,
            capture_dir: setup.capture_dir,
            segment: setup.segment,
            georeference: setup.georeference,
            drop_missed: setup.drop_missed,
            started: Instant::now(),
            sequence: 0,
            last: None,
            prev_e2e: LatencyHistogram::default(),
            prev_stages: Vec::new(),
            viewer: WaveformViewer::new(&setup.stages),
        }
    }

    /// Builds one snapshot and publishes it; returns it.
    pub fn tick(&mut self) -> Arc<QcSnapshot> {
        let now = Instant::now();
        let p = self.read_published();
        let stages = merged_stages(&p.workers);
        let missed = p
            .source
            .georeference()
            .map(|g| g.missed)
            .unwrap_or_default();
        let drops = self.drops(&stages, &missed);
        let dropped_total: u64 = drops.values().sum();
        let (counts, rates) = self.rates(now, dropped_total);
        let (stage_lat, e2e_lat, e2e_recent, stage_p99) = self.latencies(&stages, p.e2e);
        let queues = self.queues(&p.in_q, &p.out_q);
        let queue_fill = queues
            .iter()
            .filter(|q| q.capacity > 0)
            .map(|q| q.len as f64 / q.capacity as f64)
            .fold(0.0, f64::max);
        let now_ns = now_ns();
        let inputs = self.input_status(now_ns);
        let nav = self.nav_status(&p.nav, now_ns);
        let disk = self.disk_status(rates.bytes_per_s);
        let alerts = self.alerts(&inputs, &nav, &rates, &disk);
        let rec = &self.recorder;
        let frames_state = self.inputs.iter().find(|i| i.name == "frames");
        let georeference = p.source.georeference().unwrap_or_default();
        let snapshot = QcSnapshot {
            time_unix_s: now_ns as f64 / 1e9,
            uptime_s: self.started.elapsed().as_secs_f64(),
            version: env!("CARGO_PKG_VERSION").into(),
            survey: self.cfg.survey.clone(),
            sequence: self.sequence,
            inputs,
            pulses: PulseCounts {
                frames_received: counts.frames,
                frames_recorded: rec.frames_recorded.load(Ordering::Relaxed),
                frames_lost: frames_state.map_or(0, |i| i.state.lost.load(Ordering::Relaxed)),
                frames_bad: rec.bad_frames.load(Ordering::Relaxed),
                pulses_in: self.control.live.pulses_in.load(Ordering::Relaxed),
                pulses_processed: counts.processed,
                dropped_total,
                rate_in_hz: rates.rate_in,
                rate_processed_hz: rates.rate_out,
                rate_dropped_hz: rates.rate_drop,
            },
            drops,
            queues,
            stages: stage_lat,
            end_to_end: e2e_lat,
            nav,
            georeference: GeorefStatus {
                enabled: self.georeference,
                placed: georeference.georeferenced,
                missed,
                crs: georeference.output_crs,
            },
            tiles: tiles_status(&p.sink),
            recording: RecordingStatus {
                segment: self.segment.clone(),
                bytes: counts.bytes,
                records: rec.records.load(Ordering::Relaxed),
                nav_records: rec.nav_records.load(Ordering::Relaxed),
                error: rec.error(),
            },
            disk,
            saturation: SaturationStatus {
                pulses: counts.saturated,
                recent_fraction: rates.saturated_fraction,
            },
            alerts,
        };
        self.sequence += 1;
        let point = HistoryPoint {
            t: snapshot.time_unix_s,
            rate_in_hz: rates.rate_in,
            rate_processed_hz: rates.rate_out,
            rate_dropped_hz: rates.rate_drop,
            queue_fill,
            e2e_p50_us: e2e_recent.p50_ns as f64 / 1e3,
            e2e_p99_us: e2e_recent.p99_ns as f64 / 1e3,
            stage_p99_us: stage_p99,
        };
        self.show_sampled_pulse();
        self.hub.publish(snapshot, point);
        self.hub.snapshot()
    }

    /// A copy of what the pipeline's threads published last.
    fn read_published(&self) -> Published {
        fn get<T: Clone>(m: &std::sync::Mutex<T>) -> T {
            m.lock().unwrap_or_else(|e| e.into_inner()).clone()
        }
        let pb = &self.publish;
        Published {
            source: get(&pb.source),
            sink: get(&pb.sink),
            nav: get(&pb.nav),
            workers: get(&pb.workers),
            e2e: get(&pb.end_to_end),
            in_q: get(&pb.input_queues),
            out_q: get(&pb.output_queues),
        }
    }

    /// Pulses dropped by reason: the input edge's, the stages', and the georeferencing's
    /// misses when it drops them.
    fn drops(
        &self,
        stages: &[StageTelemetry],
        missed: &BTreeMap<String, u64>,
    ) -> BTreeMap<String, u64> {
        let mut drops: BTreeMap<String, u64> = BTreeMap::new();
        let input_dropped = self.control.live.input_dropped.load(Ordering::Relaxed);
        if input_dropped > 0 {
            drops.insert(
                crate::pipeline::runner::INPUT_QUEUE_FULL.into(),
                input_dropped,
            );
        }
        for s in stages {
            for (r, c) in s.dropped.iter() {
                *drops.entry(format!("{}.{r}", s.name)).or_insert(0) += c;
            }
        }
        if self.drop_missed {
            for (k, v) in missed {
                if *v > 0 {
                    drops.insert(format!("georeference.{k}"), *v);
                }
            }
        }
        drops
    }

    /// The counts now, and the rates since the last tick (per second; zero at the first).
    fn rates(&mut self, now: Instant, dropped_total: u64) -> (Counts, Rates) {
        let frames_state = self.inputs.iter().find(|i| i.name == "frames");
        let rec = &self.recorder;
        let counts = Counts {
            at: now,
            frames: frames_state.map_or(0, |i| i.state.frames.load(Ordering::Relaxed)),
            processed: self.control.live.pulses_out.load(Ordering::Relaxed),
            dropped: dropped_total,
            decoded: rec.decoded.load(Ordering::Relaxed),
            saturated: rec.saturated.load(Ordering::Relaxed),
            bytes: rec.bytes.load(Ordering::Relaxed),
        };
        let rates = match self.last {
            Some(l) => {
                let dt = (now - l.at).as_secs_f64().max(1e-3);
                let d = |a: u64, b: u64| a.saturating_sub(b) as f64;
                let decoded = d(counts.decoded, l.decoded);
                Rates {
                    rate_in: d(counts.frames, l.frames) / dt,
                    rate_out: d(counts.processed, l.processed) / dt,
                    rate_drop: d(counts.dropped, l.dropped) / dt,
                    saturated_fraction: if decoded > 0.0 {
                        d(counts.saturated, l.saturated) / decoded
                    } else {
                        0.0
                    },
                    bytes_per_s: d(counts.bytes, l.bytes) / dt,
                }
            }
            None => Rates::default(),
        };
        self.last = Some(counts);
        (counts, rates)
    }

    /// Latencies: cumulative for the snapshot (per stage, end to end), the last interval's for
    /// the chart (end to end, and each stage's p99 in µs).
    fn latencies(
        &mut self,
        stages: &[StageTelemetry],
        e2e: LatencyHistogram,
    ) -> (
        Vec<StageLatency>,
        StageLatency,
        crate::pipeline::telemetry::LatencySummary,
        Vec<f64>,
    ) {
        let stage_lat: Vec<StageLatency> =
            stages.iter().map(|s| latency(s.name, &s.service)).collect();
        let e2e_lat = latency("end_to_end", &e2e);
        let e2e_recent = e2e.since(&self.prev_e2e).summary();
        if self.prev_stages.len() != stages.len() {
            self.prev_stages = vec![LatencyHistogram::default(); stages.len()];
        }
        let stage_p99: Vec<f64> = stages
            .iter()
            .zip(&self.prev_stages)
            .map(|(s, p)| s.service.since(p).summary().p99_ns as f64 / 1e3)
            .collect();
        self.prev_e2e = e2e;
        self.prev_stages = stages.iter().map(|s| s.service.clone()).collect();
        (stage_lat, e2e_lat, e2e_recent, stage_p99)
    }

    /// The queues' fill: the recorder's, each worker's input edge, each worker's edge to the
    /// sink.
    fn queues(&self, in_q: &[(u64, u64)], out_q: &[u64]) -> Vec<QueueFill> {
        let mut queues = Vec::new();
        if let Some((rx, cap)) = &self.recorder_queue {
            queues.push(QueueFill {
                name: "recorder".into(),
                len: rx.len() as u64,
                capacity: *cap,
            });
        }
        for (i, (len, cap)) in in_q.iter().enumerate() {
            queues.push(QueueFill {
                name: format!("worker-{i}"),
                len: *len,
                capacity: *cap,
            });
        }
        let out_cap = in_q.first().map_or(0, |q| q.1);
        for (i, len) in out_q.iter().enumerate() {
            queues.push(QueueFill {
                name: format!("sink-from-worker-{i}"),
                len: *len,
                capacity: out_cap,
            });
        }
        queues
    }

    /// Each input's state (`now_ns`: host clock, ns since the epoch).
    fn input_status(&self, now_ns: u64) -> Vec<InputStatus> {
        self.inputs
            .iter()
            .map(|i| InputStatus {
                name: i.name.clone(),
                detail: i.detail.clone(),
                up: i.state.up.load(Ordering::Relaxed),
                last_data_age_s: age_s(now_ns, i.state.last_data_ns.load(Ordering::Relaxed)),
                bytes: i.state.bytes.load(Ordering::Relaxed),
                connects: i.state.connects.load(Ordering::Relaxed),
                failed_attempts: i.state.failed.load(Ordering::Relaxed),
                last_error: i.state.last_error(),
            })
            .collect()
    }

    /// Navigation per port: the configured ports first, then any other seen.
    fn nav_status(&self, nav: &NavReport, now_ns: u64) -> Vec<NavStatus> {
        let mut ports: Vec<u8> = self.serial_ports.clone();
        for p in nav.ports.keys() {
            if !ports.contains(p) {
                ports.push(*p);
            }
        }
        ports
            .iter()
            .map(|p| {
                let v = nav.ports.get(p).cloned().unwrap_or_default();
                let l = &v.latest;
                let kind = l.fix_kind.as_deref().unwrap_or("");
                let ins_kind = l.ins_kind.as_deref().unwrap_or("");
                NavStatus {
                    port: *p,
                    fix: l.fix,
                    fix_name: l.fix.map_or("no record yet".into(), |f| fix_name(kind, f)),
                    satellites: l.satellites,
                    ins_status: l.ins_status,
                    ins_name: l.ins_status.map_or("—".into(), |s| ins_name(ins_kind, s)),
                    last_packet_age_s: l.last_record_receive_ns.and_then(|ns| age_s(now_ns, ns)),
                    last_gps_sow: v.last_gps_time.map(|t| t.sow),
                    position: l.position,
                    samples: v.records,
                    rejected: v.rejected,
                }
            })
            .collect()
    }

    /// The recording disk's space, and its alarm at `byte_rate` (bytes/s recorded).
    fn disk_status(&self, byte_rate: f64) -> DiskStatus {
        let space = disk::space(&self.capture_dir).unwrap_or_default();
        DiskStatus {
            path: self.capture_dir.display().to_string(),
            free_bytes: space.free_bytes,
            total_bytes: space.total_bytes,
            seconds_left: disk::seconds_left(space, byte_rate),
            alarm: disk::alarm(
                space,
                byte_rate,
                self.cfg.disk_alarm_free_gb,
                self.cfg.disk_alarm_minutes,
            ),
        }
    }

    /// What the operator must look at: inputs down, navigation gaps, overrun, saturation, disk,
    /// the recording's error.
    fn alerts(
        &self,
        inputs: &[InputStatus],
        nav: &[NavStatus],
        rates: &Rates,
        disk: &DiskStatus,
    ) -> Vec<Alert> {
        let mut alerts = Vec::new();
        let mut alert = |kind: &str, critical: bool, message: String| {
            alerts.push(Alert {
                kind: kind.into(),
                severity: if critical { "critical" } else { "warning" }.into(),
                message,
            })
        };
        for i in inputs.iter().filter(|i| !i.up) {
            alert(
                "input_down",
                false,
                format!(
                    "{} ({}) is down, retrying{}",
                    i.name,
                    i.detail,
                    i.last_error
                        .as_ref()
                        .map_or(String::new(), |e| format!(": {e}"))
                ),
            );
        }
        for n in nav {
            match n.last_packet_age_s {
                Some(a) if a > self.cfg.nav_alarm_s => alert(
                    "navigation_gap",
                    a > 10.0 * self.cfg.nav_alarm_s,
                    format!(
                        "no navigation record on port {} for {a:.1} s; pulses in the gap are {}",
                        n.port,
                        if self.drop_missed {
                            "dropped from processing (recorded)"
                        } else {
                            "processed without geometry (recorded)"
                        }
                    ),
                ),
                None if self.started.elapsed().as_secs_f64() > self.cfg.nav_alarm_s => alert(
                    "navigation_gap",
                    true,
                    format!("no navigation record received on port {} yet", n.port),
                ),
                _ => {}
            }
        }
        if rates.rate_drop > 0.0 {
            alert(
                "overrun",
                rates.rate_drop > 0.1 * rates.rate_in.max(1.0),
                format!(
                    "processing falls behind: {:.0} pulses/s dropped from processing (every \
                     frame is recorded)",
                    rates.rate_drop
                ),
            );
        }
        if rates.saturated_fraction > self.cfg.saturation_alarm {
            alert(
                "saturation",
                false,
                format!(
                    "{:.1} % of the last second's pulses saturated the digitizer",
                    100.0 * rates.saturated_fraction
                ),
            );
        }
        if disk.alarm {
            alert(
                "disk",
                disk.free_bytes < 1_000_000_000,
                format!(
                    "{:.1} GB free on {}{}",
                    disk.free_bytes as f64 / 1e9,
                    self.capture_dir.display(),
                    disk.seconds_left.map_or(String::new(), |s| format!(
                        ", {:.0} min of recording left",
                        s / 60.0
                    ))
                ),
            );
        }
        if let Some(e) = self.recorder.error() {
            alert("recording", true, e);
        }
        alerts
    }

    /// Runs the last sampled pulse through the stages for the waveform viewer, once per pulse.
    fn show_sampled_pulse(&mut self) {
        let sampled = self
            .publish
            .sampled_pulse
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .as_ref()
            .map(|(t, p)| (*t, p.clone()));
        if let Some((t, p)) = sampled
            && let Some(view) = self.viewer.view(t, &p)
        {
            self.hub.set_waveform(view);
        }
    }
}

/// What the pipeline's threads published, copied.
struct Published {
    source: SourceReport,
    sink: SinkReports,
    nav: NavReport,
    workers: Vec<Vec<StageTelemetry>>,
    e2e: LatencyHistogram,
    in_q: Vec<(u64, u64)>,
    out_q: Vec<u64>,
}

/// Rates since the last tick.
#[derive(Clone, Copy, Default)]
struct Rates {
    /// Frames received per second.
    rate_in: f64,
    /// Pulses processed per second.
    rate_out: f64,
    /// Pulses dropped per second.
    rate_drop: f64,
    /// Share of the pulses decoded that saturated the digitizer, 0..1.
    saturated_fraction: f64,
    /// Bytes recorded per second.
    bytes_per_s: f64,
}

/// How long ago a host time was, s (`None` for 0: never).
fn age_s(now_ns: u64, ns: u64) -> Option<f64> {
    (ns > 0).then(|| now_ns.saturating_sub(ns) as f64 / 1e9)
}

/// Stage telemetry merged over the workers.
fn merged_stages(workers: &[Vec<StageTelemetry>]) -> Vec<StageTelemetry> {
    let mut stages: Vec<StageTelemetry> = Vec::new();
    for w in workers {
        if stages.is_empty() {
            stages = w.iter().map(|t| StageTelemetry::new(t.name)).collect();
        }
        for (acc, t) in stages.iter_mut().zip(w) {
            acc.merge(t);
        }
    }
    stages
}

/// The tiles and the coverage map, from the voxel store's report.
fn tiles_status(sink: &SinkReports) -> TilesStatus {
    let vox = sink.voxels();
    let mut tiles = TilesStatus {
        open: 0,
        closed: vox
            .and_then(|v| v.tiles.as_ref())
            .map_or(0, |t| t.lifecycle.closed),
        tile_m: [0.0, 0.0],
        cells: Vec::new(),
    };
    if let Some(cov) = vox.and_then(|v| v.coverage.as_ref()) {
        tiles.tile_m = cov.tile_m;
        let area = (cov.tile_m[0] * cov.tile_m[1]).max(1e-9);
        for (i, c) in cov.cells.iter().enumerate() {
            let open = c[3] == 1;
            tiles.open += open as u64;
            tiles.cells.push(TileCell {
                tx: c[0],
                ty: c[1],
                state: if open { "open" } else { "closed" }.into(),
                pulses: c[2] as u64,
                density_per_m2: c[2] as f64 / area,
                canopy_height_m: cov.canopy_max_m.get(i).copied().flatten().map(f64::from),
            });
        }
    }
    tiles
}

/// A latency histogram as the QC shows it.
fn latency(name: &str, h: &LatencyHistogram) -> StageLatency {
    let s = h.summary();
    StageLatency {
        name: name.into(),
        count: s.count,
        p50_us: s.p50_ns as f64 / 1e3,
        p99_us: s.p99_ns as f64 / 1e3,
        p999_us: s.p999_ns as f64 / 1e3,
        max_us: s.max_ns as f64 / 1e3,
        sum_s: s.mean_ns * s.count as f64 / 1e9,
        buckets: BUCKETS_S
            .iter()
            .map(|&b| {
                let n = if b.is_finite() {
                    h.count_at_or_below((b * 1e9) as u64)
                } else {
                    s.count
                };
                (b, n)
            })
            .collect(),
    }
}

/// The fix in words: GGA quality for NMEA records, the aiding flag for PASHR, the position
/// type for NovAtel ones (the code itself is beside it in the snapshot).
pub fn fix_name(kind: &str, fix: u32) -> String {
    let nmea = matches!(kind, "Gga" | "Rmc" | "Gst" | "Vtg" | "Zda" | "Hdt");
    let name = if nmea {
        match fix {
            0 => "no fix",
            1 => "GPS",
            2 => "DGPS",
            3 => "PPS",
            4 => "RTK fixed",
            5 => "RTK float",
            6 => "dead reckoning",
            7 => "manual",
            8 => "simulation",
            _ => "unknown",
        }
    } else if kind == "Pashr" {
        match fix {
            0 => "no aiding",
            1 => "GNSS aiding",
            2 => "GNSS + GAMS aiding",
            _ => "unknown",
        }
    } else {
        match fix {
            0 => "no solution",
            1 => "fixed position",
            8 => "Doppler velocity",
            16 => "single point",
            17 => "pseudorange differential",
            18 => "SBAS",
            32..=34 => "RTK float",
            48..=50 => "RTK fixed",
            51 => "INS + RTK (wide lane)",
            52 => "INS",
            53 => "INS + single point",
            54 => "INS + pseudorange differential",
            55 => "INS + RTK float",
            56 => "INS + RTK fixed",
            68 | 69 => "PPP",
            77 => "PPP basic",
            _ => "other",
        }
    };
    name.into()
}

/// The INS status in words (NovAtel INS status; PASHR IMU status: 0 out, 1 satisfactory).
pub fn ins_name(kind: &str, status: u32) -> String {
    let name = if kind == "Pashr" {
        match status {
            0 => "IMU out",
            1 => "IMU satisfactory",
            _ => "other",
        }
    } else {
        match status {
            0 => "inactive",
            1 => "aligning",
            2 => "high variance",
            3 => "solution good",
            6 => "solution free",
            7 => "alignment complete",
            8 => "determining orientation",
            9 => "waiting for initial position",
            10 => "waiting for azimuth",
            11 => "initialising biases",
            12 => "motion detect",
            _ => "other",
        }
    };
    name.into()
}

/// Reruns a sampled pulse through the stages one at a time (see the module documentation).
struct WaveformViewer {
    stages: Vec<(&'static str, Box<dyn Stage>)>,
    pool: PulsePool,
    last: Option<Instant>,
}

impl WaveformViewer {
    fn new(configs: &[StageConfig]) -> Self {
        WaveformViewer {
            // Built once already when the run was put together (`stages::Chain::prepare`).
            stages: configs
                .iter()
                .filter_map(|c| Some((c.kind(), c.build().ok()?)))
                .collect(),
            pool: PulsePool::new(4),
            last: None,
        }
    }

    /// The view of `sample` (taken at `taken`), unless it was shown already.
    fn view(&mut self, taken: Instant, sample: &Pulse) -> Option<WaveformView> {
        if self.last == Some(taken) {
            return None;
        }
        self.last = Some(taken);
        let seg = sample
            .segments
            .iter()
            .position(|s| s.kind == SegmentKind::Return)?;
        let s = sample.segments[seg];
        let mut view = WaveformView {
            pulse_id: sample.pulse_id,
            gps_time: sample.gps_time,
            sample_ns: sample.sample_ns,
            start_ns: s.start_ns,
            steps: vec![WaveformStep {
                name: "raw".into(),
                values: sample
                    .raw_of(seg)
                    .iter()
                    .map(|&c| sample.counts_to_volts(c))
                    .collect(),
            }],
            returns: Vec::new(),
        };
        let mut p = self.pool.take();
        p.copy_from(sample);
        p.signal.clear();
        p.returns.clear();
        p.calibration = None;
        p.noise = Default::default();
        let mut out: Vec<Box<Pulse>> = Vec::with_capacity(2);
        let (mut dropped, mut errors) = (DropCounts::default(), 0u64);
        let mut current = Some(p);
        for (name, stage) in &mut self.stages {
            let Some(p) = current.take() else { break };
            let mut em = Emitter::new(&mut out, &self.pool, &mut dropped, &mut errors);
            if stage.process(p, &mut em).is_err() {
                break;
            }
            current = out.pop();
            for q in out.drain(..) {
                self.pool.give(q);
            }
            if let Some(p) = &current
                && p.signal.len() == p.raw.len()
                && view
                    .steps
                    .last()
                    .is_none_or(|l| l.values != p.signal_of(seg))
            {
                view.steps.push(WaveformStep {
                    name: (*name).into(),
                    values: p.signal_of(seg).to_vec(),
                });
            }
        }
        if let Some(p) = current {
            view.returns = p
                .returns
                .iter()
                .filter(|r| r.segment as usize == seg)
                .map(|r| FittedView {
                    time_ns: r.time_ns,
                    amplitude: r.amplitude,
                    sigma_ns: r.sigma_bins as f64 * p.sample_ns,
                })
                .collect();
            self.pool.give(p);
        }
        Some(view)
    }
}
