//! The streaming runtime end to end with synthetic pulses: order restored across workers,
//! overload accounting under drop-newest, bounded memory, fatal errors, flush at the end.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use fwlidar::nav::consumer::NavTally;
use fwlidar::pipeline::edge::FullPolicy;
use fwlidar::pipeline::runner::{INPUT_QUEUE_FULL, PipelineSpec, StageFactory};
use fwlidar::pipeline::testing::{IdSink, SyntheticSource};
use fwlidar::pipeline::{Emitter, RunControl, Stage, StageError, run};
use fwlidar::pulse::Pulse;
use fwlidar::stages::passthrough::Passthrough;

fn spec(workers: usize, cap: usize, policy: FullPolicy, stages: StageFactory) -> PipelineSpec {
    PipelineSpec {
        workers,
        queue_capacity: cap,
        input_policy: policy,
        stages,
        stage_names: vec![],
    }
}

/// Drops every pulse whose id is divisible by `every`, and sleeps `delay` per pulse.
struct Picky {
    every: u64,
    delay: Duration,
}
impl Stage for Picky {
    fn name(&self) -> &'static str {
        "picky"
    }
    fn process(&mut self, p: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        if !self.delay.is_zero() {
            std::thread::sleep(self.delay);
        }
        if self.every > 0 && p.pulse_id.is_multiple_of(self.every) {
            out.drop_pulse(p, "divisible");
        } else {
            out.emit(p);
        }
        Ok(())
    }
}

#[test]
fn order_is_restored_across_workers_with_drops() {
    for workers in [1, 2, 3, 5] {
        let factory: StageFactory = Arc::new(|| {
            vec![
                Box::new(Passthrough) as Box<dyn Stage>,
                Box::new(Picky {
                    every: 7,
                    delay: Duration::ZERO,
                }),
                Box::new(Passthrough),
            ]
        });
        let sink = IdSink::default();
        let ids = sink.ids.clone();
        let flushed = sink.flushed.clone();
        let report = run(
            &spec(workers, 8, FullPolicy::Block, factory),
            Box::new(SyntheticSource::new(20_000)),
            Box::new(sink),
            Box::new(NavTally::default()),
            &RunControl::default(),
            |_| {},
        );
        let ids = ids.lock().unwrap();
        let expect: Vec<u64> = (0..20_000u64).filter(|i| !i.is_multiple_of(7)).collect();
        assert_eq!(*ids, expect, "workers={workers}");
        assert!(flushed.load(Ordering::SeqCst));
        assert_eq!(report.pulses_in, 20_000);
        assert_eq!(report.pulses_out, expect.len() as u64);
        assert_eq!(
            report.dropped["picky.divisible"],
            20_000 - expect.len() as u64
        );
        assert_eq!(report.pulses_in, report.pulses_out + report.dropped_total);
        assert_eq!(report.stages.len(), 3);
        assert_eq!(report.stages[0].received, 20_000);
        assert_eq!(report.stages[2].sent, expect.len() as u64);
        assert!(report.stages[1].service.count == 20_000);
        assert!(report.fatal.is_none());
    }
}

#[test]
fn overload_with_drop_newest_is_bounded_and_counted_exactly() {
    // A stage ~50x slower than the source: most pulses must be dropped at the input edge.
    let factory: StageFactory = Arc::new(|| {
        vec![Box::new(Picky {
            every: 0,
            delay: Duration::from_micros(200),
        }) as Box<dyn Stage>]
    });
    let cap = 16;
    let workers = 2;
    let report = run(
        &spec(workers, cap, FullPolicy::DropNewest, factory),
        Box::new(SyntheticSource::new(50_000)),
        Box::new(IdSink::default()),
        Box::new(NavTally::default()),
        &RunControl::default(),
        |_| {},
    );
    let dropped = report.dropped.get(INPUT_QUEUE_FULL).copied().unwrap_or(0);
    assert!(dropped > 10_000, "expected heavy dropping, got {dropped}");
    assert_eq!(report.pulses_in, 50_000);
    assert_eq!(report.stages[0].received + dropped, report.pulses_in);
    assert_eq!(report.pulses_out, report.stages[0].sent);
    assert_eq!(report.pulses_in, report.pulses_out + report.dropped_total);
    // Memory bounded: pulses ever allocated never exceed what the edges can hold in flight.
    assert!(
        report.pool_allocations <= (workers * (2 * cap + 8) + 8) as u64,
        "pool allocated {}",
        report.pool_allocations
    );
}

#[test]
fn blocking_replay_loses_nothing_and_reuses_pulses() {
    let factory: StageFactory = Arc::new(|| {
        vec![Box::new(Picky {
            every: 0,
            delay: Duration::from_micros(20),
        }) as Box<dyn Stage>]
    });
    let report = run(
        &spec(2, 4, FullPolicy::Block, factory),
        Box::new(SyntheticSource::new(3_000)),
        Box::new(IdSink::default()),
        Box::new(NavTally::default()),
        &RunControl::default(),
        |_| {},
    );
    assert_eq!(report.pulses_out, 3_000);
    assert_eq!(report.dropped_total, 0);
    assert!(report.pool_allocations < 100, "{}", report.pool_allocations);
}

struct Fails;
impl Stage for Fails {
    fn name(&self) -> &'static str {
        "fails"
    }
    fn process(&mut self, p: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        if p.pulse_id == 100 {
            return Err(StageError::Fatal {
                stage: "fails",
                message: "calibration lost".into(),
            });
        }
        out.emit(p);
        Ok(())
    }
}

#[test]
fn fatal_stage_error_stops_the_run_and_is_reported() {
    let factory: StageFactory = Arc::new(|| vec![Box::new(Fails) as Box<dyn Stage>]);
    let sink = IdSink::default();
    let flushed = sink.flushed.clone();
    let report = run(
        &spec(2, 8, FullPolicy::Block, factory),
        Box::new(SyntheticSource::new(1_000_000)),
        Box::new(sink),
        Box::new(NavTally::default()),
        &RunControl::default(),
        |_| {},
    );
    let fatal = report.fatal.expect("fatal reported");
    assert!(fatal.contains("calibration lost"), "{fatal}");
    assert!(report.pulses_in < 1_000_000);
    assert!(
        flushed.load(Ordering::SeqCst),
        "sink flushed even after a fatal error"
    );
}

#[test]
fn stop_flag_ends_the_run_cleanly() {
    let factory: StageFactory = Arc::new(|| vec![Box::new(Passthrough) as Box<dyn Stage>]);
    let control = RunControl::default();
    let stop = control.stop.clone();
    let sink = IdSink::default();
    let ids = sink.ids.clone();
    let flushed = sink.flushed.clone();
    let mut ticks = 0;
    let report = run(
        &spec(2, 8, FullPolicy::Block, factory),
        Box::new(SyntheticSource::new(u64::MAX)),
        Box::new(sink),
        Box::new(NavTally::default()),
        &control,
        |_| {
            ticks += 1;
            if ticks == 3 {
                stop.store(true, Ordering::SeqCst);
            }
        },
    );
    assert!(report.stopped_early);
    assert!(flushed.load(Ordering::SeqCst));
    let ids = ids.lock().unwrap();
    assert_eq!(ids.len() as u64, report.pulses_out);
    assert_eq!(report.pulses_in, report.pulses_out);
    assert!(ids.windows(2).all(|w| w[1] == w[0] + 1));
}
