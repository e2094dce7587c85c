//! No allocation per pulse on the hot path: the number of heap allocations of a whole run
//! (source → denoise worker → sink; source → calibrate worker, which fills the signal itself,
//! → sink) must not grow with the number of pulses. A counting global
//! allocator sees every allocation of this test process.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use fwlidar::config::FullPolicy;
use fwlidar::pipeline::runner::{PipelineSpec, StageFactory};
use fwlidar::pipeline::testing::SyntheticSource;
use fwlidar::pipeline::{RunControl, Stage, run};
use fwlidar::signal::{Calibrate, CalibrateConfig, Denoise, DenoiseConfig};
use fwlidar::sink::NullSink;
use fwlidar::sink::nav_tally::NavTally;

struct Counting;
static ALLOCS: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn allocations_for(pulses: u64, workers: usize) -> u64 {
    let factory: StageFactory =
        Arc::new(|| vec![Box::new(Denoise::new(DenoiseConfig::default())) as Box<dyn Stage>]);
    allocations_with(factory, vec!["denoise"], pulses, workers)
}

fn allocations_with(
    factory: StageFactory,
    stage_names: Vec<&'static str>,
    pulses: u64,
    workers: usize,
) -> u64 {
    let spec = PipelineSpec {
        workers,
        queue_capacity: 8,
        input_policy: FullPolicy::Block,
        stages: factory,
        stage_names,
    };
    let before = ALLOCS.load(Ordering::SeqCst);
    let report = run(
        &spec,
        Box::new(SyntheticSource::new(pulses)),
        Box::new(NullSink),
        Box::new(NavTally::default()),
        &RunControl::default(),
        |_| {},
    );
    assert_eq!(report.pulses_out, pulses);
    ALLOCS.load(Ordering::SeqCst) - before
}

#[test]
fn allocations_do_not_grow_with_pulses() {
    for workers in [1, 2] {
        let small = allocations_for(10_000, workers);
        let large = allocations_for(100_000, workers);
        // 90 000 more pulses may fill the bounded pulse pool further (at most
        // workers × (2 × 8 + 8) + 8 pulses of ~5 buffers each), never cost one allocation each.
        assert!(
            large.saturating_sub(small) < 1_000,
            "workers={workers}: {small} allocations for 10 000 pulses, {large} for 100 000"
        );
    }
}

#[test]
fn calibrate_allocates_nothing_per_pulse() {
    let factory: StageFactory = Arc::new(|| {
        vec![Box::new(Calibrate::new(CalibrateConfig {
            t0_is_emission: Some(true),
            ..Default::default()
        })) as Box<dyn Stage>]
    });
    let small = allocations_with(factory.clone(), vec!["calibrate"], 10_000, 1);
    let large = allocations_with(factory, vec!["calibrate"], 100_000, 1);
    assert!(
        large.saturating_sub(small) < 1_000,
        "{small} allocations for 10 000 pulses, {large} for 100 000"
    );
}
