//! Arbitrary bytes through the navigation framer, NMEA/NovAtel decoders and dater
//! (`NavDecoder`), fed in pieces whose sizes the first byte chooses, and through the SBET reader.
//! Nothing may panic; the same bytes in other piece sizes give the same samples and counts;
//! everything read is accounted for.
#![no_main]

use fwlidar::nav::decoder::NavDecoder;
use fwlidar::nav::sbet::SbetReader;
use libfuzzer_sys::fuzz_target;

fn run(data: &[u8], piece: usize) -> (Vec<String>, String) {
    let mut dec = NavDecoder::new(18.0, 64, None);
    let mut out = Vec::new();
    for chunk in data.chunks(piece.max(1)) {
        dec.push(chunk, &mut |s, t| out.push(format!("{s:?} {t:?}")));
    }
    dec.finish(&mut |s, t| out.push(format!("{s:?} {t:?}")));
    let summary = dec.summary();
    assert_eq!(summary.records, out.len() as u64);
    assert_eq!(summary.bytes, data.len() as u64);
    assert!(summary.unframed_bytes <= summary.bytes);
    (out, format!("{summary:?}"))
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let whole = run(rest, rest.len());
    let pieces = run(rest, 1 + mode as usize % 17);
    assert_eq!(whole, pieces, "split reads change nothing");
    let n = SbetReader::new(rest, "fuzz.sbet").count();
    assert!(n <= rest.len() / 136 + 1);
});
