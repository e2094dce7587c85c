//! The daemon's live inputs started: the frame receiver (network) and one reader per serial
//! navigation port, each with the live state the QC page shows.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use super::InputState;
use super::config::{DaemonConfig, FrameInput};
use super::frames::{FrameMsg, FrameReceiver, channels};
use super::recorder::LiveInputs;
use super::sampler::InputView;
use crate::source::serial::{SerialConfig, SerialReader};

/// The started inputs: what the recorder reads, what the QC page shows of them, and the frame
/// queue into the recorder with its capacity (the page shows how full it is).
pub struct StartedInputs {
    /// The inputs the recording source reads.
    pub live: LiveInputs,
    /// One view per input for the QC page.
    pub views: Vec<InputView>,
    /// The frame queue into the recorder and its capacity, when frames are received.
    pub recorder_queue: Option<(crossbeam_channel::Receiver<FrameMsg>, u64)>,
}

/// Starts the frame receiver (`[daemon] frames`, when set) and the serial readers. An absent
/// device or a refused connection is not an error: it is reported down and retried forever;
/// a receiver that cannot start at all is (the message says which).
pub fn start_inputs(d: &DaemonConfig, serial: &[SerialConfig]) -> Result<StartedInputs, String> {
    let mut views = Vec::new();
    let frames = match &d.frames {
        Some(spec) => {
            let input = FrameInput::parse(spec)?;
            let ((tx, rx), (free_tx, free_rx)) = channels(d.recorder_queue);
            let state = Arc::new(InputState::default());
            views.push(InputView {
                name: "frames".into(),
                detail: input.to_string(),
                state: state.clone(),
            });
            let receiver =
                FrameReceiver::spawn(input, Duration::from_millis(d.retry_ms), tx, free_rx, state)
                    .map_err(|e| format!("cannot start the frame receiver: {e}"))?;
            Some((rx, free_tx, receiver))
        }
        None => {
            tracing::warn!("no [daemon] frames input: recording navigation only");
            None
        }
    };
    let recorder_queue = frames
        .as_ref()
        .map(|(rx, _, _)| (rx.clone(), d.recorder_queue as u64));
    let (serial_tx, serial_rx) = crossbeam_channel::bounded(4096);
    let mut serial_readers = Vec::new();
    let mut serial_states = BTreeMap::new();
    for s in serial {
        let state = Arc::new(InputState::default());
        state.error(format!(
            "navigation port {}: waiting for {}",
            s.port,
            s.device.display()
        ));
        views.push(InputView {
            name: format!("serial:{}", s.port),
            detail: format!("{} @ {} bit/s", s.device.display(), s.baud),
            state: state.clone(),
        });
        serial_states.insert(s.port, state);
        serial_readers.push(
            SerialReader::spawn(s.clone(), serial_tx.clone())
                .map_err(|e| format!("cannot start the serial reader: {e}"))?,
        );
    }
    Ok(StartedInputs {
        live: LiveInputs {
            frames,
            serial: serial_rx,
            serial_readers,
            serial_states,
        },
        views,
        recorder_queue,
    })
}
