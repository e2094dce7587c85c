//! The LAS reader does not allocate per pulse: after opening, its buffers (point record,
//! packet, the pulse's sample buffer) grow only to the largest packet met; reading the real
//! RIEGL file's 2376 pulses costs at most those few growths. For LAZ, the `laz` crate's
//! decompressor is made again at each chunk start (as LASzip does): allocations grow with the
//! chunks, not with the points.

mod common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use fwlidar::format::las_read::LasReader;
use fwlidar::pulse::Pulse;

struct Counting;

thread_local! {
    /// Allocations made by this thread (the test harness's own threads do not count).
    static ALLOCS: Cell<u64> = const { Cell::new(0) };
}

fn count() {
    let _ = ALLOCS.try_with(|c| c.set(c.get() + 1));
}

fn allocs() -> u64 {
    ALLOCS.with(Cell::get)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn reading_pulses_does_not_allocate_per_pulse() {
    let las = fwlidar::fixtures::path("waveform/riegl_q680i/100429_152240_2535pt_UTM.las");
    let mut r = LasReader::open(&las).unwrap();
    let mut p = Pulse::default();
    assert!(r.next_pulse(&mut p).unwrap());
    let before = allocs();
    let mut n = 1;
    while r.next_pulse(&mut p).unwrap() {
        n += 1;
    }
    let during = allocs() - before;
    assert_eq!(n, 2376);
    // The first pulse has 60 samples; the first 120-sample packet grows the packet buffer and
    // the pulse's sample buffer once each.
    assert!(during <= 2, "{during} allocations while reading {n} pulses");
}

/// LAZ (laspy and lazrs, from the real file). The `laz` crate makes its decompressor afresh
/// at each chunk start (its models: thousands of small allocations for point format 9) and
/// creates a few models lazily inside a chunk, when a context is first met. So calls that start
/// no chunk allocate at most a small bounded number per chunk, whatever the points in it: a
/// per-point allocation would cost more than 2000 here.
#[test]
fn reading_laz_allocates_per_chunk_not_per_point() {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("las_read_no_alloc");
    common::write_laz_copies(&dir);
    for (name, chunks) in [("r9.laz", 1u64), ("r9v.laz", 6)] {
        let mut r = LasReader::open(&dir.join(name)).unwrap();
        let mut p = Pulse::default();
        let (mut pulses, mut at_starts, mut elsewhere) = (0u64, 0u64, 0u64);
        loop {
            let started = r.stats().laz_chunks;
            let before = allocs();
            if !r.next_pulse(&mut p).unwrap() {
                break;
            }
            let made = allocs() - before;
            pulses += 1;
            if r.stats().laz_chunks > started {
                at_starts += made;
            } else {
                elsewhere += made;
            }
        }
        assert_eq!(pulses, 2376);
        assert_eq!(r.stats().laz_chunks, chunks);
        eprintln!(
            "{name}: {at_starts} allocations in the calls that started its {chunks} chunks, \
             {elsewhere} in the other {} calls",
            pulses - chunks
        );
        assert!(
            elsewhere <= 64 * chunks,
            "{name}: {elsewhere} allocations outside chunk starts ({chunks} chunks, {pulses} \
             pulses)"
        );
    }
}
