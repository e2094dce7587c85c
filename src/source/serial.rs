//! Navigation bytes from a serial port (a GNSS/INS receiver), read on its own thread with the
//! `serialport` crate, surviving unplug and replug.
//!
//! The reader opens the configured device (baud rate, parity, 8 data bits, 1 stop bit), reads
//! whatever arrives into [`NavChunk`]s stamped with the host receive time, and sends them on a
//! crossbeam channel. When the device goes away (USB adapter unplugged, receiver powered down:
//! the read fails or the line hangs up) it reports [`SerialEvent::Disconnected`], then tries to
//! open the device again every `reconnect_ms` until it is back, reports
//! [`SerialEvent::Connected`] and the length of the gap. A device that is absent at start-up is
//! the same case: on an aircraft, devices power up in any order.
//!
//! The channel is bounded by its creator; the reader blocks when it is full (the port's kernel
//! buffer then absorbs the burst), so a slow consumer delays bytes but never reorders them.

use std::io::Read;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crossbeam_channel::Sender;
use serde::{Deserialize, Serialize};

use crate::pipeline::ports::NavChunk;

/// Parity of the serial line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Parity {
    /// No parity bit (8N1, what GNSS receivers use).
    #[default]
    None,
    /// Odd parity.
    Odd,
    /// Even parity.
    Even,
}

/// One serial navigation input.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SerialConfig {
    /// Device path, e.g. `/dev/ttyUSB0` or a udev symlink such as `/dev/gnss0`.
    pub device: PathBuf,
    /// Baud rate, bits per second.
    pub baud: u32,
    /// Parity.
    #[serde(default)]
    pub parity: Parity,
    /// Port number stamped on every chunk (index of this port in the configuration).
    #[serde(default)]
    pub port: u8,
    /// Time between attempts to (re)open the device, milliseconds.
    #[serde(default = "default_reconnect_ms")]
    pub reconnect_ms: u64,
    /// Longest wait of one read, milliseconds (bounds how fast a stop request is seen).
    #[serde(default = "default_read_timeout_ms")]
    pub read_timeout_ms: u64,
}

fn default_reconnect_ms() -> u64 {
    500
}

fn default_read_timeout_ms() -> u64 {
    100
}

/// What the reader reports.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SerialEvent {
    /// The device is open (again). `gap_ms` is how long it was away, for a reconnection.
    Connected {
        /// Port number.
        port: u8,
        /// Milliseconds since the disconnection; `None` for the first connection.
        gap_ms: Option<u64>,
    },
    /// Bytes as they came.
    Data(NavChunk),
    /// The device went away.
    Disconnected {
        /// Port number.
        port: u8,
        /// Why, as the operating system said it.
        reason: String,
    },
}

/// Counts for the report.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SerialStats {
    /// Bytes read.
    pub bytes: u64,
    /// Chunks sent.
    pub chunks: u64,
    /// Successful opens.
    pub connects: u64,
    /// Times the device went away.
    pub disconnects: u64,
    /// Failed attempts to open the device.
    pub failed_opens: u64,
    /// Longest time without the device after it had been open, milliseconds.
    pub longest_gap_ms: u64,
}

/// A running serial reader (see the module documentation).
pub struct SerialReader {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<SerialStats>>,
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

impl SerialReader {
    /// Starts reading `cfg.device` on a new thread, sending events to `tx`.
    pub fn spawn(cfg: SerialConfig, tx: Sender<SerialEvent>) -> std::io::Result<SerialReader> {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::Builder::new()
            .name(format!("serial-{}", cfg.port))
            .spawn(move || run(cfg, tx, flag))?;
        Ok(SerialReader {
            stop,
            thread: Some(thread),
        })
    }

    /// Stops the reader (within one read timeout) and returns its counts.
    pub fn stop(mut self) -> SerialStats {
        self.stop.store(true, Ordering::Relaxed);
        self.thread
            .take()
            .and_then(|t| t.join().ok())
            .unwrap_or_default()
    }
}

impl Drop for SerialReader {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn open(cfg: &SerialConfig) -> serialport::Result<Box<dyn serialport::SerialPort>> {
    let parity = match cfg.parity {
        Parity::None => serialport::Parity::None,
        Parity::Odd => serialport::Parity::Odd,
        Parity::Even => serialport::Parity::Even,
    };
    serialport::new(cfg.device.to_string_lossy(), cfg.baud)
        .parity(parity)
        .data_bits(serialport::DataBits::Eight)
        .stop_bits(serialport::StopBits::One)
        .flow_control(serialport::FlowControl::None)
        .timeout(Duration::from_millis(cfg.read_timeout_ms.max(1)))
        .open()
}

/// Sleeps `ms` in short steps; false when a stop was requested meanwhile.
fn pause(ms: u64, stop: &AtomicBool) -> bool {
    let until = Instant::now() + Duration::from_millis(ms);
    while Instant::now() < until {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    !stop.load(Ordering::Relaxed)
}

fn run(cfg: SerialConfig, tx: Sender<SerialEvent>, stop: Arc<AtomicBool>) -> SerialStats {
    let mut stats = SerialStats::default();
    let mut down_since: Option<Instant> = None;
    let mut buf = vec![0u8; 4096];
    let mut warned = false;
    while !stop.load(Ordering::Relaxed) {
        let mut port = match open(&cfg) {
            Ok(p) => p,
            Err(e) => {
                stats.failed_opens += 1;
                if !warned {
                    tracing::warn!(device = %cfg.device.display(), "serial navigation input down: {e}; retrying every {} ms", cfg.reconnect_ms);
                    warned = true;
                }
                if !pause(cfg.reconnect_ms, &stop) {
                    break;
                }
                continue;
            }
        };
        warned = false;
        stats.connects += 1;
        let gap_ms = down_since.take().map(|d| d.elapsed().as_millis() as u64);
        if let Some(g) = gap_ms {
            stats.longest_gap_ms = stats.longest_gap_ms.max(g);
            tracing::info!(device = %cfg.device.display(), gap_ms = g, "serial navigation input back");
        }
        if tx
            .send(SerialEvent::Connected {
                port: cfg.port,
                gap_ms,
            })
            .is_err()
        {
            break;
        }
        let reason = loop {
            if stop.load(Ordering::Relaxed) {
                return stats;
            }
            match port.read(&mut buf) {
                Ok(0) => break "the line hung up".to_string(),
                Ok(n) => {
                    stats.bytes += n as u64;
                    stats.chunks += 1;
                    let chunk = NavChunk {
                        port: cfg.port,
                        receive_time_ns: now_ns(),
                        bytes: buf[..n].to_vec(),
                    };
                    if tx.send(SerialEvent::Data(chunk)).is_err() {
                        return stats;
                    }
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::Interrupted
                            | std::io::ErrorKind::WouldBlock
                    ) => {}
                Err(e) => break e.to_string(),
            }
        };
        drop(port);
        stats.disconnects += 1;
        down_since = Some(Instant::now());
        tracing::warn!(device = %cfg.device.display(), "serial navigation input lost: {reason}");
        if tx
            .send(SerialEvent::Disconnected {
                port: cfg.port,
                reason,
            })
            .is_err()
        {
            break;
        }
        if !pause(cfg.reconnect_ms, &stop) {
            break;
        }
    }
    stats
}
