//! The snapshot as Prometheus text (exposition format 0.0.4), served at `/metrics`.
//!
//! Every metric is named `fwlidar_…` with its unit in the name (`_seconds`, `_bytes`, `_hertz`,
//! `_ratio`) and `_total` on counters. Counters are cumulative since the daemon started; gauges
//! are the value at the snapshot. Latencies are real histograms (`_bucket{le=…}`, `_sum`,
//! `_count`) built from [`StageLatency::buckets`]. The full list, with units, is in `docs/qc.md`.
//!
//! The families are the table `METRICS`, written in its order by one loop.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;

use super::snapshot::{InputStatus, NavStatus, QcSnapshot, QueueFill, StageLatency};

/// The content type of [`render`]'s output.
pub const CONTENT_TYPE: &str = "text/plain; version=0.0.4; charset=utf-8";

/// Renders `s` in the Prometheus text exposition format 0.0.4 (every family with `# HELP` and
/// `# TYPE`, one sample a line, `\n` line ends, a final line end).
pub fn render(s: &QcSnapshot) -> String {
    let mut w = Writer::default();
    for m in METRICS {
        w.metric(m, s);
    }
    w.out
}

/// One metric family of the exposition: its name, type and help, and how its samples are
/// read from the snapshot.
struct Metric {
    /// Family name: `fwlidar_…`, the unit in the name, `_total` on counters.
    name: &'static str,
    /// Prometheus type (`# TYPE`).
    kind: Kind,
    /// Help text (`# HELP`).
    help: &'static str,
    /// Where its samples come from.
    read: Read,
}

/// Prometheus metric type.
#[derive(Clone, Copy)]
enum Kind {
    Counter,
    Gauge,
    Histogram,
}

impl Kind {
    /// The type's name in `# TYPE`.
    fn as_str(self) -> &'static str {
        match self {
            Kind::Counter => "counter",
            Kind::Gauge => "gauge",
            Kind::Histogram => "histogram",
        }
    }
}

