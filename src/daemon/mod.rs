//! The on-board daemon (`fwlidar run`): digitizer frames from the network and navigation bytes
//! from serial ports, recorded to the capture before anything else, then processed by the same
//! pipeline as replay, with live QC.
//!
//! ```text
//!  network ─> frame receiver thread ─[bounded, blocking: recording never drops]─┐
//!  serial ports ─> one reader thread each ─[bounded, blocking]──────────────────┤
//!                                                                               v
//!   source thread: LiveSource (record every frame and nav chunk into the capture segment,
//!                  then decode) → GeoreferencingSource ─[input edges: drop_newest]─> workers → sink
//!   sampler thread: once a second, counters and reports → QcSnapshot → QcHub ← QC server (tokio)
//! ```
//!
//! Files: [`config`] (`[daemon]`), [`frames`] (network receiver), [`recorder`] (the recording
//! live source), [`disk`] (free space), [`sampler`] (QC snapshots, the waveform viewer).

pub mod config;
pub mod disk;
pub mod frames;
pub mod inputs;
pub mod recorder;
pub mod sampler;

pub use config::{DaemonConfig, FrameInput};

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// Host clock, nanoseconds since the Unix epoch.
pub fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

/// Live state of one input (the frame stream or a serial port), written by its thread, read by
/// the sampler.
#[derive(Debug, Default)]
pub struct InputState {
    /// Connected and delivering.
    pub up: AtomicBool,
    /// Bytes received.
    pub bytes: AtomicU64,
    /// Connections made.
    pub connects: AtomicU64,
    /// Failed attempts (absent device, refused connection).
    pub failed: AtomicU64,
    /// Host time of the last data, ns since the epoch (0 = never).
    pub last_data_ns: AtomicU64,
    /// Frames received (frame input).
    pub frames: AtomicU64,
    /// Frames lost on the network (sequence gaps).
    pub lost: AtomicU64,
    /// Bytes skipped as not frames (bad CRC, garbage).
    pub skipped_bytes: AtomicU64,
    /// The last problem.
    pub last_error: Mutex<Option<String>>,
}

impl InputState {
    /// Records a problem (and logs it when it differs from the last one).
    pub fn error(&self, what: String) {
        let mut e = self.last_error.lock().unwrap_or_else(|e| e.into_inner());
        if e.as_deref() != Some(what.as_str()) {
            tracing::warn!("{what}");
            *e = Some(what);
        }
    }

    /// The last problem, if any.
    pub fn last_error(&self) -> Option<String> {
        self.last_error
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Marks data received now.
    pub fn data(&self, bytes: usize) {
        self.bytes.fetch_add(bytes as u64, Ordering::Relaxed);
        self.last_data_ns.store(now_ns(), Ordering::Relaxed);
    }
}
