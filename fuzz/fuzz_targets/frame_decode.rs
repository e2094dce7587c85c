//! Arbitrary payloads through the raw frame and nav decoders (below the record layer, so no
//! CRC stands between the fuzzer and the decoders). They must never panic; a decoded frame must
//! agree with `check_frame` and re-encode to the same payload (reserved bytes aside).
#![no_main]

use fwlidar::format::frame::{
    FRAME_FIXED_LEN, NAV_FIXED_LEN, SEGMENT_HEADER_LEN, check_frame, decode_frame, decode_nav,
    encode_frame,
};
use fwlidar::pulse::Pulse;
use libfuzzer_sys::fuzz_target;

/// `payload` with the reserved bytes (which the encoder writes as zero) cleared.
fn without_reserved(payload: &[u8], bits: u8, n_segments: usize) -> Vec<u8> {
    let mut v = payload.to_vec();
    v[42] = 0;
    v[43] = 0;
    let mut at = FRAME_FIXED_LEN;
    for _ in 0..n_segments {
        v[at + 2] = 0;
        v[at + 3] = 0;
        let n = u32::from_le_bytes([v[at + 12], v[at + 13], v[at + 14], v[at + 15]]) as usize;
        at += SEGMENT_HEADER_LEN + n * (bits as usize / 8);
    }
    v
}

fuzz_target!(|data: &[u8]| {
    let mut pulse = Pulse::default();
    let checked = check_frame(data);
    match decode_frame(data, &mut pulse) {
        Ok(()) => {
            let shape = checked.expect("decode_frame accepted what check_frame rejected");
            assert_eq!(pulse.segments.len(), shape.n_segments as usize);
            assert_eq!(pulse.raw.len(), shape.total_samples);
            assert_eq!(pulse.bits, shape.bits);
            let mut out = Vec::new();
            encode_frame(&pulse, &mut out).expect("a decoded frame re-encodes");
            assert_eq!(
                out,
                without_reserved(data, shape.bits, shape.n_segments as usize),
                "decode/encode round trip"
            );
        }
        Err(e) => {
            assert_eq!(checked.err(), Some(e), "decode_frame and check_frame disagree");
            // On error the pulse is unchanged.
            assert_eq!(pulse.pulse_id, 0);
            assert!(pulse.segments.is_empty() && pulse.raw.is_empty());
        }
    }
    match decode_nav(data) {
        Ok(nav) => {
            assert_eq!(nav.bytes.len() + NAV_FIXED_LEN, data.len());
            assert_eq!(nav.port, data[0]);
        }
        Err(_) => assert!(data.len() < NAV_FIXED_LEN),
    }
});
