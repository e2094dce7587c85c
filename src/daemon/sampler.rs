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
use crate::pipeline::stage::{DropCounts, Emitter, Stage};
use crate::pipeline::telemetry::{LatencyHistogram, StageTelemetry};
use crate::pipeline::{LivePublish, RunControl};
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
        let live = &self.control.live;
        let pb = &self.publish;
        let source = pb.source.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let sink = pb.sink.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let nav = pb.nav.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let workers = pb.workers.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let e2e = pb
            .end_to_end
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let in_q = pb
            .input_queues
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let out_q = pb
            .output_queues
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();

        // Stage telemetry merged over workers.
        let mut stages: Vec<StageTelemetry> = Vec::new();
        for w in &workers {
            if stages.is_empty() {
                stages = w.iter().map(|t| StageTelemetry::new(t.name)).collect();
            }
            for (acc, t) in stages.iter_mut().zip(w) {
                acc.merge(t);
            }
        }

        // Drops by reason.
        let mut drops: BTreeMap<String, u64> = BTreeMap::new();
        let input_dropped = live.input_dropped.load(Ordering::Relaxed);
        if input_dropped > 0 {
            drops.insert(
                crate::pipeline::runner::INPUT_QUEUE_FULL.into(),
                input_dropped,
            );
        }
        for s in &stages {
            for (r, c) in s.dropped.iter() {
                *drops.entry(format!("{}.{r}", s.name)).or_insert(0) += c;
            }
        }
        let g = &source["georeference"];
        let missed: BTreeMap<String, u64> = g["missed"]
            .as_object()
            .map(|m| {
                m.iter()
                    .map(|(k, v)| (k.clone(), v.as_u64().unwrap_or(0)))
                    .collect()
            })
            .unwrap_or_default();
        if self.drop_missed {
            for (k, v) in &missed {
                if *v > 0 {
                    drops.insert(format!("georeference.{k}"), *v);
                }
            }
        }
        let dropped_total: u64 = drops.values().sum();

        // Counts and rates.
        let frames_state = self.inputs.iter().find(|i| i.name == "frames");
        let frames = frames_state.map_or(0, |i| i.state.frames.load(Ordering::Relaxed));
        let rec = &self.recorder;
        let counts = Counts {
            at: now,
            frames,
            processed: live.pulses_out.load(Ordering::Relaxed),
            dropped: dropped_total,
            decoded: rec.decoded.load(Ordering::Relaxed),
            saturated: rec.saturated.load(Ordering::Relaxed),
            bytes: rec.bytes.load(Ordering::Relaxed),
        };
        let (rate_in, rate_out, rate_drop, sat_frac, byte_rate) = match self.last {
            Some(l) => {
                let dt = (now - l.at).as_secs_f64().max(1e-3);
                let d = |a: u64, b: u64| a.saturating_sub(b) as f64;
                let decoded = d(counts.decoded, l.decoded);
                (
                    d(counts.frames, l.frames) / dt,
                    d(counts.processed, l.processed) / dt,
                    d(counts.dropped, l.dropped) / dt,
                    if decoded > 0.0 {
                        d(counts.saturated, l.saturated) / decoded
                    } else {
                        0.0
                    },
                    d(counts.bytes, l.bytes) / dt,
                )
            }
            None => (0.0, 0.0, 0.0, 0.0, 0.0),
        };
        self.last = Some(counts);

        // Latencies: cumulative for the snapshot, the last interval for the chart.
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

        // Queues.
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
        let queue_fill = queues
            .iter()
            .filter(|q| q.capacity > 0)
            .map(|q| q.len as f64 / q.capacity as f64)
            .fold(0.0, f64::max);

        // Inputs.
        let now_ns = now_ns();
        let age = |ns: u64| (ns > 0).then(|| now_ns.saturating_sub(ns) as f64 / 1e9);
        let inputs: Vec<InputStatus> = self
            .inputs
            .iter()
            .map(|i| InputStatus {
                name: i.name.clone(),
                detail: i.detail.clone(),
                up: i.state.up.load(Ordering::Relaxed),
                last_data_age_s: age(i.state.last_data_ns.load(Ordering::Relaxed)),
                bytes: i.state.bytes.load(Ordering::Relaxed),
                connects: i.state.connects.load(Ordering::Relaxed),
                failed_attempts: i.state.failed.load(Ordering::Relaxed),
                last_error: i.state.last_error(),
            })
            .collect();

        // Navigation per port (configured ports first, then any other seen).
        let mut ports: Vec<u8> = self.serial_ports.clone();
        if let Some(m) = nav["ports"].as_object() {
            for k in m.keys() {
                if let Ok(p) = k.parse::<u8>()
                    && !ports.contains(&p)
                {
                    ports.push(p);
                }
            }
        }
        let nav_status: Vec<NavStatus> = ports
            .iter()
            .map(|p| {
                let v = &nav["ports"][p.to_string()];
                let l = &v["latest"];
                let fix = l["fix"].as_u64().map(|x| x as u32);
                let ins = l["ins_status"].as_u64().map(|x| x as u32);
                let kind = l["fix_kind"].as_str().unwrap_or("");
                let ins_kind = l["ins_kind"].as_str().unwrap_or("");
                NavStatus {
                    port: *p,
                    fix,
                    fix_name: fix.map_or("no record yet".into(), |f| fix_name(kind, f)),
                    satellites: l["satellites"].as_u64().map(|x| x as u32),
                    ins_status: ins,
                    ins_name: ins.map_or("—".into(), |s| ins_name(ins_kind, s)),
                    last_packet_age_s: l["last_record_receive_ns"].as_u64().and_then(age),
                    last_gps_sow: v["last_gps_time"]["sow"].as_f64(),
                    position: l["position"].as_array().and_then(|a| {
                        Some([
                            a.first()?.as_f64()?,
                            a.get(1)?.as_f64()?,
                            a.get(2)?.as_f64()?,
                        ])
                    }),
                    samples: v["records"].as_u64().unwrap_or(0),
                    rejected: v["rejected"].as_u64().unwrap_or(0),
                }
            })
            .collect();

        // Tiles and the coverage map.
        let vox = &sink["voxels"];
        let mut tiles = TilesStatus {
            open: 0,
            closed: vox["tiles"]["closed"].as_u64().unwrap_or(0),
            tile_m: [0.0, 0.0],
            cells: Vec::new(),
        };
        if let Some(cov) = vox.get("coverage") {
            let tm = [
                cov["tile_m"][0].as_f64().unwrap_or(0.0),
                cov["tile_m"][1].as_f64().unwrap_or(0.0),
            ];
            tiles.tile_m = tm;
            let area = (tm[0] * tm[1]).max(1e-9);
            let canopy = cov["canopy_max_m"].as_array();
            for (i, c) in cov["cells"].as_array().into_iter().flatten().enumerate() {
                let f = |i: usize| c[i].as_i64().unwrap_or(0);
                let open = f(3) == 1;
                tiles.open += open as u64;
                tiles.cells.push(TileCell {
                    tx: f(0),
                    ty: f(1),
                    state: if open { "open" } else { "closed" }.into(),
                    pulses: f(2) as u64,
                    density_per_m2: f(2) as f64 / area,
                    canopy_height_m: canopy.and_then(|a| a.get(i)).and_then(|h| h.as_f64()),
                });
            }
        }

        // Disk.
        let space = disk::space(&self.capture_dir).unwrap_or_default();
        let disk_alarm = disk::alarm(
            space,
            byte_rate,
            self.cfg.disk_alarm_free_gb,
            self.cfg.disk_alarm_minutes,
        );
        let disk = DiskStatus {
            path: self.capture_dir.display().to_string(),
            free_bytes: space.free_bytes,
            total_bytes: space.total_bytes,
            seconds_left: disk::seconds_left(space, byte_rate),
            alarm: disk_alarm,
        };

        // Alerts.
        let mut alerts = Vec::new();
        let mut alert = |kind: &str, critical: bool, message: String| {
            alerts.push(Alert {
                kind: kind.into(),
                severity: if critical { "critical" } else { "warning" }.into(),
                message,
            })
        };
        for i in &inputs {
            if !i.up {
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
        }
        for n in &nav_status {
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
        if rate_drop > 0.0 {
            alert(
                "overrun",
                rate_drop > 0.1 * rate_in.max(1.0),
                format!(
                    "processing falls behind: {rate_drop:.0} pulses/s dropped from processing \
                     (every frame is recorded)"
                ),
            );
        }
        if sat_frac > self.cfg.saturation_alarm {
            alert(
                "saturation",
                false,
                format!(
                    "{:.1} % of the last second's pulses saturated the digitizer",
                    100.0 * sat_frac
                ),
            );
        }
        if disk_alarm {
            alert(
                "disk",
                space.free_bytes < 1_000_000_000,
                format!(
                    "{:.1} GB free on {}{}",
                    space.free_bytes as f64 / 1e9,
                    self.capture_dir.display(),
                    disk.seconds_left.map_or(String::new(), |s| format!(
                        ", {:.0} min of recording left",
                        s / 60.0
                    ))
                ),
            );
        }
        if let Some(e) = rec.error() {
            alert("recording", true, e);
        }

        let snapshot = QcSnapshot {
            time_unix_s: now_ns as f64 / 1e9,
            uptime_s: self.started.elapsed().as_secs_f64(),
            version: env!("CARGO_PKG_VERSION").into(),
            survey: self.cfg.survey.clone(),
            sequence: self.sequence,
            inputs,
            pulses: PulseCounts {
                frames_received: frames,
                frames_recorded: rec.frames_recorded.load(Ordering::Relaxed),
                frames_lost: frames_state.map_or(0, |i| i.state.lost.load(Ordering::Relaxed)),
                frames_bad: rec.bad_frames.load(Ordering::Relaxed),
                pulses_in: live.pulses_in.load(Ordering::Relaxed),
                pulses_processed: counts.processed,
                dropped_total,
                rate_in_hz: rate_in,
                rate_processed_hz: rate_out,
                rate_dropped_hz: rate_drop,
            },
            drops,
            queues,
            stages: stage_lat,
            end_to_end: e2e_lat,
            nav: nav_status,
            georeference: GeorefStatus {
                enabled: self.georeference,
                placed: g["georeferenced"].as_u64().unwrap_or(0),
                missed,
                crs: g["output_crs"].as_str().map(str::to_string),
            },
            tiles,
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
                recent_fraction: sat_frac,
            },
            alerts,
        };
        self.sequence += 1;
        let point = HistoryPoint {
            t: snapshot.time_unix_s,
            rate_in_hz: rate_in,
            rate_processed_hz: rate_out,
            rate_dropped_hz: rate_drop,
            queue_fill,
            e2e_p50_us: e2e_recent.p50_ns as f64 / 1e3,
            e2e_p99_us: e2e_recent.p99_ns as f64 / 1e3,
            stage_p99_us: stage_p99,
        };
        let sampled = pb
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
        self.hub.publish(snapshot, point);
        self.hub.snapshot()
    }
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
