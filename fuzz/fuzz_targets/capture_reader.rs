//! Arbitrary bytes through `CaptureReader`: every record is walked and every frame decoded.
//! The reader promises never to panic, whatever the input.
//!
//! The first input byte chooses the framing: odd -> the rest is prefixed with a valid preamble
//! (so the fuzzer spends its time in the record walker), even -> the rest is read as is (so the
//! preamble checks are exercised too).
#![no_main]

use std::io::Cursor;

use fwlidar::format::capture::preamble;
use fwlidar::format::{CaptureReader, Record};
use fwlidar::pulse::Pulse;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let bytes: Vec<u8> = if mode & 1 == 1 {
        let mut v = preamble().to_vec();
        v.extend_from_slice(rest);
        v
    } else {
        rest.to_vec()
    };
    let len = bytes.len() as u64;
    let Ok(mut reader) = CaptureReader::new(Cursor::new(bytes), "fuzz") else {
        return;
    };
    let mut pulse = Pulse::default();
    let mut records = 0u64;
    while let Some(rec) = reader.next_record() {
        records += 1;
        // A Cursor over memory never fails to read.
        match rec.expect("no I/O error from a Cursor") {
            Record::Frame(f) => {
                // The reader checked the frame: decoding it must succeed.
                f.decode_into(&mut pulse)
                    .expect("a frame the reader accepted decodes");
                assert_eq!(f.pulse_id(), pulse.pulse_id);
            }
            Record::Header(_) | Record::Nav { .. } => {}
        }
        assert!(records <= len, "more records than input bytes");
    }
    assert!(reader.next_record().is_none(), "None is final");
    assert_eq!(reader.position(), len, "the whole input is accounted for");
});