/// How a family's samples are read from the snapshot.
enum Read {
    /// One unlabelled sample of this value.
    Value(fn(&QcSnapshot) -> f64),
    /// One sample per reason of a count by reason, labelled `reason`, in the map's order.
    ByReason(fn(&QcSnapshot) -> &BTreeMap<String, u64>),
    /// One sample per queue, labelled `queue`.
    PerQueue(fn(&QueueFill) -> f64),
    /// One sample per input, labelled `input`; none for an input whose value is `None`.
    PerInput(fn(&InputStatus) -> Option<f64>),
    /// One sample per navigation port, labelled `port` and, when given, a second label that
    /// names the value; none for a port whose value is `None`.
    PerPort(fn(&NavStatus) -> Option<PortValue<'_>>),
    /// One sample with the one label named here, the label's value read with the sample's
    /// value (no sample when that is `None`).
    Labelled(&'static str, fn(&QcSnapshot) -> (&str, Option<f64>)),
    /// Samples written by the function (labels of their own, histograms).
    Written(fn(&QcSnapshot, &mut Family<'_>)),
}

/// A navigation port's sample: the value and, when given, a second label (name, value) that
/// names it.
type PortValue<'a> = (f64, Option<(&'static str, &'a str)>);

/// Every family of the exposition, in the order written.
const METRICS: &[Metric] = &[
    // Daemon.
    Metric {
        name: "fwlidar_build_info",
        kind: Kind::Gauge,
        help: "Always 1; the labels name the fwlidar version and the survey.",
        read: Read::Written(build_info),
    },
    Metric {
        name: "fwlidar_uptime_seconds",
        kind: Kind::Gauge,
        help: "Seconds since the daemon started.",
        read: Read::Value(|s| s.uptime_s),
    },
    Metric {
        name: "fwlidar_snapshot_timestamp_seconds",
        kind: Kind::Gauge,
        help: "When the snapshot was taken, seconds since the Unix epoch.",
        read: Read::Value(|s| s.time_unix_s),
    },
    Metric {
        name: "fwlidar_snapshot_sequence",
        kind: Kind::Gauge,
        help: "Snapshot number, from 0, one more a snapshot.",
        read: Read::Value(|s| s.sequence as f64),
    },
    // Frames and pulses.
    Metric {
        name: "fwlidar_frames_received_total",
        kind: Kind::Counter,
        help: "Digitizer frames received from the network.",
        read: Read::Value(|s| s.pulses.frames_received as f64),
    },
    Metric {
        name: "fwlidar_frames_recorded_total",
        kind: Kind::Counter,
        help: "Frames written to the capture.",
        read: Read::Value(|s| s.pulses.frames_recorded as f64),
    },
    Metric {
        name: "fwlidar_frames_lost_total",
        kind: Kind::Counter,
        help: "Frames lost on the network (sequence gaps).",
        read: Read::Value(|s| s.pulses.frames_lost as f64),
    },
    Metric {
        name: "fwlidar_frames_bad_total",
        kind: Kind::Counter,
        help: "Frames that are not valid digitizer frames (recorded, not processed).",
        read: Read::Value(|s| s.pulses.frames_bad as f64),
    },
    Metric {
        name: "fwlidar_pulses_in_total",
        kind: Kind::Counter,
        help: "Pulses that entered processing.",
        read: Read::Value(|s| s.pulses.pulses_in as f64),
    },
    Metric {
        name: "fwlidar_pulses_processed_total",
        kind: Kind::Counter,
        help: "Pulses that left the sink with every output written.",
        read: Read::Value(|s| s.pulses.pulses_processed as f64),
    },
    Metric {
        name: "fwlidar_pulses_dropped_total",
        kind: Kind::Counter,
        help: "Pulses dropped from processing, by reason.",
        read: Read::ByReason(|s| &s.drops),
    },
    Metric {
        name: "fwlidar_frames_received_rate_hertz",
        kind: Kind::Gauge,
        help: "Frames received per second over the last snapshot interval.",
        read: Read::Value(|s| s.pulses.rate_in_hz),
    },
    Metric {
        name: "fwlidar_pulses_processed_rate_hertz",
        kind: Kind::Gauge,
        help: "Pulses processed per second over the last snapshot interval.",
        read: Read::Value(|s| s.pulses.rate_processed_hz),
    },
    Metric {
        name: "fwlidar_pulses_dropped_rate_hertz",
        kind: Kind::Gauge,
        help: "Pulses dropped per second over the last snapshot interval.",
        read: Read::Value(|s| s.pulses.rate_dropped_hz),
    },
    // Queues.
    Metric {
        name: "fwlidar_queue_length",
        kind: Kind::Gauge,
        help: "Items in a bounded queue now.",
        read: Read::PerQueue(|q| q.len as f64),
    },
    Metric {
        name: "fwlidar_queue_capacity",
        kind: Kind::Gauge,
        help: "Capacity of a bounded queue, items.",
        read: Read::PerQueue(|q| q.capacity as f64),
    },
    // Latency.
    Metric {
        name: "fwlidar_stage_latency_seconds",
        kind: Kind::Histogram,
        help: "Service time of one pulse in a processing stage, seconds, since the start.",
        read: Read::Written(stage_latencies),
    },
    Metric {
        name: "fwlidar_end_to_end_latency_seconds",
        kind: Kind::Histogram,
        help: "Frame arrival to the sink (every output done), seconds, since the start.",
        read: Read::Written(|s, f| f.histogram(None, &s.end_to_end)),
    },
    // Inputs.
    Metric {
        name: "fwlidar_input_up",
        kind: Kind::Gauge,
        help: "1 when the input is connected and delivering, else 0.",
        read: Read::PerInput(|i| Some(bool01(i.up))),
    },
    Metric {
        name: "fwlidar_input_last_data_age_seconds",
        kind: Kind::Gauge,
        help: "Seconds since the input's last data (absent before any came).",
        read: Read::PerInput(|i| i.last_data_age_s),
    },
    Metric {
        name: "fwlidar_input_received_bytes_total",
        kind: Kind::Counter,
        help: "Bytes received on the input.",
        read: Read::PerInput(|i| Some(i.bytes as f64)),
    },
    Metric {
        name: "fwlidar_input_connects_total",
        kind: Kind::Counter,
        help: "Connections made on the input (TCP peers accepted, serial device opens).",
        read: Read::PerInput(|i| Some(i.connects as f64)),
    },
    Metric {
        name: "fwlidar_input_failed_attempts_total",
        kind: Kind::Counter,
        help: "Connection or open attempts on the input that failed.",
        read: Read::PerInput(|i| Some(i.failed_attempts as f64)),
    },
    // Navigation.
    Metric {
        name: "fwlidar_nav_last_packet_age_seconds",
        kind: Kind::Gauge,
        help: "Seconds since the port's last decoded navigation record (host clock).",
        read: Read::PerPort(|n| n.last_packet_age_s.map(|age| (age, None))),
    },
    Metric {
        name: "fwlidar_nav_fix_quality",
        kind: Kind::Gauge,
        help: "Fix quality code of the last record (GGA quality or NovAtel position type); the \
               label names it.",
        read: Read::PerPort(|n| {
            n.fix
                .map(|fix| (fix as f64, Some(("fix", n.fix_name.as_str()))))
        }),
    },
    Metric {
        name: "fwlidar_nav_satellites",
        kind: Kind::Gauge,
        help: "Satellites used in the last fix.",
        read: Read::PerPort(|n| n.satellites.map(|sats| (sats as f64, None))),
    },
    Metric {
        name: "fwlidar_nav_ins_status",
        kind: Kind::Gauge,
        help: "INS status code of the last record; the label names it.",
        read: Read::PerPort(|n| {
            n.ins_status
                .map(|ins| (ins as f64, Some(("status", n.ins_name.as_str()))))
        }),
    },
    Metric {
        name: "fwlidar_nav_samples_total",
        kind: Kind::Counter,
        help: "Navigation samples decoded on the port.",
        read: Read::PerPort(|n| Some((n.samples as f64, None))),
    },
    Metric {
        name: "fwlidar_nav_rejected_total",
        kind: Kind::Counter,
        help: "Navigation records rejected on the port (bad checksum, malformed).",
        read: Read::PerPort(|n| Some((n.rejected as f64, None))),
    },
    // Georeferencing.
    Metric {
        name: "fwlidar_georeference_enabled",
        kind: Kind::Gauge,
        help: "1 when georeferencing is on, else 0.",
        read: Read::Value(|s| bool01(s.georeference.enabled)),
    },
    Metric {
        name: "fwlidar_georeference_placed_total",
        kind: Kind::Counter,
        help: "Pulses georeferenced.",
        read: Read::Value(|s| s.georeference.placed as f64),
    },
    Metric {
        name: "fwlidar_georeference_missed_total",
        kind: Kind::Counter,
        help: "Pulses not georeferenced, by reason.",
        read: Read::ByReason(|s| &s.georeference.missed),
    },
    // Tiles.
    Metric {
        name: "fwlidar_tiles_open",
        kind: Kind::Gauge,
        help: "Voxel tiles open now.",
        read: Read::Value(|s| s.tiles.open as f64),
    },
    Metric {
        name: "fwlidar_tiles_closed_total",
        kind: Kind::Counter,
        help: "Voxel tiles closed (written).",
        read: Read::Value(|s| s.tiles.closed as f64),
    },
    // Recording and disk.
    Metric {
        name: "fwlidar_recording_segment_bytes",
        kind: Kind::Gauge,
        help: "Bytes written to the capture segment being written.",
        read: Read::Labelled("segment", |s| {
            (&s.recording.segment, Some(s.recording.bytes as f64))
        }),
    },
    Metric {
        name: "fwlidar_recording_segment_records",
        kind: Kind::Gauge,
        help: "Records written to the capture segment being written.",
        read: Read::Labelled("segment", |s| {
            (&s.recording.segment, Some(s.recording.records as f64))
        }),
    },
    Metric {
        name: "fwlidar_recording_error",
        kind: Kind::Gauge,
        help: "1 when the recording stopped on a write error, else 0.",
        read: Read::Value(|s| bool01(s.recording.error.is_some())),
    },
    Metric {
        name: "fwlidar_disk_free_bytes",
        kind: Kind::Gauge,
        help: "Bytes available on the recording's file system.",
        read: Read::Labelled("path", |s| (&s.disk.path, Some(s.disk.free_bytes as f64))),
    },
    Metric {
        name: "fwlidar_disk_total_bytes",
        kind: Kind::Gauge,
        help: "Size of the recording's file system, bytes.",
        read: Read::Labelled("path", |s| (&s.disk.path, Some(s.disk.total_bytes as f64))),
    },
    Metric {
        name: "fwlidar_disk_time_left_seconds",
        kind: Kind::Gauge,
        help: "Seconds of recording left at the current rate (absent when not recording).",
        read: Read::Labelled("path", |s| (&s.disk.path, s.disk.seconds_left)),
    },
    Metric {
        name: "fwlidar_disk_alarm",
        kind: Kind::Gauge,
        help: "1 when the free space is below the alarm threshold, else 0.",
        read: Read::Value(|s| bool01(s.disk.alarm)),
    },
    // Saturation.
    Metric {
        name: "fwlidar_saturated_pulses_total",
        kind: Kind::Counter,
        help: "Pulses with a raw sample at the digitizer's full scale.",
        read: Read::Value(|s| s.saturation.pulses as f64),
    },
    Metric {
        name: "fwlidar_saturated_pulses_ratio",
        kind: Kind::Gauge,
        help: "Fraction (0..1) of the last interval's pulses that were saturated.",
        read: Read::Value(|s| s.saturation.recent_fraction),
    },
    // Alerts.
    Metric {
        name: "fwlidar_alert",
        kind: Kind::Gauge,
        help: "1 for every alert in force (kind and severity in the labels).",
        read: Read::Written(alerts_in_force),
    },
    Metric {
        name: "fwlidar_alerts",
        kind: Kind::Gauge,
        help: "Number of alerts in force.",
        read: Read::Value(|s| s.alerts.len() as f64),
    },
];

/// `fwlidar_build_info`: one sample of 1 labelled with the version and the survey.
fn build_info(s: &QcSnapshot, f: &mut Family<'_>) {
    f.sample(&[("version", &s.version), ("survey", &s.survey)], 1.0);
}

/// `fwlidar_stage_latency_seconds`: one histogram series per stage, labelled `stage`. Two
/// stages of one name would make duplicate series: the first is kept.
fn stage_latencies(s: &QcSnapshot, f: &mut Family<'_>) {
    let mut seen = BTreeSet::new();
    for st in &s.stages {
        if seen.insert(st.name.as_str()) {
            f.histogram(Some(("stage", &st.name)), st);
        }
    }
}

/// `fwlidar_alert`: a sample of 1 per (kind, severity) in force, in that order, however many
/// alerts share it.
fn alerts_in_force(s: &QcSnapshot, f: &mut Family<'_>) {
    let alerts: BTreeSet<(&str, &str)> = s
        .alerts
        .iter()
        .map(|a| (a.kind.as_str(), a.severity.as_str()))
        .collect();
    for (kind, severity) in alerts {
        f.sample(&[("kind", kind), ("severity", severity)], 1.0);
    }
}

/// 1 for true, 0 for false.
fn bool01(b: bool) -> f64 {
    if b { 1.0 } else { 0.0 }
}

/// The samples of one family being written: the writer and the family's name.
struct Family<'w> {
    w: &'w mut Writer,
    name: &'static str,
}

impl Family<'_> {
    /// A sample of the family with these labels.
    fn sample(&mut self, labels: &[(&str, &str)], value: f64) {
        self.w.sample(self.name, labels, value);
    }

    /// A histogram series of the family ([`Writer::histogram`]).
    fn histogram(&mut self, label: Option<(&str, &str)>, h: &StageLatency) {
        self.w.histogram(self.name, label, h);
    }
}

/// Builds the text, one family after another.
#[derive(Default)]
struct Writer {
    out: String,
}

impl Writer {
    /// Family `m` of snapshot `s`: `# HELP`, `# TYPE`, then its samples.
    fn metric(&mut self, m: &Metric, s: &QcSnapshot) {
        let name = m.name;
        self.family(name, m.kind.as_str(), m.help);
        match m.read {
            Read::Value(value) => self.sample(name, &[], value(s)),
            Read::ByReason(counts) => {
                for (reason, n) in counts(s) {
                    self.sample(name, &[("reason", reason)], *n as f64);
                }
            }
            Read::PerQueue(value) => {
                for q in &s.queues {
                    self.sample(name, &[("queue", &q.name)], value(q));
                }
            }
            Read::PerInput(value) => {
                for i in &s.inputs {
                    if let Some(v) = value(i) {
                        self.sample(name, &[("input", &i.name)], v);
                    }
                }
            }
            Read::PerPort(value) => {
                for n in &s.nav {
                    if let Some((v, named)) = value(n) {
                        let port = n.port.to_string();
                        match named {
                            Some(label) => self.sample(name, &[("port", &port), label], v),
                            None => self.sample(name, &[("port", &port)], v),
                        }
                    }
                }
            }
            Read::Labelled(label, read) => {
                if let (key, Some(v)) = read(s) {
                    self.sample(name, &[(label, key)], v);
                }
            }
            Read::Written(write) => write(s, &mut Family { w: self, name }),
        }
    }

    /// `# HELP` and `# TYPE` of a family.
    fn family(&mut self, name: &str, kind: &str, help: &str) {
        let _ = writeln!(self.out, "# HELP {name} {}", escape_help(help));
        let _ = writeln!(self.out, "# TYPE {name} {kind}");
    }

    /// One sample line: the name, the labels (values escaped) and the value.
    fn sample(&mut self, name: &str, labels: &[(&str, &str)], value: f64) {
        self.out.push_str(name);
        if !labels.is_empty() {
            self.out.push('{');
            for (i, (k, v)) in labels.iter().enumerate() {
                if i > 0 {
                    self.out.push(',');
                }
                self.out.push_str(k);
                self.out.push_str("=\"");
                escape_label_into(&mut self.out, v);
                self.out.push('"');
            }
            self.out.push('}');
        }
        self.out.push(' ');
        push_value(&mut self.out, value);
        self.out.push('\n');
    }

    /// The `_bucket`, `_sum` and `_count` samples of one histogram series. The buckets are
    /// cumulative; a missing +Inf bucket is added with `count`, and `_count` is the +Inf
    /// bucket's count, as the format requires.
    fn histogram(&mut self, name: &str, label: Option<(&str, &str)>, h: &StageLatency) {
        let bucket = format!("{name}_bucket");
        let mut last = f64::NEG_INFINITY;
        let mut total = None;
        for &(bound, n) in &h.buckets {
            // `null` from JSON or a NaN is the +Inf bound; skip bounds out of order.
            let bound = if bound.is_nan() { f64::INFINITY } else { bound };
            if bound <= last {
                continue;
            }
            last = bound;
            let le = format_value(bound);
            let mut labels: Vec<(&str, &str)> = label.into_iter().collect();
            labels.push(("le", &le));
            self.sample(&bucket, &labels, n as f64);
            if bound == f64::INFINITY {
                total = Some(n);
                break;
            }
        }
        let total = match total {
            Some(n) => n,
            None => {
                let mut labels: Vec<(&str, &str)> = label.into_iter().collect();
                labels.push(("le", "+Inf"));
                self.sample(&bucket, &labels, h.count as f64);
                h.count
            }
        };
        let labels: Vec<(&str, &str)> = label.into_iter().collect();
        self.sample(&format!("{name}_sum"), &labels, h.sum_s);
        self.sample(&format!("{name}_count"), &labels, total as f64);
    }
}

/// A float as the format writes it: `NaN`, `+Inf`, `-Inf` or a decimal number.
fn format_value(v: f64) -> String {
    let mut s = String::new();
    push_value(&mut s, v);
    s
}

fn push_value(out: &mut String, v: f64) {
    if v.is_nan() {
        out.push_str("NaN");
    } else if v == f64::INFINITY {
        out.push_str("+Inf");
    } else if v == f64::NEG_INFINITY {
        out.push_str("-Inf");
    } else {
        let _ = write!(out, "{v}");
    }
}

/// Label values escape `\`, `"` and line feeds.
fn escape_label_into(out: &mut String, v: &str) {
    for c in v.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '"' => out.push_str("\\\""),
            '\n' => out.push_str("\\n"),
            c => out.push(c),
        }
    }
}

