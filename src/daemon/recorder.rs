//! The recording live source: every frame and navigation chunk that arrives is appended to the
//! capture segment **first**, then decoded and passed on to processing. It runs on the pipeline's
//! source thread, in front of the georeferencing wrapper and the input edges; since those edges
//! drop the newest pulse when the workers fall behind (`input_edge = "drop_newest"`), this
//! thread never waits for processing, so a slow chain costs processed pulses (counted), never
//! recorded ones.
//!
//! A capture segment is a complete capture file (`docs/formats.md`): a restart writes the next
//! segment; a kill -9 loses at most what was written since the last flush (`flush_ms`), and the
//! reader skips a partial last record. A write error (disk full) stops the recording with an
//! alarm; processing goes on.

use crate::source::report::{InputReport, LiveReport, SourceReport};
use std::collections::BTreeMap;
use std::fs::File;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender, TryRecvError, never, select};

use super::InputState;
use super::frames::{FrameMsg, FrameReceiver};
use crate::core::facts::SourceFacts;
use crate::core::nap::Napper;
use crate::format::capture_writer::CaptureWriter;
use crate::format::frame::decode_frame;
use crate::pipeline::ports::{NavChunk, Source, SourceError, SourceEvent};
use crate::pulse::PulsePool;
use crate::source::serial::{SerialEvent, SerialReader};

/// Counters of the recording, read by the QC sampler.
#[derive(Debug, Default)]
pub struct RecorderState {
    /// Frames written to the capture.
    pub frames_recorded: AtomicU64,
    /// Navigation chunks written to the capture.
    pub nav_records: AtomicU64,
    /// Bytes of the current segment (buffered included).
    pub bytes: AtomicU64,
    /// Records of the current segment.
    pub records: AtomicU64,
    /// Frames recorded that are not valid digitizer frames (not processed).
    pub bad_frames: AtomicU64,
    /// Frames recorded at shutdown, after processing had stopped.
    pub recorded_unprocessed: AtomicU64,
    /// Decoded pulses with a sample at the digitizer's full scale.
    pub saturated: AtomicU64,
    /// Pulses decoded and passed on to processing.
    pub decoded: AtomicU64,
    /// The write error that stopped the recording.
    pub error: Mutex<Option<String>>,
}

