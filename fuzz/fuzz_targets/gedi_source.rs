//! Arbitrary bytes as a GEDI Level 1B granule through `GediSource`: opened from memory, then
//! every pulse read. The reader and the source promise never to panic; errors name the file.
//! Seed with `tests/data/waveform/gedi/GEDI01_B_*.h5`.
#![no_main]

use fwlidar::format::gedi::GediL1b;
use fwlidar::pulse::PulsePool;
use fwlidar::source::gedi::{GediOptions, GediSource};
use fwlidar::pipeline::ports::{Source, SourceEvent};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let source = GediL1b::from_bytes(data, "fuzz.h5")
        .and_then(|g| GediSource::from_l1b(g, GediOptions::default()));
    let mut source = match source {
        Ok(s) => s,
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.starts_with("fuzz.h5"), "error names the file: {msg}");
            return;
        }
    };
    let pool = PulsePool::new(4);
    loop {
        match source.next(&pool) {
            Ok(SourceEvent::Pulse(p)) => pool.give(p),
            Ok(SourceEvent::End) => break,
            Ok(_) => {}
            Err(e) => {
                assert!(e.to_string().starts_with("fuzz.h5"), "{e}");
                break;
            }
        }
    }
    let _ = source.report();
});
