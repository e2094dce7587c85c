//! The Gaussian decomposition allocates nothing per segment: every buffer is sized when the
//! [`Decomposer`] is built. A counting global allocator sees every allocation of this process
//! (this file holds a single test so no other test allocates concurrently).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering};

use fwlidar::signal::DecomposeConfig;
use fwlidar::signal::decompose::Decomposer;

struct Counting;
static ALLOCS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Counted on the test's own thread only: the harness's waiting thread allocates now and
    /// then on a loaded machine.
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

#[test]
fn decomposer_fits_without_allocating() {
    COUNTED.with(|c| c.set(true));
    let echoes = [
        (60.0f64, 60.0f64, 4.0f64),
        (40.0, 130.0, 4.0),
        (35.0, 136.0, 4.0),
    ];
    let segments: Vec<Vec<f32>> = (0..8)
        .map(|k| {
            (0..256 + 64 * k)
                .map(|i| {
                    let t = i as f64;
                    let s: f64 = echoes
                        .iter()
                        .map(|&(a, mu, s)| a * (-0.5 * ((t - mu - k as f64) / s).powi(2)).exp())
                        .sum();
                    (s + 0.3 * ((i * 7919 % 13) as f64 / 6.0 - 1.0)) as f32
                })
                .collect()
        })
        .collect();
    // The defaults, and the prominence test (its stack passes use the finder's buffers).
    for config in [
        DecomposeConfig::default(),
        DecomposeConfig {
            min_prominence_snr: 2.0,
            ..DecomposeConfig::default()
        },
    ] {
        let mut d = Decomposer::new(config, 4096);
        let mut out = Vec::with_capacity(8);
        let before = ALLOCS.load(Ordering::SeqCst);
        let mut found = 0;
        for _ in 0..50 {
            for y in &segments {
                out.clear();
                d.fit(y, 0.15, &mut out).unwrap();
                found += out.len();
            }
        }
        let allocations = ALLOCS.load(Ordering::SeqCst) - before;
        assert_eq!(allocations, 0);
        assert_eq!(found, 50 * 8 * 3);
    }
    // The waveformlidar-compatible options: raw counts over the record's minimum (the input
    // buffer), a running mean (the smoothing buffer), the package's peak rule and start values.
    let counts: Vec<Vec<u16>> = segments
        .iter()
        .map(|y| y.iter().map(|v| (200.0 + 4.0 * v).round() as u16).collect())
        .collect();
    let config = DecomposeConfig::waveformlidar_compatible();
    let mut d = Decomposer::new(config, 4096);
    let mut out = Vec::with_capacity(8);
    let before = ALLOCS.load(Ordering::SeqCst);
    let mut found = 0;
    for _ in 0..50 {
        for c in &counts {
            out.clear();
            let floor = *c.iter().min().unwrap();
            d.fit_counts(c, floor, 1.0, 0.6, &mut out).unwrap();
            found += out.len();
        }
    }
    let allocations = ALLOCS.load(Ordering::SeqCst) - before;
    assert_eq!(allocations, 0);
    assert!(found >= 50 * 8 * 2, "{found} components");
}
