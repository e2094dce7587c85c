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
    /// This thread's counted allocations (the two tests run at once).
    static MINE: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

fn mine() -> u64 {
    MINE.with(|c| c.get())
}

fn count_one() {
    ALLOCS.fetch_add(1, Ordering::Relaxed);
    let _ = MINE.try_with(|c| c.set(c.get() + 1));
}

fn counted() -> bool {
    COUNTED.try_with(|c| c.get()).unwrap_or(false)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if counted() {
            count_one();
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if counted() {
            count_one();
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

/// Echoes found against a learned response allocate nothing per pulse either: the stage's
/// finder and buffers are sized when it is built.
#[test]
fn echoes_against_a_learned_response_are_found_without_allocating() {
    use fwlidar::pulse::{Pulse, SegmentKind};
    use fwlidar::signal::decompose::{Decompose, EchoModel};
    use fwlidar::signal::learned_response::ResponseLearner;
    // A receiver with a tail: Gaussian core, a 5 % bump 10 samples after, a 2 % tail.
    let response = |x: f64| {
        (-0.5 * (x / 1.87).powi(2)).exp()
            + 0.05 * (-0.5 * ((x - 10.0) / 1.5).powi(2)).exp()
            + if x > 3.0 {
                0.02 * (-(x - 3.0) / 15.0).exp()
            } else {
                0.0
            }
    };
    let segment = |echoes: &[(f64, f64)], k: usize| -> Vec<u16> {
        (0..96)
            .map(|i| {
                let s: f64 = echoes
                    .iter()
                    .map(|&(a, at)| a * response(i as f64 - at - 0.37 * k as f64))
                    .sum();
                (3.0 + s + ((i * 7919 + k) % 3) as f64 - 1.0)
                    .round()
                    .max(0.0) as u16
            })
            .collect()
    };
    let mut learner = ResponseLearner::new();
    for k in 0..400 {
        let y: Vec<f32> = segment(&[(100.0 + (k % 90) as f64, 20.0)], k % 7)
            .iter()
            .map(|&c| f32::from(c))
            .collect();
        learner.add_segment(0, 1.0, &y, 255.0);
    }
    let file = std::sync::Arc::new(learner.finish("test").unwrap());
    let mut stage = Decompose::new(DecomposeConfig {
        model: EchoModel::Response,
        learned: Some(file),
        ..DecomposeConfig::default()
    });
    let mut pulses: Vec<Pulse> = (0..8)
        .map(|k| {
            let mut p = Pulse {
                bits: 8,
                gain_v_per_dn: 1.0,
                ..Pulse::default()
            };
            p.push_segment(
                SegmentKind::Return,
                0,
                0.0,
                segment(&[(150.0, 20.0), (60.0, 45.0), (40.0, 51.0)], k),
            );
            p.signal = p.raw.iter().map(|&c| f32::from(c)).collect();
            p.returns.reserve(16);
            p
        })
        .collect();
    COUNTED.with(|c| c.set(true));
    let before = mine();
    let mut found = 0;
    for _ in 0..50 {
        for p in &mut pulses {
            stage.decompose_pulse(p);
            found += p.returns.len();
        }
    }
    let allocations = mine() - before;
    COUNTED.with(|c| c.set(false));
    assert_eq!(allocations, 0);
    assert_eq!(found, 50 * 8 * 3, "three echoes, their tails none");
}
