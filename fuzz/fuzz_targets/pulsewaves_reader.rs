//! Arbitrary bytes as a PulseWaves `.pls` + `.wvs` pair through `PulseWavesReader`: the header,
//! every record and every pulse's waves are read. The reader promises never to panic.
//!
//! Input layout: a little-endian u16 `n`, then `n` bytes of `.pls` (fewer if the input is
//! shorter), then the rest as the `.wvs`.
#![no_main]

use std::io::Cursor;

use fwlidar::format::pulsewaves::PulseWavesReader;
use fwlidar::pulse::Pulse;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((len, rest)) = data.split_first_chunk::<2>() else {
        return;
    };
    let n = usize::from(u16::from_le_bytes(*len)).min(rest.len());
    let (pls, wvs) = rest.split_at(n);
    let reader = PulseWavesReader::new(
        Cursor::new(pls.to_vec()),
        "fuzz.pls",
        Cursor::new(wvs.to_vec()),
        "fuzz.wvs",
    );
    let mut reader = match reader {
        Ok(r) => r,
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.starts_with("fuzz."), "error names the file: {msg}");
            return;
        }
    };
    let total = reader.number_of_pulses();
    // The pulse table was checked against the file: it cannot claim more records than bytes.
    assert!(total <= pls.len() as u64);
    let mut pulse = Pulse::default();
    loop {
        match reader.read_pulse(&mut pulse) {
            Ok(true) => {
                assert!(pulse.pulse_id < total);
                for s in &pulse.segments {
                    assert!(s.range().end <= pulse.raw.len());
                }
                assert!(matches!(pulse.bits, 8 | 16));
                assert!(pulse.sample_ns > 0.0);
            }
            Ok(false) => {
                assert_eq!(reader.pulses_read(), total);
                // The end stays the end.
                assert!(!reader.read_pulse(&mut pulse).expect("end is final"));
                break;
            }
            Err(e) => {
                let msg = e.to_string();
                assert!(msg.starts_with("fuzz."), "error names the file: {msg}");
                break;
            }
        }
    }
    assert!(reader.wave_bytes_read() <= reader.waves_len().saturating_mul(reader.pulses_read().max(1)));
});