impl RecorderState {
    /// The write error that stopped the recording, if any.
    pub fn error(&self) -> Option<String> {
        self.error.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// The live source (see the module documentation).
pub struct LiveSource {
    frames: Receiver<FrameMsg>,
    free: Sender<Vec<u8>>,
    serial: Receiver<SerialEvent>,
    receiver: Option<FrameReceiver>,
    serial_readers: Vec<SerialReader>,
    serial_states: BTreeMap<u8, Arc<InputState>>,
    writer: Option<CaptureWriter<File>>,
    segment: PathBuf,
    state: Arc<RecorderState>,
    stop: Arc<AtomicBool>,
    facts: SourceFacts,
    ended: bool,
    napper: Napper,
}

/// What the live source reads from and records into.
pub struct LiveInputs {
    /// Frames from the receiver (`None`: no frame input configured).
    pub frames: Option<(Receiver<FrameMsg>, Sender<Vec<u8>>, FrameReceiver)>,
    /// Events of the serial readers.
    pub serial: Receiver<SerialEvent>,
    /// The serial readers (stopped when the source ends).
    pub serial_readers: Vec<SerialReader>,
    /// Each serial port's live state, by port number.
    pub serial_states: BTreeMap<u8, Arc<InputState>>,
}

const POLL: Duration = Duration::from_millis(100);

impl LiveSource {
    /// A source recording into `writer` (the open segment at `segment`); it ends when `stop` is
    /// set, after stopping its inputs and recording everything they had delivered.
    pub fn new(
        inputs: LiveInputs,
        writer: CaptureWriter<File>,
        segment: PathBuf,
        state: Arc<RecorderState>,
        stop: Arc<AtomicBool>,
        facts: SourceFacts,
    ) -> Self {
        let (frames, free, receiver) = match inputs.frames {
            Some((rx, free, r)) => (rx, free, Some(r)),
            None => (never(), crossbeam_channel::bounded(1).0, None),
        };
        LiveSource {
            frames,
            free,
            serial: inputs.serial,
            receiver,
            serial_readers: inputs.serial_readers,
            serial_states: inputs.serial_states,
            writer: Some(writer),
            segment,
            state,
            stop,
            facts,
            ended: false,
            napper: Napper::new(),
        }
    }

    fn write_failed(&mut self, e: impl std::fmt::Display) {
        let msg = format!(
            "recording into {} stopped: {e}; processing goes on",
            self.segment.display()
        );
        tracing::error!("{msg}");
        *self.state.error.lock().unwrap_or_else(|e| e.into_inner()) = Some(msg);
        self.writer = None;
    }

    fn note_written(&self) {
        if let Some(w) = &self.writer {
            self.state.bytes.store(w.bytes_written(), Ordering::Relaxed);
            self.state
                .records
                .store(w.records_written(), Ordering::Relaxed);
        }
    }

    /// Records one frame; true when it was written (or the recording had already failed).
    fn record_frame(&mut self, msg: &FrameMsg) {
        if let Some(w) = self.writer.as_mut() {
            match w.write_frame_payload(&msg.payload) {
                Ok(()) => {
                    self.state.frames_recorded.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => self.write_failed(e),
            }
        }
        self.note_written();
    }

    fn record_nav(&mut self, chunk: &NavChunk) {
        if let Some(w) = self.writer.as_mut() {
            match w.write_nav(chunk.port, chunk.receive_time_ns, &chunk.bytes) {
                Ok(()) => {
                    self.state.nav_records.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => self.write_failed(e),
            }
        }
        self.note_written();
    }

    /// A serial event: records data and returns it as a navigation chunk.
    fn serial_event(&mut self, ev: SerialEvent) -> Option<NavChunk> {
        match ev {
            SerialEvent::Connected { port, gap_ms } => {
                if let Some(s) = self.serial_states.get(&port) {
                    s.up.store(true, Ordering::Relaxed);
                    s.connects.fetch_add(1, Ordering::Relaxed);
                    *s.last_error.lock().unwrap_or_else(|e| e.into_inner()) = None;
                }
                tracing::info!(port, gap_ms, "navigation port connected");
                None
            }
            SerialEvent::Disconnected { port, reason } => {
                if let Some(s) = self.serial_states.get(&port) {
                    s.up.store(false, Ordering::Relaxed);
                    s.error(format!("navigation port {port} went away: {reason}"));
                }
                None
            }
            SerialEvent::Data(chunk) => {
                if let Some(s) = self.serial_states.get(&chunk.port) {
                    s.up.store(true, Ordering::Relaxed);
                    s.data(chunk.bytes.len());
                }
                self.record_nav(&chunk);
                Some(chunk)
            }
        }
    }

    /// One received frame: recorded, then decoded into a pulse for processing (`None`: it does
    /// not decode; counted and logged).
    fn frame(&mut self, msg: FrameMsg, pool: &PulsePool) -> Option<SourceEvent> {
        self.record_frame(&msg);
        let mut pulse = pool.take();
        let decoded = decode_frame(&msg.payload, &mut pulse);
        let received = msg.received;
        let _ = self.free.try_send(msg.payload);
        match decoded {
            Ok(()) => {
                pulse.arrived = received;
                self.state.decoded.fetch_add(1, Ordering::Relaxed);
                let full = pulse.full_scale_dn().unwrap_or(u16::MAX);
                if pulse.raw.iter().any(|&r| r >= full) {
                    self.state.saturated.fetch_add(1, Ordering::Relaxed);
                }
                Some(SourceEvent::Pulse(pulse))
            }
            Err(e) => {
                pool.give(pulse);
                self.state.bad_frames.fetch_add(1, Ordering::Relaxed);
                tracing::debug!("recorded frame does not decode: {e}");
                None
            }
        }
    }

    /// At the end: stops the inputs, records what they had delivered, closes the segment.
    fn shut_down(&mut self) {
        if let Some(r) = self.receiver.take() {
            r.stop();
        }
        for r in self.serial_readers.drain(..) {
            r.stop();
        }
        while let Ok(msg) = self.frames.try_recv() {
            self.record_frame(&msg);
            self.state
                .recorded_unprocessed
                .fetch_add(1, Ordering::Relaxed);
        }
        while let Ok(ev) = self.serial.try_recv() {
            let _ = self.serial_event(ev);
        }
        if let Some(w) = self.writer.take() {
            let bytes = w.bytes_written();
            if let Err(e) = w.finish() {
                self.write_failed(e);
            } else {
                tracing::info!(segment = %self.segment.display(), bytes, "capture segment closed");
            }
        }
    }
}

impl Source for LiveSource {
    type Report = SourceReport;

    fn name(&self) -> &'static str {
        "live"
    }

    fn next(&mut self, pool: &PulsePool) -> Result<SourceEvent, SourceError> {
        loop {
            if self.ended {
                return Ok(SourceEvent::End);
            }
            if self.stop.load(Ordering::Relaxed) {
                self.shut_down();
                self.ended = true;
                return Ok(SourceEvent::End);
            }
            // What is already there, without blocking; while the inputs are busy, an empty look
            // naps instead of waiting to be woken by the next frame (`core::nap`). Navigation
            // first: a frame waits for the record after it to be georeferenced, and a busy
            // frame queue must not starve the serial ports.
            match self.serial.try_recv() {
                Ok(ev) => {
                    self.napper.active();
                    match self.serial_event(ev) {
                        Some(chunk) => return Ok(SourceEvent::Nav(chunk)),
                        None => continue,
                    }
                }
                Err(TryRecvError::Disconnected) => self.serial = never(),
                Err(TryRecvError::Empty) => {}
            }
            match self.frames.try_recv() {
                Ok(msg) => {
                    self.napper.active();
                    match self.frame(msg, pool) {
                        Some(ev) => return Ok(ev),
                        None => continue,
                    }
                }
                Err(TryRecvError::Disconnected) => self.frames = never(),
                Err(TryRecvError::Empty) => {}
            }
            if self.napper.nap() {
                if let Some(w) = self.writer.as_mut()
                    && let Err(e) = w.flush_if_due()
                {
                    self.write_failed(e);
                }
                return Ok(SourceEvent::Idle);
            }
            // Quiet: block until something arrives (or POLL passes).
            select! {
                recv(self.frames) -> msg => {
                    let Ok(msg) = msg else {
                        // The receiver is gone (it only goes at shutdown).
                        self.frames = never();
                        continue;
                    };
                    self.napper.active();
                    if let Some(ev) = self.frame(msg, pool) {
                        return Ok(ev);
                    }
                }
                recv(self.serial) -> ev => {
                    let Ok(ev) = ev else {
                        self.serial = never();
                        continue;
                    };
                    self.napper.active();
                    if let Some(chunk) = self.serial_event(ev) {
                        return Ok(SourceEvent::Nav(chunk));
                    }
                }
                default(POLL) => {
                    if let Some(w) = self.writer.as_mut()
                        && let Err(e) = w.flush_if_due()
                    {
                        self.write_failed(e);
                    }
                    return Ok(SourceEvent::Idle);
                }
            }
        }
    }

    fn facts(&self) -> SourceFacts {
        self.facts.clone()
    }

    fn report(&self) -> SourceReport {
        let s = &self.state;
        SourceReport::of(InputReport::Live(LiveReport {
            segment: self.segment.display().to_string(),
            frames_recorded: s.frames_recorded.load(Ordering::Relaxed),
            nav_records: s.nav_records.load(Ordering::Relaxed),
            bytes: s.bytes.load(Ordering::Relaxed),
            bad_frames: s.bad_frames.load(Ordering::Relaxed),
            recorded_unprocessed: s.recorded_unprocessed.load(Ordering::Relaxed),
            saturated_pulses: s.saturated.load(Ordering::Relaxed),
            error: s.error(),
        }))
    }
}

impl Drop for LiveSource {
    fn drop(&mut self) {
        if !self.ended {
            self.shut_down();
        }
    }
}
