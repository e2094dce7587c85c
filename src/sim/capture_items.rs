//! A recorded capture as a stream of [`SimItem`]s, for `fwlidar simulate --live --from CAPTURE`:
//! every digitizer frame decoded into a pulse and every navigation record's bytes, in file
//! order, so that [`live::play`](crate::sim::live::play) paces them in real time into a
//! daemon's inputs.
//!
//! Pacing uses each item's time: a pulse's GPS time and a navigation record's receive time. In
//! a capture written by `fwlidar simulate --out` both are GPS nanoseconds (the simulator stamps
//! navigation with its epoch's GPS time), so the stream plays as it was simulated. A capture
//! recorded by the daemon stamps navigation with the host clock instead (Unix time): playing it
//! is refused with an error naming the record, rather than paced on two clocks.
//!
//! Damaged stretches of the file are skipped as the capture reader skips them (counted, not
//! fatal); a frame that does not decode ends the stream with an error naming the file and the
//! pulse.

use std::collections::VecDeque;
use std::fs::File;
use std::path::{Path, PathBuf};

use crate::format::capture_reader::{CaptureReader, Record};
use crate::pulse::Pulse;
use crate::sim::SimItem;

/// Navigation receive times beyond this many seconds from the first pulse's GPS time are on
/// another clock than the pulses (GPS seconds of the week against Unix seconds differ by ~1.7e9).
const MAX_CLOCK_OFFSET_S: f64 = 7.0 * 86_400.0;

/// Why a capture cannot be played.
#[derive(Debug, thiserror::Error)]
pub enum CaptureItemsError {
    /// The capture could not be opened or read.
    #[error(transparent)]
    Capture(#[from] crate::format::capture::CaptureError),
    /// A frame did not decode.
    #[error("{path}: frame of pulse {pulse_id}: {message}")]
    Frame {
        /// The capture.
        path: PathBuf,
        /// The frame's pulse id.
        pulse_id: u64,
        /// What is wrong with it.
        message: String,
    },
    /// Navigation and pulses are on different clocks.
    #[error(
        "{path}: navigation record at byte {offset} was received at {receive_s:.3} s, {offset_s:.0} s \
         from the pulses' GPS times: its receive time is not on the pulses' clock (a capture \
         recorded by the daemon stamps navigation with the host clock); only captures written \
         by `fwlidar simulate --out` can be played"
    )]
    Clocks {
        /// The capture.
        path: PathBuf,
        /// Byte offset of the record.
        offset: u64,
        /// The record's receive time, s.
        receive_s: f64,
        /// Its distance from the pulses' times, s.
        offset_s: f64,
    },
}

/// The items of a capture, in file order (see the module documentation).
pub struct CaptureItems {
    reader: CaptureReader<File>,
    path: PathBuf,
    /// GPS time of the first pulse, s (NaN until one is read).
    first_pulse_s: f64,
    /// Navigation records read before the first pulse, with their byte offsets: their clock is
    /// checked against it before they go out.
    early_nav: Vec<(u64, u64, Vec<u8>)>,
    /// Items ready to go out, in order.
    ready: VecDeque<SimItem>,
    error: Option<CaptureItemsError>,
}

impl CaptureItems {
    /// Opens the capture at `path`.
    pub fn open(path: &Path) -> Result<Self, CaptureItemsError> {
        Ok(CaptureItems {
            reader: CaptureReader::open(path)?,
            path: path.to_path_buf(),
            first_pulse_s: f64::NAN,
            early_nav: Vec::new(),
            ready: VecDeque::new(),
            error: None,
        })
    }

    /// What ended the stream early, if something did (checked after playing).
    pub fn error(&self) -> Option<&CaptureItemsError> {
        self.error.as_ref()
    }

    /// Reads records until at least one item is ready or the file ends.
    fn read_more(&mut self) -> Result<(), CaptureItemsError> {
        while self.ready.is_empty() {
            let offset = self.reader.position();
            let record = match self.reader.next_record() {
                None => {
                    // A capture without pulses: its navigation alone, unchecked.
                    for (_, receive_time_ns, bytes) in self.early_nav.drain(..) {
                        self.ready.push_back(SimItem::Nav {
                            receive_time_ns,
                            bytes,
                        });
                    }
                    return Ok(());
                }
                Some(r) => r?,
            };
            match record {
                Record::Header(_) => {}
                Record::Frame(frame) => {
                    let mut pulse = Pulse::default();
                    frame
                        .decode_into(&mut pulse)
                        .map_err(|e| CaptureItemsError::Frame {
                            path: self.path.clone(),
                            pulse_id: frame.pulse_id(),
                            message: e.to_string(),
                        })?;
                    if !self.first_pulse_s.is_finite() && pulse.gps_time.is_finite() {
                        self.first_pulse_s = pulse.gps_time;
                        let early = std::mem::take(&mut self.early_nav);
                        for (offset, receive_time_ns, bytes) in early {
                            check_clock(&self.path, self.first_pulse_s, offset, receive_time_ns)?;
                            self.ready.push_back(SimItem::Nav {
                                receive_time_ns,
                                bytes,
                            });
                        }
                    }
                    self.ready.push_back(SimItem::Pulse(pulse));
                }
                Record::Nav {
                    receive_time_ns,
                    bytes,
                    ..
                } => {
                    if self.first_pulse_s.is_finite() {
                        check_clock(&self.path, self.first_pulse_s, offset, receive_time_ns)?;
                        self.ready.push_back(SimItem::Nav {
                            receive_time_ns,
                            bytes: bytes.to_vec(),
                        });
                    } else {
                        self.early_nav
                            .push((offset, receive_time_ns, bytes.to_vec()));
                    }
                }
            }
        }
        Ok(())
    }
}

