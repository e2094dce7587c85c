//! Replay's navigation consumer: each port's bytes through the framer, the NMEA/NovAtel
//! decoders and the NMEA dater (`nav::decoder::NavDecoder`), so `summary.json` says what the
//! navigation stream held — samples by type, their GPS time span, rejections by reason — not
//! just how many bytes came. (The trajectory and the georeference stage build on it next.)

use std::collections::BTreeMap;

use crate::nav::dating::GpsTime;
use crate::nav::decoder::{LEAP_SECONDS_NOW, NavDecoder};
use crate::pipeline::NavConsumer;
use crate::source::NavChunk;

/// Samples held per port while waiting for the first date.
const MAX_UNDATED: usize = 512;

struct Port {
    chunks: u64,
    decoder: NavDecoder,
    first: Option<GpsTime>,
    last: Option<GpsTime>,
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
    fn consume(&mut self, chunk: NavChunk) {
        let (leap, earliest) = (self.leap_seconds, self.earliest_days);
        let port = self.ports.entry(chunk.port).or_insert_with(|| Port {
            chunks: 0,
            decoder: NavDecoder::new(leap, MAX_UNDATED, earliest),
            first: None,
            last: None,
        });
        port.chunks += 1;
        let mut times = Vec::new();
        port.decoder.push(&chunk.bytes, &mut |_, t| times.push(t));
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

    fn report(&self) -> serde_json::Value {
        let ports: serde_json::Map<String, serde_json::Value> = self
            .ports
            .iter()
            .map(|(k, p)| {
                let s = p.decoder.summary();
                (
                    k.to_string(),
                    serde_json::json!({
                        "chunks": p.chunks,
                        "bytes": s.bytes,
                        "records": s.records,
                        "by_kind": s.by_kind,
                        "rejected": s.rejected,
                        "rejected_by_reason": s.rejected_by_reason,
                        "ignored": s.ignored,
                        "unframed_bytes": s.unframed_bytes,
                        "first_gps_time": p.first,
                        "last_gps_time": p.last,
                    }),
                )
            })
            .collect();
        serde_json::json!({ "ports": ports, "leap_seconds": self.leap_seconds })
    }
}
