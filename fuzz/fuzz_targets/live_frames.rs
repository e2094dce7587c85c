//! Arbitrary bytes through the live digitizer stream parsers (`source::live_frames`): as one
//! datagram, and as a TCP stream cut into reads at points the input chooses. They must never
//! panic; every byte of the stream is either in a returned frame or in a reported skip, and the
//! frames found do not depend on how the stream was cut.
#![no_main]

use fwlidar::source::live_frames::{LIVE_HEADER_LEN, StreamDecoder, StreamItem, parse_datagram};
use libfuzzer_sys::fuzz_target;

/// Decodes `data` pushed in pieces of `step` bytes (0 = all at once); returns the frames
/// (sequence, payload) and checks that frames and skips account for every byte.
fn decode(data: &[u8], step: usize) -> Vec<(u64, Vec<u8>)> {
    let mut d = StreamDecoder::new();
    let mut frames = Vec::new();
    let mut in_frames = 0u64;
    let step = if step == 0 { data.len().max(1) } else { step };
    for piece in data.chunks(step) {
        d.push(piece);
        while let Some(item) = d.next_item() {
            match item {
                StreamItem::Frame(f) => {
                    in_frames += (LIVE_HEADER_LEN + f.payload.len()) as u64;
                    frames.push((f.sequence, f.payload.to_vec()));
                }
                StreamItem::Skipped { bytes, .. } => assert!(bytes > 0),
            }
        }
    }
    let _ = d.finish();
    assert_eq!(in_frames + d.skipped_bytes(), data.len() as u64);
    frames
}

fuzz_target!(|data: &[u8]| {
    if let Ok(f) = parse_datagram(data) {
        assert_eq!(f.payload.len() + LIVE_HEADER_LEN, data.len());
    }
    let step = data.first().map_or(0, |&b| b as usize % 17);
    assert_eq!(
        decode(data, step),
        decode(data, 0),
        "frames depend on the cut"
    );
});
