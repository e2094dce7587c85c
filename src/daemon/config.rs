//! `[daemon]` of a run configuration: where the digitizer frames come from, the survey and its
//! recording, the QC server's address and the alarm thresholds.

use std::net::SocketAddr;

use serde::{Deserialize, Serialize};

use crate::core::validate::{Validate, Validator, field};

/// Where digitizer frames come from (`docs/formats.md`, "Live digitizer stream").
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FrameInput {
    /// One frame per UDP datagram, received on this address.
    Udp(SocketAddr),
    /// Frames back to back on a TCP stream; the daemon listens and takes one peer at a time.
    TcpListen(SocketAddr),
    /// Frames on a TCP stream; the daemon connects (and reconnects) to the digitizer.
    TcpConnect(SocketAddr),
}

impl FrameInput {
    /// Parses `udp:HOST:PORT`, `tcp-listen:HOST:PORT` or `tcp-connect:HOST:PORT`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let (kind, addr) = s.split_once(':').ok_or_else(|| {
            format!(
                "expected udp:HOST:PORT, tcp-listen:HOST:PORT or tcp-connect:HOST:PORT, got {s:?}"
            )
        })?;
        let make: fn(SocketAddr) -> FrameInput = match kind {
            "udp" => FrameInput::Udp,
            "tcp-listen" => FrameInput::TcpListen,
            "tcp-connect" => FrameInput::TcpConnect,
            _ => {
                return Err(format!(
                    "unknown frame input kind {kind:?}: udp, tcp-listen or tcp-connect"
                ));
            }
        };
        let addr: SocketAddr = addr
            .parse()
            .map_err(|e| format!("{addr:?} is not an IP address and port ({e})"))?;
        Ok(make(addr))
    }
}

impl std::fmt::Display for FrameInput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FrameInput::Udp(a) => write!(f, "udp {a}"),
            FrameInput::TcpListen(a) => write!(f, "tcp-listen {a}"),
            FrameInput::TcpConnect(a) => write!(f, "tcp-connect {a}"),
        }
    }
}

/// `[daemon]`: the on-board daemon's inputs, recording, QC server and alarms.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DaemonConfig {
    /// Digitizer frames: `udp:HOST:PORT`, `tcp-listen:HOST:PORT` or `tcp-connect:HOST:PORT`.
    /// Default none (the daemon records navigation only and reports the frame input absent).
    #[serde(default)]
    pub frames: Option<String>,
    /// Survey name: names the capture segments (`<survey>_NNNN.fwcap`) and the voxel store's
    /// run; a restart with the same name continues the survey. Default `survey`.
    #[serde(default = "default_survey")]
    pub survey: String,
    /// Folder of the capture segments; relative paths are inside the output folder. Default
    /// `capture`.
    #[serde(default = "default_capture_dir")]
    pub capture_dir: String,
    /// Hand the recording to the disk at least this often, milliseconds (what a crash can
    /// lose); 1..=10000. Default 200.
    #[serde(default = "default_flush_ms")]
    pub flush_ms: u32,
    /// Sync the recording to the disk at each flush (fsync), not only to the OS. Default true.
    #[serde(default = "yes")]
    pub fsync: bool,
    /// Frames buffered between the network receiver and the recorder (count); when full, the
    /// receiver waits and the sender or the kernel's socket buffer holds the rest. 16..=4194304.
    /// Default 65536.
    #[serde(default = "default_recorder_queue")]
    pub recorder_queue: usize,
    /// Time between attempts to reach an absent frame input (bind, accept, connect),
    /// milliseconds. Default 500.
    #[serde(default = "default_retry_ms")]
    pub retry_ms: u64,
    /// QC server address (`HOST:PORT`); `off` for none. Default `127.0.0.1:8080` (this machine
    /// only; name another address to serve the cockpit network).
    #[serde(default = "default_qc")]
    pub qc: String,
    /// Disk alarm: free space below this, gigabytes (10^9 bytes). Default 2.
    #[serde(default = "default_disk_alarm_gb")]
    pub disk_alarm_free_gb: f64,
    /// Disk alarm: less than this many minutes of recording left at the current rate. Default
    /// 15.
    #[serde(default = "default_disk_alarm_minutes")]
    pub disk_alarm_minutes: f64,
    /// Navigation alarm: no navigation record for this long, seconds. Default 1.
    #[serde(default = "default_nav_alarm_s")]
    pub nav_alarm_s: f64,
    /// Saturation alarm: more than this fraction of the last second's pulses saturated. Default
    /// 0.01.
    #[serde(default = "default_saturation_alarm")]
    pub saturation_alarm: f64,
}

