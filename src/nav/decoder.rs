//! Bytes in, dated navigation samples out: the [`Framer`], the NMEA and NovAtel decoders and
//! the [`NmeaDater`] in one piece, with one summary of everything counted on the way.

use std::collections::BTreeMap;

use serde::Serialize;

use super::dating::{GpsTime, NmeaDater};
use super::framer::{Frame, Framer};
use super::{NavSample, nmea, novatel};

/// Leap seconds GPS − UTC since 2017-01-01.
pub const LEAP_SECONDS_NOW: f64 = 18.0;

/// Everything a [`NavDecoder`] counted.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DecodeSummary {
    /// Samples decoded and passed on.
    pub records: u64,
    /// Candidate records that gave no sample (all reasons below).
    pub rejected: u64,
    /// Rejections by reason: framing (`bad_checksum`, `truncated`, `bad_crc`, ...), contents
    /// (`no_fix`, `bad_latitude`, ...) and `undated` (no date arrived for an NMEA time).
    pub rejected_by_reason: BTreeMap<String, u64>,
    /// Well-formed records of types we do not use, by type (`GSV`, `novatel_264`, ...).
    pub ignored: BTreeMap<String, u64>,
    /// Samples passed on, by record type.
    pub by_kind: BTreeMap<String, u64>,
    /// Bytes read.
    pub bytes: u64,
    /// Bytes outside any record.
    pub unframed_bytes: u64,
    /// Receiver dates moved forward by 1024 weeks.
    pub rollover_corrected: u64,
}

/// Framer + decoders + dater (see the module documentation).
pub struct NavDecoder {
    framer: Framer,
    dater: NmeaDater,
    summary: DecodeSummary,
}

impl NavDecoder {
    /// A decoder adding `leap_seconds` to UTC, holding at most `max_pending` NMEA samples while
    /// waiting for a date, correcting dates before `earliest` (days since 1970) for rollover.
    pub fn new(leap_seconds: f64, max_pending: usize, earliest: Option<i64>) -> Self {
        NavDecoder {
            framer: Framer::new(),
            dater: NmeaDater::new(leap_seconds, max_pending, earliest),
            summary: DecodeSummary::default(),
        }
    }

    /// Feeds bytes as they arrived; `out` receives every sample that is complete and dated.
    pub fn push(&mut self, bytes: &[u8], out: &mut impl FnMut(NavSample, Option<GpsTime>)) {
        self.framer.push(bytes);
        self.drain(out);
    }

    /// Ends the stream: a cut record is counted, held samples are counted as undated.
    pub fn finish(&mut self, out: &mut impl FnMut(NavSample, Option<GpsTime>)) {
        self.framer.finish();
        self.drain(out);
        self.dater.finish();
    }

    /// Everything counted so far (framing, decoding and dating together).
    pub fn summary(&self) -> DecodeSummary {
        let mut s = self.summary.clone();
        let f = self.framer.stats();
        for (why, n) in &f.rejected {
            *s.rejected_by_reason.entry((*why).to_string()).or_insert(0) += n;
        }
        let d = self.dater.stats();
        if d.undated > 0 {
            *s.rejected_by_reason.entry("undated".into()).or_insert(0) += d.undated;
        }
        s.rejected = s.rejected_by_reason.values().sum();
        s.bytes = f.bytes;
        s.unframed_bytes = f.unframed_bytes;
        s.rollover_corrected = d.rollover_corrected;
        s
    }

    fn drain(&mut self, out: &mut impl FnMut(NavSample, Option<GpsTime>)) {
        while let Some(frame) = self.framer.next_frame() {
            let outcome = match frame {
                Frame::Nmea(body) => match nmea::decode(body) {
                    nmea::Decoded::Sample(s) => Outcome::Sample(s),
                    nmea::Decoded::Ignored(t) => {
                        Outcome::Ignored(String::from_utf8_lossy(&t).trim().to_string())
                    }
                    nmea::Decoded::Rejected(why) => Outcome::Rejected(why),
                },
                Frame::Novatel { header, body } => novatel_outcome(header, body, false),
                Frame::NovatelShort { header, body } => novatel_outcome(header, body, true),
            };
            match outcome {
                Outcome::Sample(s) => {
                    let summary = &mut self.summary;
                    self.dater.push(s, &mut |s, t| {
                        summary.records += 1;
                        *summary
                            .by_kind
                            .entry(format!("{:?}", s.kind).to_uppercase())
                            .or_insert(0) += 1;
                        out(s, t)
                    });
                }
                Outcome::Ignored(name) => *self.summary.ignored.entry(name).or_insert(0) += 1,
                Outcome::Rejected(why) => {
                    *self
                        .summary
                        .rejected_by_reason
                        .entry(why.to_string())
                        .or_insert(0) += 1
                }
            }
        }
    }
}

/// One frame's outcome (short-lived, on the stack: the size difference does not matter).
#[allow(clippy::large_enum_variant)]
enum Outcome {
    Sample(NavSample),
    Ignored(String),
    Rejected(&'static str),
}

fn novatel_outcome(header: &[u8], body: &[u8], short: bool) -> Outcome {
    match novatel::decode(header, body, short) {
        Ok(Some(s)) => Outcome::Sample(s),
        Ok(None) => Outcome::Ignored(match novatel::header_id_time(header, short) {
            Some((id, _)) => format!("novatel_{id}"),
            None => "novatel".into(),
        }),
        Err(why) => Outcome::Rejected(why),
    }
}
