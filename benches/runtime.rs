//! Runtime overhead per pulse: pulses without samples through three no-op stages, from a source
//! thread through the workers to a null sink. One criterion iteration = one pulse.

use std::sync::Arc;
use std::time::Instant;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::nav::consumer::NavTally;
use fwlidar::pipeline::edge::FullPolicy;
use fwlidar::pipeline::ports::NullSink;
use fwlidar::pipeline::runner::{PipelineSpec, StageFactory};
use fwlidar::pipeline::testing::SyntheticSource;
use fwlidar::pipeline::{RunControl, Stage, run};
use fwlidar::stages::passthrough::Passthrough;

fn overhead(c: &mut Criterion) {
    let mut g = c.benchmark_group("runtime_overhead_per_pulse");
    for workers in [1usize, 2] {
        let factory: StageFactory = Arc::new(|| {
            vec![
                Box::new(Passthrough) as Box<dyn Stage>,
                Box::new(Passthrough),
                Box::new(Passthrough),
            ]
        });
        let spec = PipelineSpec {
            workers,
            queue_capacity: 1024,
            input_policy: FullPolicy::Block,
            stages: factory,
            stage_names: vec!["passthrough"; 3],
        };
        g.bench_function(format!("three_noop_stages/workers={workers}"), |b| {
            b.iter_custom(|iters| {
                let start = Instant::now();
                let report = run(
                    &spec,
                    Box::new(SyntheticSource::empty(iters)),
                    Box::new(NullSink),
                    Box::new(NavTally::default()),
                    &RunControl::default(),
                    |_| {},
                );
                assert_eq!(report.pulses_out, iters);
                start.elapsed()
            })
        });
    }
    g.finish();
}

criterion_group!(benches, overhead);
criterion_main!(benches);