/// Help text escapes `\` and line feeds.
fn escape_help(v: &str) -> String {
    v.replace('\\', "\\\\").replace('\n', "\\n")
}

#[cfg(test)]
pub(crate) mod tests {
    use std::collections::{BTreeMap, HashMap};

    use super::*;
    use crate::qc::snapshot::*;

    /// A snapshot with every part filled, awkward label values included.
    pub(crate) fn filled_snapshot(sequence: u64) -> QcSnapshot {
        let hist = |name: &str, scale: f64| StageLatency {
            name: name.into(),
            count: 1000,
            p50_us: 40.0 * scale,
            p99_us: 90.0 * scale,
            p999_us: 120.0 * scale,
            max_us: 300.0 * scale,
            sum_s: 0.05 * scale,
            buckets: vec![
                (1e-5 * scale, 10),
                (1e-4 * scale, 990),
                (1e-3 * scale, 1000),
                (f64::INFINITY, 1000),
            ],
        };
        let mut drops = BTreeMap::new();
        drops.insert("input_queue_full".to_string(), 7);
        drops.insert("decompose.no_return".to_string(), 3);
        let mut missed = BTreeMap::new();
        missed.insert("navigation_gap".to_string(), 11);
        QcSnapshot {
            time_unix_s: 1_790_000_000.5,
            uptime_s: 3723.25,
            version: "0.1.0".into(),
            survey: "Block \"A\" \\ north\nline".into(),
            sequence,
            inputs: vec![
                InputStatus {
                    name: "frames".into(),
                    detail: "udp 127.0.0.1:5000".into(),
                    up: true,
                    last_data_age_s: Some(0.01),
                    bytes: 123_456_789,
                    connects: 1,
                    failed_attempts: 0,
                    last_error: None,
                },
                InputStatus {
                    name: "serial:2".into(),
                    detail: "/dev/gnss0 @ 115200".into(),
                    up: false,
                    last_data_age_s: None,
                    bytes: 0,
                    connects: 0,
                    failed_attempts: 5,
                    last_error: Some("device /dev/gnss0 absent".into()),
                },
            ],
            pulses: PulseCounts {
                frames_received: 12_355,
                frames_recorded: 12_355,
                frames_lost: 2,
                frames_bad: 1,
                pulses_in: 12_355,
                pulses_processed: 12_345,
                dropped_total: 10,
                rate_in_hz: 100_000.0,
                rate_processed_hz: 99_990.5,
                rate_dropped_hz: 9.5,
            },
            drops,
            queues: vec![
                QueueFill {
                    name: "recorder".into(),
                    len: 12,
                    capacity: 1024,
                },
                QueueFill {
                    name: "worker-0".into(),
                    len: 3,
                    capacity: 256,
                },
            ],
            stages: vec![hist("denoise", 1.0), hist("decompose", 3.0)],
            end_to_end: hist("end_to_end", 10.0),
            nav: vec![NavStatus {
                port: 2,
                fix: Some(4),
                fix_name: "RTK fixed".into(),
                satellites: Some(14),
                ins_status: Some(3),
                ins_name: "solution good".into(),
                last_packet_age_s: Some(0.25),
                last_gps_sow: Some(345_600.5),
                position: Some([47.1, 8.5, 1200.0]),
                samples: 5000,
                rejected: 2,
            }],
            georeference: GeorefStatus {
                enabled: true,
                placed: 12_000,
                missed,
                crs: Some("EPSG:2056".into()),
            },
            tiles: TilesStatus {
                open: 3,
                closed: 5,
                tile_m: [250.0, 250.0],
                cells: vec![
                    TileCell {
                        tx: 10,
                        ty: -3,
                        state: "open".into(),
                        pulses: 400,
                        density_per_m2: 0.0064,
                        canopy_height_m: None,
                    },
                    TileCell {
                        tx: 11,
                        ty: -3,
                        state: "closed".into(),
                        pulses: 900,
                        density_per_m2: 0.0144,
                        canopy_height_m: Some(21.5),
                    },
                ],
            },
            recording: RecordingStatus {
                segment: "capture-0001.fwc".into(),
                bytes: 987_654_321,
                records: 12_355,
                nav_records: 5000,
                error: None,
            },
            disk: DiskStatus {
                path: "/data".into(),
                free_bytes: 500_000_000_000,
                total_bytes: 1_000_000_000_000,
                seconds_left: Some(36_000.0),
                alarm: false,
            },
            saturation: SaturationStatus {
                pulses: 42,
                recent_fraction: 0.002,
            },
            alerts: vec![
                Alert {
                    kind: "input_down".into(),
                    severity: "critical".into(),
                    message: "serial:2 is down".into(),
                },
                Alert {
                    kind: "saturation".into(),
                    severity: "warning".into(),
                    message: "0.2 % of pulses saturated".into(),
                },
            ],
        }
    }

