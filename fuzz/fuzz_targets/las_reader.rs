//! Arbitrary bytes as a LAS (or LAZ) file and its `.wdp` through `LasReader`: every pulse is
//! read until the end or an error. The reader promises never to panic, whatever the input, and
//! every error names the file at fault. LAZ inputs (point format bit 7 and the LASzip VLR) go
//! through the `laz` crate's decoder, whose own panics the reader turns into errors.
//!
//! Input: a u32 little-endian length n, then n bytes of `.las`, then the `.wdp` (the rest).
//! When n is larger than what follows, all of it is the `.las` and the `.wdp` is empty. Packets
//! internal to the `.las` (global encoding bit 1) are read from the `.las` bytes.
#![no_main]

use fwlidar::format::las_read::LasReader;
use fwlidar::pulse::{Pulse, SegmentKind};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((head, rest)) = data.split_first_chunk::<4>() else {
        return;
    };
    let n = (u32::from_le_bytes(*head) as usize).min(rest.len());
    let (las, wdp) = rest.split_at(n);
    let names_file = |e: &dyn std::fmt::Display| {
        let m = e.to_string();
        assert!(m.starts_with("las.las: ") || m.starts_with("las.wdp: "), "{m}");
    };
    let mut reader = match LasReader::from_bytes(las, Some(wdp)) {
        Ok(r) => r,
        Err(e) => return names_file(&e),
    };
    let points = reader.info().header.number_of_points;
    let mut pulse = Pulse::default();
    let mut pulses = 0u64;
    let mut samples = 0u64;
    loop {
        match reader.next_pulse(&mut pulse) {
            Ok(true) => {}
            Ok(false) => break,
            Err(e) => {
                names_file(&e);
                break;
            }
        }
        pulses += 1;
        // One return segment from 0 ns holding every sample of the packet.
        assert_eq!(pulse.segments.len(), 1);
        let s = pulse.segments[0];
        assert_eq!((s.kind, s.channel, s.start_ns), (SegmentKind::Return, 0, 0.0));
        assert_eq!(s.len as usize, pulse.raw.len());
        assert!(!pulse.raw.is_empty());
        assert!((1..=16).contains(&pulse.bits));
        assert!(pulse.sample_ns > 0.0);
        if pulse.bits <= 8 {
            assert!(pulse.raw.iter().all(|&c| c <= 255));
        }
        if let Some(g) = pulse.geometry {
            assert!(g.anchor.iter().chain(&g.direction).all(|v| v.is_finite()));
        }
        samples += pulse.raw.len() as u64;
        // Each pulse consumes at least one point record.
        assert!(pulses <= points);
    }
    let stats = reader.stats();
    assert!(stats.points <= points);
    assert!(stats.pulses == pulses);
    // Every sample came from a packet that lies in the data given.
    assert!(stats.waveform_bytes >= samples);
    assert!(stats.waveform_bytes <= samples * 2);
});
