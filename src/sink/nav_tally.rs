//! Counts navigation bytes per port. The navigation parsers (NMEA, NovAtel, SBET) and the
//! trajectory buffer replace it as they land; until then replay at least accounts for every byte.

use std::collections::BTreeMap;

use crate::pipeline::NavConsumer;
use crate::source::NavChunk;

/// Per-port tally of navigation chunks and bytes.
#[derive(Debug, Default)]
pub struct NavTally {
    ports: BTreeMap<u8, (u64, u64)>,
}

impl NavConsumer for NavTally {
    fn consume(&mut self, chunk: NavChunk) {
        let e = self.ports.entry(chunk.port).or_insert((0, 0));
        e.0 += 1;
        e.1 += chunk.bytes.len() as u64;
    }

    fn report(&self) -> serde_json::Value {
        let ports: serde_json::Map<String, serde_json::Value> = self
            .ports
            .iter()
            .map(|(p, (c, b))| {
                (
                    p.to_string(),
                    serde_json::json!({ "chunks": c, "bytes": b }),
                )
            })
            .collect();
        serde_json::json!({ "ports": ports })
    }
}
