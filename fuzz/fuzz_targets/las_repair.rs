//! Arbitrary bytes as a cut LAS file and its `.wdp` through `las_repair::analyse`: the analysis
//! promises never to panic, and a plan never grows the file.
//!
//! Input: a u32 little-endian length n, then n bytes of `.las`, then the `.wdp` (the rest; no
//! `.wdp` when the rest is empty).
#![no_main]

use std::io::Cursor;

use fwlidar::format::las_repair::analyse;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((head, rest)) = data.split_first_chunk::<4>() else {
        return;
    };
    let n = (u32::from_le_bytes(*head) as usize).min(rest.len());
    let (las, wdp) = rest.split_at(n);
    let wdp_info = (!wdp.is_empty()).then(|| ("f.wdp", wdp.len() as u64, &wdp[..wdp.len().min(60)]));
    if let Ok(plan) = analyse(&mut Cursor::new(las), "f.las", las.len() as u64, wdp_info) {
        assert!(plan.new_len <= las.len() as u64);
        assert!(plan.report.points <= las.len() as u64);
    }
});