/// Refuses a navigation receive time (ns) too far from the first pulse's GPS time (s) to be on
/// its clock; `offset` is the record's byte offset in `path`.
fn check_clock(
    path: &Path,
    first_pulse_s: f64,
    offset: u64,
    receive_time_ns: u64,
) -> Result<(), CaptureItemsError> {
    let receive_s = receive_time_ns as f64 * 1e-9;
    let offset_s = receive_s - first_pulse_s;
    if offset_s.abs() > MAX_CLOCK_OFFSET_S {
        return Err(CaptureItemsError::Clocks {
            path: path.to_path_buf(),
            offset,
            receive_s,
            offset_s,
        });
    }
    Ok(())
}

impl Iterator for CaptureItems {
    type Item = SimItem;

    fn next(&mut self) -> Option<SimItem> {
        if self.error.is_some() {
            return None;
        }
        if self.ready.is_empty()
            && let Err(e) = self.read_more()
        {
            self.error = Some(e);
            self.ready.clear();
            return None;
        }
        self.ready.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::capture::FlushPolicy;
    use crate::format::capture_writer::CaptureWriter;
    use crate::pulse::SegmentKind;

    fn pulse(id: u64, gps_time: f64) -> Pulse {
        let mut p = Pulse {
            pulse_id: id,
            gps_time,
            sample_ns: 1.0,
            gain_v_per_dn: 1.0,
            bits: 16,
            ..Pulse::default()
        };
        p.push_segment(SegmentKind::Return, 0, 100.0, [1u16, 5, 9, 5, 1]);
        p
    }

    fn capture(dir: &Path, nav_time_ns: u64) -> PathBuf {
        let path = dir.join("c.fwcap");
        let mut w =
            CaptureWriter::create(&path, "sensor = \"test\"\n", FlushPolicy::default()).unwrap();
        w.write_nav(0, nav_time_ns, b"$GPGGA,early*00\r\n").unwrap();
        w.write_pulse(&pulse(7, 345_600.0)).unwrap();
        w.write_nav(0, nav_time_ns + 10_000_000, b"$GPGGA,later*00\r\n")
            .unwrap();
        w.write_pulse(&pulse(8, 345_600.01)).unwrap();
        w.finish().unwrap();
        path
    }

    #[test]
    fn frames_and_navigation_come_out_in_file_order() {
        let dir = tempfile::tempdir().unwrap();
        let path = capture(dir.path(), 345_599_990_000_000);
        let mut items = CaptureItems::open(&path).unwrap();
        let got: Vec<String> = items
            .by_ref()
            .map(|i| match i {
                SimItem::Pulse(p) => format!("pulse {} {:?}", p.pulse_id, p.raw),
                SimItem::Nav { bytes, .. } => String::from_utf8_lossy(&bytes).into_owned(),
            })
            .collect();
        assert!(items.error().is_none(), "{:?}", items.error());
        assert_eq!(
            got,
            vec![
                "$GPGGA,early*00\r\n".to_string(),
                "pulse 7 [1, 5, 9, 5, 1]".into(),
                "$GPGGA,later*00\r\n".into(),
                "pulse 8 [1, 5, 9, 5, 1]".into(),
            ]
        );
    }

    #[test]
    fn navigation_on_the_host_clock_is_refused_with_the_file_named() {
        let dir = tempfile::tempdir().unwrap();
        // Unix time of 2026: 1.78e18 ns, against pulses at 345 600 s of the GPS week.
        let path = capture(dir.path(), 1_780_000_000_000_000_000);
        let mut items = CaptureItems::open(&path).unwrap();
        assert_eq!(items.by_ref().count(), 0);
        let e = items.error().expect("an error").to_string();
        assert!(
            e.contains("c.fwcap") && e.contains("not on the pulses' clock"),
            "{e}"
        );
    }

    #[test]
    fn a_missing_file_is_an_error_naming_it() {
        let e = CaptureItems::open(Path::new("/nonexistent/x.fwcap"))
            .err()
            .expect("error")
            .to_string();
        assert!(e.contains("/nonexistent/x.fwcap"), "{e}");
    }
}
