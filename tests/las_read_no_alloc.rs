//! The LAS reader does not allocate per pulse: after opening, its buffers (point record,
//! packet, the pulse's sample buffer) grow only to the largest packet met; reading the real
//! RIEGL file's 2376 pulses costs at most those few growths.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::PathBuf;

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
