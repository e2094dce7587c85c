//! Replay's navigation consumer: each port's bytes through the framer, the NMEA/NovAtel
//! decoders and the NMEA dater (`nav::decoder::NavDecoder`), so `summary.json` says what the
//! navigation stream held — samples by type, their GPS time span, rejections by reason — not
//! just how many bytes came. The daemon and replay run it on the navigation thread.

use std::collections::BTreeMap;

use crate::nav::dating::GpsTime;
use crate::nav::decoder::{LEAP_SECONDS_NOW, NavDecoder};
use crate::pipeline::ports::NavChunk;
use crate::pipeline::ports::NavConsumer;

/// Samples held per port while waiting for the first date.
const MAX_UNDATED: usize = 512;

struct Port {
    chunks: u64,
    decoder: NavDecoder,
    first: Option<GpsTime>,
    last: Option<GpsTime>,
    state: LatestState,
}

/// The latest navigation state a port reported (for live QC): each field as last stated by any
/// record that carries it.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct LatestState {
    /// Host receive time of the chunk holding the last decoded record, ns since the epoch.
    pub last_record_receive_ns: Option<u64>,
    /// The receiver's fix quality (GGA quality, NovAtel solution status), as stated.
    pub fix: Option<u32>,
    /// The record kind that stated the fix.
    pub fix_kind: Option<String>,
    /// Satellites used.
    pub satellites: Option<u32>,
    /// The INS status, as stated.
    pub ins_status: Option<u32>,
    /// The record kind that stated the INS status.
    pub ins_kind: Option<String>,
    /// Latitude, longitude (degrees), ellipsoidal height (m).
    pub position: Option<[f64; 3]>,
}

/// The navigation consumer's report (`summary.json` → `nav`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct NavReport {
    /// Per port (by port number).
    pub ports: BTreeMap<u8, PortReport>,
    /// GPS − UTC leap seconds applied to NMEA times, s.
    pub leap_seconds: f64,
}

/// What one port's bytes held.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct PortReport {
    /// Chunks received.
    pub chunks: u64,
    /// Bytes read.
    pub bytes: u64,
    /// Samples decoded.
    pub records: u64,
    /// Samples by record type.
    pub by_kind: BTreeMap<String, u64>,
    /// Candidate records that gave no sample.
    pub rejected: u64,
    /// Rejections by reason.
    pub rejected_by_reason: BTreeMap<String, u64>,
    /// Well-formed records of types not used, by type.
    pub ignored: BTreeMap<String, u64>,
    /// Bytes outside any record.
    pub unframed_bytes: u64,
    /// GPS time of the first dated sample.
    pub first_gps_time: Option<GpsTime>,
    /// GPS time of the last dated sample.
    pub last_gps_time: Option<GpsTime>,
    /// The latest state stated.
    pub latest: LatestState,
}

/// Decodes every port's navigation bytes and reports per port.
pub struct NavDecode {
    leap_seconds: f64,
    earliest_days: Option<i64>,
    ports: BTreeMap<u8, Port>,
}

impl Default for NavDecode {
    fn default() -> Self {
        NavDecode::new(LEAP_SECONDS_NOW, None)
    }
}

impl NavDecode {
    /// A consumer adding `leap_seconds` (GPS − UTC) to NMEA times and correcting dates before
    /// `earliest_days` (since 1970) for week rollover.
    pub fn new(leap_seconds: f64, earliest_days: Option<i64>) -> Self {
        NavDecode {
            leap_seconds,
            earliest_days,
            ports: BTreeMap::new(),
        }
    }
}

fn note(port: &mut Port, t: Option<GpsTime>) {
    if let Some(t) = t {
        port.first.get_or_insert(t);
        port.last = Some(t);
    }
}

impl NavConsumer for NavDecode {
    type Report = NavReport;

    fn consume(&mut self, chunk: NavChunk) {
        let (leap, earliest) = (self.leap_seconds, self.earliest_days);
        let port = self.ports.entry(chunk.port).or_insert_with(|| Port {
            chunks: 0,
            decoder: NavDecoder::new(leap, MAX_UNDATED, earliest),
            first: None,
            last: None,
            state: LatestState::default(),
        });
        port.chunks += 1;
        let mut times = Vec::new();
        let state = &mut port.state;
        let received = chunk.receive_time_ns;
        port.decoder.push(&chunk.bytes, &mut |s, t| {
            times.push(t);
            state.last_record_receive_ns = Some(received);
            if s.fix.is_some() {
                state.fix = s.fix;
                state.fix_kind = Some(format!("{:?}", s.kind));
            }
            if s.satellites.is_some() {
                state.satellites = s.satellites;
            }
            if s.ins_status.is_some() {
                state.ins_status = s.ins_status;
                state.ins_kind = Some(format!("{:?}", s.kind));
            }
            if let (Some(la), Some(lo), Some(h)) = (s.lat, s.lon, s.height) {
                state.position = Some([la, lo, h]);
            }
        });
        for t in times {
            note(port, t);
        }
    }

    fn finish(&mut self) {
        for port in self.ports.values_mut() {
            let mut times = Vec::new();
            port.decoder.finish(&mut |_, t| times.push(t));
            for t in times {
                note(port, t);
            }
        }
    }

    fn report(&self) -> NavReport {
        NavReport {
            ports: self
                .ports
                .iter()
                .map(|(k, p)| {
                    let s = p.decoder.summary();
                    let report = PortReport {
                        chunks: p.chunks,
                        bytes: s.bytes,
                        records: s.records,
                        by_kind: s.by_kind,
                        rejected: s.rejected,
                        rejected_by_reason: s.rejected_by_reason,
                        ignored: s.ignored,
                        unframed_bytes: s.unframed_bytes,
                        first_gps_time: p.first,
                        last_gps_time: p.last,
                        latest: p.state.clone(),
                    };
                    (*k, report)
                })
                .collect(),
            leap_seconds: self.leap_seconds,
        }
    }
}

/// Counts navigation chunks and bytes per port without decoding them: the consumer of runs
/// where decoding is not the point (runtime tests and benchmarks).
#[derive(Debug, Default)]
pub struct NavTally {
    ports: BTreeMap<u8, (u64, u64)>,
}

/// What [`NavTally`] counted.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct TallyReport {
    /// Per port.
    pub ports: BTreeMap<u8, PortTally>,
}

/// Chunks and bytes of one port.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct PortTally {
    /// Chunks.
    pub chunks: u64,
    /// Bytes.
    pub bytes: u64,
}

impl NavConsumer for NavTally {
    type Report = TallyReport;

    fn consume(&mut self, chunk: NavChunk) {
        let e = self.ports.entry(chunk.port).or_insert((0, 0));
        e.0 += 1;
        e.1 += chunk.bytes.len() as u64;
    }

    fn report(&self) -> TallyReport {
        TallyReport {
            ports: self
                .ports
                .iter()
                .map(|(p, &(chunks, bytes))| (*p, PortTally { chunks, bytes }))
                .collect(),
        }
    }
}