    /// One parsed sample line.
    #[derive(Debug)]
    pub(crate) struct Sample {
        name: String,
        labels: Vec<(String, String)>,
        value: f64,
    }

    fn is_name(s: &str, allow_colon: bool) -> bool {
        let mut chars = s.chars();
        match chars.next() {
            Some(c) if c.is_ascii_alphabetic() || c == '_' || (allow_colon && c == ':') => {}
            _ => return false,
        }
        chars.all(|c| c.is_ascii_alphanumeric() || c == '_' || (allow_colon && c == ':'))
    }

    fn parse_value(s: &str) -> Result<f64, String> {
        match s {
            "NaN" => Ok(f64::NAN),
            "+Inf" => Ok(f64::INFINITY),
            "-Inf" => Ok(f64::NEG_INFINITY),
            _ => s.parse::<f64>().map_err(|e| format!("value {s:?}: {e}")),
        }
    }

    /// Parses a sample line per the 0.0.4 text format.
    fn parse_sample(line: &str) -> Result<Sample, String> {
        let name_end = line
            .find(['{', ' '])
            .ok_or_else(|| "no value".to_string())?;
        let name = &line[..name_end];
        if !is_name(name, true) {
            return Err(format!("bad metric name {name:?}"));
        }
        let mut rest = &line[name_end..];
        let mut labels = Vec::new();
        if let Some(r) = rest.strip_prefix('{') {
            rest = r;
            loop {
                if let Some(r) = rest.strip_prefix('}') {
                    rest = r;
                    break;
                }
                let eq = rest.find('=').ok_or("label without =")?;
                let lname = &rest[..eq];
                if !is_name(lname, false) || lname.starts_with("__") {
                    return Err(format!("bad label name {lname:?}"));
                }
                rest = rest[eq + 1..]
                    .strip_prefix('"')
                    .ok_or("label value not quoted")?;
                let mut value = String::new();
                let mut chars = rest.char_indices();
                let end = loop {
                    match chars.next() {
                        None => return Err("unterminated label value".into()),
                        Some((i, '"')) => break i,
                        Some((_, '\\')) => match chars.next() {
                            Some((_, '\\')) => value.push('\\'),
                            Some((_, '"')) => value.push('"'),
                            Some((_, 'n')) => value.push('\n'),
                            other => return Err(format!("bad escape {other:?}")),
                        },
                        Some((_, '\n')) => return Err("raw line feed in label".into()),
                        Some((_, c)) => value.push(c),
                    }
                };
                if labels.iter().any(|(n, _): &(String, String)| n == lname) {
                    return Err(format!("label {lname} twice"));
                }
                labels.push((lname.to_string(), value));
                rest = &rest[end + 1..];
                if let Some(r) = rest.strip_prefix(',') {
                    rest = r;
                } else if !rest.starts_with('}') {
                    return Err("expected , or } after a label".into());
                }
            }
        }
        let rest = rest.strip_prefix(' ').ok_or("no space before the value")?;
        let mut parts = rest.split(' ');
        let value = parse_value(parts.next().ok_or("no value")?)?;
        if let Some(ts) = parts.next() {
            ts.parse::<i64>().map_err(|_| "bad timestamp")?;
        }
        if parts.next().is_some() {
            return Err("trailing fields".into());
        }
        Ok(Sample {
            name: name.to_string(),
            labels,
            value,
        })
    }