fn default_survey() -> String {
    "survey".into()
}
fn default_capture_dir() -> String {
    "capture".into()
}
fn default_flush_ms() -> u32 {
    200
}
fn yes() -> bool {
    true
}
fn default_recorder_queue() -> usize {
    65_536
}
fn default_retry_ms() -> u64 {
    500
}
fn default_qc() -> String {
    "127.0.0.1:8080".into()
}
fn default_disk_alarm_gb() -> f64 {
    2.0
}
fn default_disk_alarm_minutes() -> f64 {
    15.0
}
fn default_nav_alarm_s() -> f64 {
    1.0
}
fn default_saturation_alarm() -> f64 {
    0.01
}

impl Default for DaemonConfig {
    fn default() -> Self {
        DaemonConfig {
            frames: None,
            survey: default_survey(),
            capture_dir: default_capture_dir(),
            flush_ms: default_flush_ms(),
            fsync: true,
            recorder_queue: default_recorder_queue(),
            retry_ms: default_retry_ms(),
            qc: default_qc(),
            disk_alarm_free_gb: default_disk_alarm_gb(),
            disk_alarm_minutes: default_disk_alarm_minutes(),
            nav_alarm_s: default_nav_alarm_s(),
            saturation_alarm: default_saturation_alarm(),
        }
    }
}

impl DaemonConfig {
    /// The frame input, when configured and valid.
    pub fn frame_input(&self) -> Option<FrameInput> {
        self.frames
            .as_deref()
            .and_then(|s| FrameInput::parse(s).ok())
    }

    /// The QC server's address; `None` for `off`.
    pub fn qc_address(&self) -> Option<SocketAddr> {
        (self.qc != "off").then(|| self.qc.parse().ok()).flatten()
    }
}

impl Validate for DaemonConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        if let Some(f) = &self.frames
            && let Err(e) = FrameInput::parse(f)
        {
            v.report(field(path, "frames"), e);
        }
        let name_ok = !self.survey.is_empty()
            && self
                .survey
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            && !self.survey.starts_with('.');
        v.require(
            name_ok,
            field(path, "survey"),
            format!(
                "must be letters, digits, '-', '_' or '.' (it names files), got {:?}",
                self.survey
            ),
        );
        v.require(
            !self.capture_dir.trim().is_empty(),
            field(path, "capture_dir"),
            "must name a folder",
        );
        v.require(
            (1..=10_000).contains(&self.flush_ms),
            field(path, "flush_ms"),
            format!("must be in 1..=10000 ms, got {}", self.flush_ms),
        );
        v.require(
            (16..=4_194_304).contains(&self.recorder_queue),
            field(path, "recorder_queue"),
            format!(
                "must be in 16..=4194304 frames, got {}",
                self.recorder_queue
            ),
        );
        v.require(
            (1..=60_000).contains(&self.retry_ms),
            field(path, "retry_ms"),
            format!("must be in 1..=60000 ms, got {}", self.retry_ms),
        );
        v.require(
            self.qc == "off" || self.qc.parse::<SocketAddr>().is_ok(),
            field(path, "qc"),
            format!(
                "must be an address HOST:PORT (e.g. 127.0.0.1:8080) or \"off\", got {:?}",
                self.qc
            ),
        );
        for (k, x) in [
            ("disk_alarm_free_gb", self.disk_alarm_free_gb),
            ("disk_alarm_minutes", self.disk_alarm_minutes),
            ("nav_alarm_s", self.nav_alarm_s),
        ] {
            v.require(
                x.is_finite() && x >= 0.0,
                field(path, k),
                format!("must be a number ≥ 0, got {x}"),
            );
        }
        v.require(
            (0.0..=1.0).contains(&self.saturation_alarm),
            field(path, "saturation_alarm"),
            format!("must be a fraction 0..=1, got {}", self.saturation_alarm),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_inputs_parse_and_refuse_with_reasons() {
        assert_eq!(
            FrameInput::parse("udp:127.0.0.1:5000"),
            Ok(FrameInput::Udp("127.0.0.1:5000".parse().unwrap()))
        );
        assert_eq!(
            FrameInput::parse("tcp-listen:0.0.0.0:5001"),
            Ok(FrameInput::TcpListen("0.0.0.0:5001".parse().unwrap()))
        );
        assert!(FrameInput::parse("tcp-connect:[::1]:7").is_ok());
        assert!(
            FrameInput::parse("serial:/dev/x")
                .unwrap_err()
                .contains("unknown")
        );
        assert!(
            FrameInput::parse("udp:localhost")
                .unwrap_err()
                .contains("not an IP")
        );
        assert!(FrameInput::parse("nothing").is_err());
    }

    #[test]
    fn the_qc_server_defaults_to_this_machine_only() {
        let c = DaemonConfig::default();
        assert!(c.qc_address().unwrap().ip().is_loopback());
        let off = DaemonConfig {
            qc: "off".into(),
            ..c
        };
        assert_eq!(off.qc_address(), None);
    }
}
