//! The LAS sink does not allocate per pulse after warm-up: descriptors, scratch buffers and
//! writers are sized by the first pulses; writing thousands more costs no heap allocation.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering};

use fwlidar::pipeline::ports::PulseSink;
use fwlidar::pulse::{FittedReturn, Pulse, PulseGeometry, SegmentKind};
use fwlidar::sink::hyper_points::HyperPointSink;
use fwlidar::sink::las_wave::{LasWaveOptions, LasWaveSink};

struct Counting;
static ALLOCS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Allocations are counted on the test's own thread only: the test harness's main thread
    /// allocates now and then while it waits (its channel's waiter), more often on a loaded
    /// machine, and that is not the sink's doing.
    static COUNTED: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

fn counted() -> bool {
    COUNTED.try_with(|c| c.get()).unwrap_or(false)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if counted() {
            ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if counted() {
            ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn pulse(i: u64) -> Pulse {
    let mut p = Pulse {
        pulse_id: i,
        gps_time: i as f64,
        gain_v_per_dn: if i.is_multiple_of(2) { 0.001 } else { 0.002 },
        bits: if i.is_multiple_of(3) { 8 } else { 16 },
        geometry: Some(PulseGeometry {
            anchor: [500_000.0 + i as f64, 6_000_000.0, 1500.0],
            direction: [0.0, 0.001, -0.1499],
        }),
        ..Default::default()
    };
    p.push_segment(SegmentKind::Outgoing, 0, -5.0, 0..16);
    p.push_segment(SegmentKind::Return, 0, 9_000.0, 0..200);
    p.push_segment(SegmentKind::Return, 1, 9_300.0, 0..100);
    for (segment, t) in [(2u16, 9_350.0), (1, 9_020.0), (1, 9_100.0)]
        .into_iter()
        .take(1 + (i % 3) as usize)
    {
        p.returns.push(FittedReturn {
            segment,
            time_ns: t,
            amplitude: 0.5,
            sigma_bins: 2.0,
            ..Default::default()
        });
    }
    p
}

#[test]
fn writing_pulses_does_not_allocate_after_warm_up() {
    COUNTED.with(|c| c.set(true));
    // One test (the allocation counter is global): format 6, then format 9 with its packets.
    for point_format in [6, 9] {
        writes_without_allocating(point_format);
    }
    hyper_points_without_allocating();
}

fn hyper_points_without_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let mut sink = HyperPointSink::create(dir.path(), 0.5, None, 1.0).unwrap();
    let mut pulses: Vec<Pulse> = (0..12).map(pulse).collect();
    for p in &mut pulses {
        let n = p.raw.len();
        p.signal = (0..n).map(|k| (k % 7) as f32 * 0.25).collect();
    }
    for p in &pulses {
        sink.write(p).unwrap();
    }
    let before = ALLOCS.load(Ordering::SeqCst);
    for _ in 0..200 {
        for p in &pulses {
            sink.write(p).unwrap();
        }
    }
    let during = ALLOCS.load(Ordering::SeqCst) - before;
    sink.finish().unwrap();
    assert!(sink.stats().points > 100_000);
    assert_eq!(
        during, 0,
        "hyper points: {during} allocations while writing 2400 pulses"
    );
}

fn writes_without_allocating(point_format: u8) {
    let dir = tempfile::tempdir().unwrap();
    let mut sink = LasWaveSink::create(
        dir.path(),
        LasWaveOptions {
            point_format,
            ..LasWaveOptions::default()
        },
    )
    .unwrap();
    let pulses: Vec<Pulse> = (0..12).map(pulse).collect();
    for p in &pulses {
        sink.write(p).unwrap();
    }
    let before = ALLOCS.load(Ordering::SeqCst);
    for _ in 0..500 {
        for p in &pulses {
            sink.write(p).unwrap();
        }
    }
    let during = ALLOCS.load(Ordering::SeqCst) - before;
    sink.finish().unwrap();
    assert_eq!(sink.stats().points, 501 * 24);
    assert_eq!(
        during, 0,
        "format {point_format}: {during} allocations while writing 6000 pulses"
    );
}