    /// Checks the whole text per the format and the rules Prometheus applies: every sample
    /// belongs to a family declared once by `# TYPE` before it, histograms have increasing
    /// `le` ending at +Inf with `_count` equal to it, no series twice. Returns the samples.
    pub(crate) fn check_exposition(text: &str) -> Vec<Sample> {
        assert!(text.ends_with('\n'), "no final line feed");
        let mut types: HashMap<String, String> = HashMap::new();
        let mut helps: HashMap<String, usize> = HashMap::new();
        let mut series = std::collections::HashSet::new();
        let mut samples = Vec::new();
        let mut current: Option<String> = None;
        for (no, line) in text.lines().enumerate() {
            let ctx = |e: String| format!("line {}: {e}: {line:?}", no + 1);
            assert!(!line.is_empty(), "{}", ctx("empty line".into()));
            if let Some(rest) = line.strip_prefix("# ") {
                let mut it = rest.splitn(3, ' ');
                let kw = it.next().unwrap();
                let name = it.next().unwrap_or_default();
                let tail = it.next().unwrap_or_default();
                assert!(is_name(name, true), "{}", ctx("bad name".into()));
                match kw {
                    "HELP" => {
                        assert!(!tail.is_empty(), "{}", ctx("empty help".into()));
                        *helps.entry(name.into()).or_default() += 1;
                        assert_eq!(helps[name], 1, "{}", ctx("HELP twice".into()));
                    }
                    "TYPE" => {
                        assert!(
                            ["counter", "gauge", "histogram", "summary", "untyped"].contains(&tail),
                            "{}",
                            ctx("bad type".into())
                        );
                        assert!(
                            types.insert(name.into(), tail.into()).is_none(),
                            "{}",
                            ctx("TYPE twice".into())
                        );
                        assert!(
                            helps.contains_key(name),
                            "{}",
                            ctx("TYPE before HELP".into())
                        );
                        current = Some(name.into());
                    }
                    _ => {}
                }
                continue;
            }
            assert!(!line.starts_with('#'), "{}", ctx("bad comment".into()));
            let s = parse_sample(line).unwrap_or_else(|e| panic!("{}", ctx(e)));
            let family = current.clone().expect("sample before any TYPE");
            let kind = &types[&family];
            let ok = if kind == "histogram" {
                [
                    format!("{family}_bucket"),
                    format!("{family}_sum"),
                    format!("{family}_count"),
                ]
                .contains(&s.name)
            } else {
                s.name == family
            };
            assert!(ok, "{}", ctx(format!("not of family {family}")));
            if kind == "counter" {
                assert!(
                    s.name.ends_with("_total"),
                    "{}",
                    ctx("counter without _total".into())
                );
                assert!(s.value >= 0.0, "{}", ctx("negative counter".into()));
            }
            let mut key = s.labels.clone();
            key.sort();
            assert!(
                series.insert((s.name.clone(), key)),
                "{}",
                ctx("series twice".into())
            );
            samples.push(s);
        }
        // Histogram structure.
        for (family, kind) in &types {
            if kind != "histogram" {
                continue;
            }
            type Labels = Vec<(String, String)>;
            let mut groups: BTreeMap<Labels, Vec<(f64, f64)>> = BTreeMap::new();
            let mut counts: BTreeMap<Labels, f64> = BTreeMap::new();
            for s in &samples {
                let base: Vec<_> = s
                    .labels
                    .iter()
                    .filter(|(k, _)| k != "le")
                    .cloned()
                    .collect();
                if s.name == format!("{family}_bucket") {
                    let le = &s.labels.iter().find(|(k, _)| k == "le").expect("no le").1;
                    groups
                        .entry(base)
                        .or_default()
                        .push((parse_value(le).unwrap(), s.value));
                } else if s.name == format!("{family}_count") {
                    counts.insert(base, s.value);
                }
            }
            // A family with no series (no stages yet) is valid.
            for (labels, buckets) in &groups {
                assert!(
                    buckets
                        .windows(2)
                        .all(|w| w[0].0 < w[1].0 && w[0].1 <= w[1].1),
                    "{family} {labels:?}: buckets not increasing"
                );
                let last = buckets.last().unwrap();
                assert_eq!(last.0, f64::INFINITY, "{family}: last bucket not +Inf");
                assert_eq!(
                    Some(&last.1),
                    counts.get(labels),
                    "{family}: _count != +Inf"
                );
            }
        }
        samples
    }

