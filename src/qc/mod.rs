//! Live QC monitoring: the snapshot the daemon publishes once a second ([`snapshot`]), the hub
//! that holds it for readers ([`QcHub`]), its Prometheus text ([`prometheus`]) and the
//! read-only HTTP server with the operator's page ([`server`]).

pub mod prometheus;
pub mod server;
pub mod snapshot;

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, RwLock};

pub use snapshot::*;

/// History points kept for the charts (one a second: ten minutes).
pub const HISTORY_LEN: usize = 600;

/// Where the daemon publishes and the server reads. Cheap to read: readers get `Arc`s.
pub struct QcHub {
    snapshot: RwLock<Arc<QcSnapshot>>,
    history: Mutex<VecDeque<HistoryPoint>>,
    waveform: RwLock<Option<Arc<WaveformView>>>,
    updates: tokio::sync::watch::Sender<u64>,
}

impl Default for QcHub {
    fn default() -> Self {
        QcHub {
            snapshot: RwLock::new(Arc::new(QcSnapshot::default())),
            history: Mutex::new(VecDeque::with_capacity(HISTORY_LEN)),
            waveform: RwLock::new(None),
            updates: tokio::sync::watch::channel(0).0,
        }
    }
}

impl QcHub {
    /// The latest snapshot.
    pub fn snapshot(&self) -> Arc<QcSnapshot> {
        self.snapshot
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The chart history, oldest first.
    pub fn history(&self) -> Vec<HistoryPoint> {
        self.history
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .cloned()
            .collect()
    }

    /// The last sampled waveform, once one was.
    pub fn waveform(&self) -> Option<Arc<WaveformView>> {
        self.waveform
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// A receiver that sees the sequence number of every new snapshot.
    pub fn subscribe(&self) -> tokio::sync::watch::Receiver<u64> {
        self.updates.subscribe()
    }

    /// Publishes a snapshot and its history point; wakes subscribers.
    pub fn publish(&self, snapshot: QcSnapshot, point: HistoryPoint) {
        let seq = snapshot.sequence;
        *self.snapshot.write().unwrap_or_else(|e| e.into_inner()) = Arc::new(snapshot);
        {
            let mut h = self.history.lock().unwrap_or_else(|e| e.into_inner());
            if h.len() == HISTORY_LEN {
                h.pop_front();
            }
            h.push_back(point);
        }
        self.updates.send_replace(seq);
    }

    /// Publishes a sampled waveform.
    pub fn set_waveform(&self, view: WaveformView) {
        *self.waveform.write().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(view));
    }
}