    fn value(samples: &[Sample], name: &str, labels: &[(&str, &str)]) -> f64 {
        samples
            .iter()
            .find(|s| {
                s.name == name
                    && labels
                        .iter()
                        .all(|(k, v)| s.labels.iter().any(|(a, b)| a == k && b == v))
            })
            .unwrap_or_else(|| panic!("no sample {name} {labels:?}"))
            .value
    }

    #[test]
    fn filled_snapshot_renders_valid_exposition_with_the_values() {
        let text = render(&filled_snapshot(17));
        let s = check_exposition(&text);
        assert_eq!(value(&s, "fwlidar_snapshot_sequence", &[]), 17.0);
        assert_eq!(value(&s, "fwlidar_uptime_seconds", &[]), 3723.25);
        assert_eq!(value(&s, "fwlidar_frames_received_total", &[]), 12_355.0);
        assert_eq!(value(&s, "fwlidar_frames_lost_total", &[]), 2.0);
        assert_eq!(value(&s, "fwlidar_frames_bad_total", &[]), 1.0);
        assert_eq!(value(&s, "fwlidar_pulses_processed_total", &[]), 12_345.0);
        assert_eq!(
            value(
                &s,
                "fwlidar_pulses_dropped_total",
                &[("reason", "input_queue_full")]
            ),
            7.0
        );
        assert_eq!(
            value(
                &s,
                "fwlidar_pulses_dropped_total",
                &[("reason", "decompose.no_return")]
            ),
            3.0
        );
        assert_eq!(
            value(&s, "fwlidar_frames_received_rate_hertz", &[]),
            100_000.0
        );
        assert_eq!(
            value(&s, "fwlidar_pulses_processed_rate_hertz", &[]),
            99_990.5
        );
        assert_eq!(
            value(&s, "fwlidar_queue_length", &[("queue", "recorder")]),
            12.0
        );
        assert_eq!(
            value(&s, "fwlidar_queue_capacity", &[("queue", "worker-0")]),
            256.0
        );
        assert_eq!(
            value(
                &s,
                "fwlidar_stage_latency_seconds_bucket",
                &[("stage", "denoise"), ("le", "0.0001")]
            ),
            990.0
        );
        assert_eq!(
            value(
                &s,
                "fwlidar_stage_latency_seconds_bucket",
                &[("stage", "decompose"), ("le", "+Inf")]
            ),
            1000.0
        );
        assert_eq!(
            value(
                &s,
                "fwlidar_stage_latency_seconds_count",
                &[("stage", "denoise")]
            ),
            1000.0
        );
        assert_eq!(
            value(&s, "fwlidar_end_to_end_latency_seconds_sum", &[]),
            0.5
        );
        assert_eq!(value(&s, "fwlidar_input_up", &[("input", "frames")]), 1.0);
        assert_eq!(value(&s, "fwlidar_input_up", &[("input", "serial:2")]), 0.0);
        assert_eq!(
            value(&s, "fwlidar_nav_last_packet_age_seconds", &[("port", "2")]),
            0.25
        );
        assert_eq!(
            value(
                &s,
                "fwlidar_nav_fix_quality",
                &[("port", "2"), ("fix", "RTK fixed")]
            ),
            4.0
        );
        assert_eq!(value(&s, "fwlidar_nav_satellites", &[("port", "2")]), 14.0);
        assert_eq!(value(&s, "fwlidar_nav_ins_status", &[("port", "2")]), 3.0);
        assert_eq!(value(&s, "fwlidar_tiles_open", &[]), 3.0);
        assert_eq!(value(&s, "fwlidar_tiles_closed_total", &[]), 5.0);
        assert_eq!(value(&s, "fwlidar_disk_free_bytes", &[]), 5e11);
        assert_eq!(value(&s, "fwlidar_disk_total_bytes", &[]), 1e12);
        assert_eq!(value(&s, "fwlidar_disk_alarm", &[]), 0.0);
        assert_eq!(value(&s, "fwlidar_saturated_pulses_total", &[]), 42.0);
        assert_eq!(value(&s, "fwlidar_alert", &[("kind", "input_down")]), 1.0);
        assert_eq!(
            value(
                &s,
                "fwlidar_alert",
                &[("kind", "saturation"), ("severity", "warning")]
            ),
            1.0
        );
        // The awkward survey name survives escaping and parsing.
        assert_eq!(
            value(
                &s,
                "fwlidar_build_info",
                &[("survey", "Block \"A\" \\ north\nline")]
            ),
            1.0
        );
        assert!(text.contains(r#"survey="Block \"A\" \\ north\nline""#));
        assert!(text.contains("# TYPE fwlidar_stage_latency_seconds histogram\n"));
        assert!(text.contains("# TYPE fwlidar_pulses_dropped_total counter\n"));
    }

    #[test]
    fn empty_snapshot_renders_valid_exposition() {
        let text = render(&QcSnapshot::default());
        let s = check_exposition(&text);
        // The end-to-end histogram still has its +Inf bucket.
        assert_eq!(
            value(
                &s,
                "fwlidar_end_to_end_latency_seconds_bucket",
                &[("le", "+Inf")]
            ),
            0.0
        );
    }

    #[test]
    fn histogram_without_inf_bound_gets_one_and_odd_values_are_spelled_right() {
        let mut snap = QcSnapshot {
            end_to_end: StageLatency {
                name: "e2e".into(),
                count: 5,
                sum_s: 0.25,
                buckets: vec![(0.001, 2), (0.01, 4)],
                ..Default::default()
            },
            ..Default::default()
        };
        snap.saturation.recent_fraction = f64::NAN;
        let text = render(&snap);
        let s = check_exposition(&text);
        assert_eq!(
            value(
                &s,
                "fwlidar_end_to_end_latency_seconds_bucket",
                &[("le", "+Inf")]
            ),
            5.0
        );
        assert_eq!(
            value(&s, "fwlidar_end_to_end_latency_seconds_count", &[]),
            5.0
        );
        assert!(text.contains("fwlidar_saturated_pulses_ratio NaN\n"));
    }

    #[test]
    fn duplicate_alerts_make_one_series() {
        let mut snap = QcSnapshot::default();
        for _ in 0..2 {
            snap.alerts.push(Alert {
                kind: "disk".into(),
                severity: "warning".into(),
                message: "low".into(),
            });
        }
        let s = check_exposition(&render(&snap));
        assert_eq!(value(&s, "fwlidar_alerts", &[]), 2.0);
    }

    /// [`filled_snapshot`] with the rarer shapes: absent values, a recording error, a disk
    /// alarm, georeferencing off, two stages of one name, histograms with a NaN bound, a bound
    /// out of order and no +Inf bound, a NaN ratio, an alert twice, a navigation port without a
    /// fix, no drops.
    fn odd_snapshot() -> QcSnapshot {
        let mut s = filled_snapshot(3);
        s.inputs[0].last_data_age_s = None;
        s.drops.clear();
        s.recording.error = Some("No space left on device".into());
        s.disk.seconds_left = None;
        s.disk.alarm = true;
        s.georeference.enabled = false;
        let mut again = s.stages[0].clone();
        again.buckets = vec![(1e-4, 5), (f64::NAN, 6)];
        s.stages.push(again);
        s.stages[1].buckets[3].0 = f64::NAN;
        s.end_to_end.buckets = vec![(0.001, 2), (0.0005, 3), (0.01, 4)];
        s.end_to_end.count = 5;
        s.saturation.recent_fraction = f64::NAN;
        s.uptime_s = f64::INFINITY;
        s.alerts.push(s.alerts[0].clone());
        s.nav.push(NavStatus {
            port: 3,
            fix: None,
            fix_name: String::new(),
            satellites: None,
            ins_status: None,
            ins_name: String::new(),
            last_packet_age_s: None,
            samples: 0,
            rejected: 9,
            ..Default::default()
        });
        s
    }

    /// The fixture `src/qc/testdata/<name>`, the text the hand-written renderer made before
    /// the metrics became a table.
    fn fixture(name: &str) -> String {
        let path = format!("{}/src/qc/testdata/{name}", env!("CARGO_MANIFEST_DIR"));
        std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
    }

    #[test]
    fn rendered_text_is_byte_for_byte_the_fixtures() {
        for (snap, name) in [
            (filled_snapshot(17), "metrics_filled.prom"),
            (odd_snapshot(), "metrics_odd.prom"),
            (QcSnapshot::default(), "metrics_empty.prom"),
        ] {
            let text = render(&snap);
            check_exposition(&text);
            assert_eq!(text, fixture(name), "{name}");
        }
    }
}
