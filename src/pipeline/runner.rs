//! The runner: one source thread, N worker threads running the per-pulse stage chain, one sink
//! thread that restores arrival order, and one navigation thread, joined by bounded edges.
//!
//! ```text
//!            ┌─[edge 0]─> worker 0: stage 1 → stage 2 → … ─[edge]─┐
//!  source ───┼─[edge 1]─> worker 1: stage 1 → stage 2 → … ─[edge]─┼─> sink (round-robin merge)
//!     │      └─ …                                                  ┘
//!     └─[nav channel]─> navigation consumer
//! ```
//!
//! The source deals accepted pulses round-robin to the workers; each worker ends the outputs of
//! one input with a `Done` marker; the sink reads the workers in the same round-robin order, so
//! it sees pulses in arrival order without a reorder buffer and with bounded memory. A pulse
//! dropped at the input edge does not advance the round-robin, which keeps the two sides in step.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

use crossbeam_channel::bounded;
use crossbeam_utils::CachePadded;
use serde::Serialize;

use crate::pipeline::edge::FullPolicy;
use crate::pipeline::edge::{EdgeRx, EdgeTx, Sent, edge};
use crate::pipeline::ports::{NavChunk, Source, SourceEvent};
use crate::pipeline::ports::{NavConsumer, PulseSink, Report};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pipeline::telemetry::{LatencyHistogram, LatencySummary, StageReport, StageTelemetry};
use crate::pulse::{Pulse, PulsePool};

/// Drop reason counted when the input edge is full under the drop-newest policy.
pub const INPUT_QUEUE_FULL: &str = "input_queue_full";

/// Builds one worker's chain of stages (called once per worker thread).
pub type StageFactory = Arc<dyn Fn() -> Vec<Box<dyn Stage>> + Send + Sync>;

/// How to run a pipeline.
#[derive(Clone)]
pub struct PipelineSpec {
    /// Worker threads (at least 1).
    pub workers: usize,
    /// Capacity of every edge, pulses.
    pub queue_capacity: usize,
    /// Policy of the edges from the source into the workers.
    pub input_policy: FullPolicy,
    /// Builds each worker's stage chain.
    pub stages: StageFactory,
    /// Stage kind names, in order (for reports when no worker ran).
    pub stage_names: Vec<&'static str>,
}

/// `0` → one worker per core, at least 1, in replay and on board alike. Measured
/// (docs/performance.md, issues 18 and 35): the source and sink threads take a small share of
/// a core each and hand pulses over in batches, so on 2 cores the chain alone runs 1.7× faster
/// with two workers than with one; live, two workers carry more (150 kHz without a drop, 1
/// worker drops 2.5 %) at a lower p99 (21 against 40 ms at 100 kHz). The daemon's default was
/// one per core less one while UDP frames were lost before recording with every core a worker;
/// since the UDP input asks for a 64 MiB receive buffer every frame is recorded at 200 kHz with
/// two workers on two cores.
pub fn resolve_workers(workers: usize) -> usize {
    if workers > 0 {
        return workers;
    }
    thread::available_parallelism()
        .map_or(1, |n| n.get())
        .max(1)
}

/// Live counters of a running pipeline, for progress bars and QC.
///
/// Each counter has one writer thread and sits on its own cache line.
#[derive(Debug, Default)]
pub struct LiveCounters {
    /// Pulses produced by the source.
    pub pulses_in: CachePadded<AtomicU64>,
    /// Pulses written by the sink.
    pub pulses_out: CachePadded<AtomicU64>,
    /// Pulses dropped at the input edge.
    pub input_dropped: CachePadded<AtomicU64>,
    /// Source progress, its own unit (bytes for files).
    pub progress_done: CachePadded<AtomicU64>,
    /// Source progress total (0 when unknown).
    pub progress_total: CachePadded<AtomicU64>,
}

/// Controls of a run: the stop flag (set by SIGINT/SIGTERM) and live counters. `S`, `K`, `N`:
/// the report types of the run's source, sink and navigation consumer (what
/// [`RunControl::publish`] carries).
pub struct RunControl<S = (), K = (), N = ()> {
    /// When set, the source stops reading; everything in flight is processed and flushed.
    pub stop: Arc<AtomicBool>,
    /// Live counters.
    pub live: Arc<LiveCounters>,
    /// Number of the run's first pulse (`Pulse::seq`): 0 for a replay; the daemon continues a
    /// survey's numbering across restarts so that a resumed voxel store takes the new pulses.
    pub seq_base: u64,
    /// When set, every thread publishes its telemetry and report here about four times a
    /// second (the daemon's QC); `None` costs nothing.
    pub publish: Option<Arc<LivePublish<S, K, N>>>,
}

impl<S, K, N> Clone for RunControl<S, K, N> {
    fn clone(&self) -> Self {
        RunControl {
            stop: self.stop.clone(),
            live: self.live.clone(),
            seq_base: self.seq_base,
            publish: self.publish.clone(),
        }
    }
}

impl<S, K, N> Default for RunControl<S, K, N> {
    fn default() -> Self {
        RunControl {
            stop: Arc::default(),
            live: Arc::default(),
            seq_base: 0,
            publish: None,
        }
    }
}

/// How often each thread publishes into [`LivePublish`].
pub const PUBLISH_EVERY: Duration = Duration::from_millis(250);

/// What the threads of a running pipeline publish for live monitoring (QC), each part under its
/// own lock, written about four times a second by its one thread (a copy: no allocation per
/// pulse, one per publication).
pub struct LivePublish<S = (), K = (), N = ()> {
    /// Each worker's stage telemetry, by worker index.
    pub workers: Mutex<Vec<Vec<StageTelemetry>>>,
    /// Arrival-to-sink latency of every pulse so far, ns.
    pub end_to_end: Mutex<LatencyHistogram>,
    /// The source's report (e.g. the recorder's counts, the georeference's misses).
    pub source: Mutex<S>,
    /// The sinks' report (e.g. voxel tiles).
    pub sink: Mutex<K>,
    /// The navigation consumer's report.
    pub nav: Mutex<N>,
    /// Pulses waiting in each worker's input edge, and the edges' capacity.
    pub input_queues: Mutex<Vec<(u64, u64)>>,
    /// Pulses waiting in each worker's output edge (to the sink).
    pub output_queues: Mutex<Vec<u64>>,
    /// A copy of the last pulse the source marked for the waveform viewer
    /// ([`Pulse::qc_sample`], about four a second) as it left the sink, with the time it
    /// was taken.
    pub sampled_pulse: Mutex<Option<(Instant, Box<Pulse>)>>,
}

impl<S: Default, K: Default, N: Default> Default for LivePublish<S, K, N> {
    fn default() -> Self {
        LivePublish {
            workers: Mutex::default(),
            end_to_end: Mutex::default(),
            source: Mutex::default(),
            sink: Mutex::default(),
            nav: Mutex::default(),
            input_queues: Mutex::default(),
            output_queues: Mutex::default(),
            sampled_pulse: Mutex::default(),
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Everything a run did, as written to `summary.json`. `S`, `K`, `N`: the reports of the
/// source, the sink and the navigation consumer, written with their keys in sorted order.
#[derive(Clone, Debug, Serialize)]
pub struct RunReport<S = (), K = (), N = ()>
where
    S: Serialize,
    K: Serialize,
    N: Serialize,
{
    /// fwlidar version that produced the report.
    pub fwlidar_version: String,
    /// Worker threads used.
    pub workers: usize,
    /// Pulses the source produced.
    pub pulses_in: u64,
    /// Pulses written by the sink.
    pub pulses_out: u64,
    /// Pulses dropped, by `reason` (input edge) or `stage.reason`.
    pub dropped: BTreeMap<String, u64>,
    /// Sum of `dropped`.
    pub dropped_total: u64,
    /// Pulses rejected as errors by stages.
    pub errors: u64,
    /// Per-stage telemetry, merged over workers.
    pub stages: Vec<StageReport>,
    /// Time from arrival to the sink, per pulse.
    pub end_to_end: LatencySummary,
    /// The source's own report (e.g. bytes skipped in a damaged capture).
    #[serde(serialize_with = "keys_sorted")]
    pub source: S,
    /// The navigation consumer's report.
    #[serde(serialize_with = "keys_sorted")]
    pub nav: N,
    /// The sinks' reports (e.g. `las`: points written, pulses without geometry), by sink name.
    #[serde(serialize_with = "keys_sorted")]
    pub sinks: K,
    /// Pulses the pool ever allocated: the bound on pulse memory.
    pub pool_allocations: u64,
    /// True when the run was stopped before the source's end (signal).
    pub stopped_early: bool,
    /// The fatal error that ended the run, if any.
    pub fatal: Option<String>,
    /// Wall-clock time, seconds.
    pub wall_time_s: f64,
    /// Pulses written per second of wall time.
    pub pulses_per_s: f64,
}

/// Serialises `report` with the keys of every object in sorted order (through a JSON value),
/// whatever the order of its fields: the order `summary.json` has always had.
fn keys_sorted<T: Serialize, Z: serde::Serializer>(report: &T, s: Z) -> Result<Z::Ok, Z::Error> {
    serde_json::to_value(report)
        .map_err(serde::ser::Error::custom)?
        .serialize(s)
}

/// What a worker sends to the sink: the outputs of one input pulse, the last of them marked
/// (`Last`), or `Done` alone when the input produced no output.
enum WorkerOut {
    Pulse(Box<Pulse>),
    Last(Box<Pulse>),
    Done,
}

fn nanos(d: Duration) -> u64 {
    d.as_nanos().min(u64::MAX as u128) as u64
}

/// Runs `source` through the stages into `sink` until the source ends or `control.stop` is set.
/// `on_tick` is called about ten times a second on the calling thread (progress bars).
pub fn run<S: Report, K: Report, N: Report>(
    spec: &PipelineSpec,
    source: Box<dyn Source<Report = S>>,
    sink: Box<dyn PulseSink<Report = K>>,
    nav: Box<dyn NavConsumer<Report = N>>,
    control: &RunControl<S, K, N>,
    mut on_tick: impl FnMut(&LiveCounters),
) -> RunReport<S, K, N> {
    let started = Instant::now();
    let workers = spec.workers.max(1);
    let cap = spec.queue_capacity.max(2);
    // Bound on pulses in flight: every edge full plus one in hand per thread, plus what the
    // source holds (pulses waiting for navigation): pulses beyond the pool's idle capacity would
    // be freed by the sink and allocated again by the source, one allocation per pulse. (The
    // pool's slots are preallocated, 16 bytes each: the source's share is capped at 2^18.)
    let held = source.held_pulses().min(1 << 18);
    let pool = PulsePool::new(workers * (2 * cap + 8) + 8 + held);
    let fatal = Fatal::new(control.stop.clone());
    let edges = Edges::new(workers, cap, spec.input_policy);
    let (nav_tx, nav_rx) = bounded::<NavChunk>(4096);
    // Disconnected when the sink thread ends: wakes the ticking caller at once.
    let (sink_alive_tx, sink_alive_rx) = bounded::<()>(0);

    thread::scope(|scope| {
        let spawn = |name: String| thread::Builder::new().name(name);
        let nav_thread = spawn("nav".into())
            .spawn_scoped(scope, {
                let publish = control.publish.clone();
                move || nav_loop(nav, nav_rx, publish.as_deref())
            })
            .expect("spawn nav thread");
        let mut worker_threads = Vec::with_capacity(workers);
        for (i, (rx, tx)) in edges.in_rxs.into_iter().zip(edges.out_txs).enumerate() {
            let stages = (spec.stages)();
            let (pool, fatal) = (pool.clone(), fatal.clone());
            let publish = control.publish.clone().map(|p| (i, p));
            worker_threads.push(
                spawn(format!("worker-{i}"))
                    .spawn_scoped(scope, move || {
                        worker(rx, tx, stages, &pool, &|m| fatal.set(m), publish.as_ref())
                    })
                    .expect("spawn worker thread"),
            );
        }
        let sink_thread = spawn("sink".into())
            .spawn_scoped(scope, {
                let (pool, fatal, control) = (pool.clone(), fatal.clone(), control.clone());
                move || {
                    let _alive = sink_alive_tx;
                    sink_loop(sink, edges.out_rxs, &pool, &control, &fatal)
                }
            })
            .expect("spawn sink thread");
        let source_thread = spawn("source".into())
            .spawn_scoped(scope, {
                let (pool, fatal, control) = (pool.clone(), fatal.clone(), control.clone());
                move || source_loop(source, edges.in_txs, nav_tx, &pool, &control, &fatal)
            })
            .expect("spawn source thread");

        while !(source_thread.is_finished() && sink_thread.is_finished()) {
            on_tick(&control.live);
            let _ = sink_alive_rx.recv_timeout(Duration::from_millis(100));
        }
        on_tick(&control.live);

        let (stopped_early, source_report) = source_thread.join().expect("source thread");
        let (e2e, sink_report) = sink_thread.join().expect("sink thread");
        let nav_report = nav_thread.join().expect("nav thread");
        let mut stages: Vec<StageTelemetry> = spec
            .stage_names
            .iter()
            .map(|n| StageTelemetry::new(n))
            .collect();
        for w in worker_threads {
            let tel = w.join().expect("worker thread");
            if stages.len() != tel.len() {
                stages = tel.iter().map(|t| StageTelemetry::new(t.name)).collect();
            }
            for (acc, t) in stages.iter_mut().zip(&tel) {
                acc.merge(t);
            }
        }
        let ended = Ended {
            stopped_early,
            source: source_report,
            sinks: sink_report,
            nav: nav_report,
            end_to_end: e2e,
            stages,
            fatal: fatal.message(),
        };
        ended.report(workers, &control.live, &pool, started)
    })
}

/// The run's first fatal error, shared by its threads: setting it stops the run.
#[derive(Clone)]
struct Fatal {
    message: Arc<Mutex<Option<String>>>,
    stop: Arc<AtomicBool>,
}

impl Fatal {
    fn new(stop: Arc<AtomicBool>) -> Self {
        Fatal {
            message: Arc::new(Mutex::new(None)),
            stop,
        }
    }

    /// Records `msg` unless an error came first, and stops the run.
    fn set(&self, msg: String) {
        let mut f = lock(&self.message);
        if f.is_none() {
            *f = Some(msg);
        }
        self.stop.store(true, Ordering::SeqCst);
    }

    /// The error, if any.
    fn message(&self) -> Option<String> {
        lock(&self.message).clone()
    }
}

/// The edges of a run: one into each worker (with the input's policy) and one out of each
/// worker into the sink (blocking).
struct Edges {
    in_txs: Vec<EdgeTx<Box<Pulse>>>,
    in_rxs: Vec<EdgeRx<Box<Pulse>>>,
    out_txs: Vec<EdgeTx<WorkerOut>>,
    out_rxs: Vec<EdgeRx<WorkerOut>>,
}

impl Edges {
    fn new(workers: usize, cap: usize, input_policy: FullPolicy) -> Self {
        let mut e = Edges {
            in_txs: Vec::with_capacity(workers),
            in_rxs: Vec::with_capacity(workers),
            out_txs: Vec::with_capacity(workers),
            out_rxs: Vec::with_capacity(workers),
        };
        for _ in 0..workers {
            let (tx, rx) = edge::<Box<Pulse>>(cap, input_policy);
            e.in_txs.push(tx);
            e.in_rxs.push(rx);
            let (tx, rx) = edge::<WorkerOut>(cap, FullPolicy::Block);
            e.out_txs.push(tx);
            e.out_rxs.push(rx);
        }
        e
    }
}

/// The navigation thread: every chunk to the consumer; with live publishing, its report about
/// four times a second, and when the bytes stop. Returns the final report.
fn nav_loop<S, K, N: Report>(
    mut nav: Box<dyn NavConsumer<Report = N>>,
    rx: crossbeam_channel::Receiver<NavChunk>,
    publish: Option<&LivePublish<S, K, N>>,
) -> N {
    let mut last = Instant::now();
    loop {
        // With live publishing, wake up when quiet too, so the latest state is published even
        // when the bytes stop.
        let chunk = match &publish {
            None => rx.recv().ok(),
            Some(_) => match rx.recv_timeout(PUBLISH_EVERY) {
                Ok(c) => Some(c),
                Err(crossbeam_channel::RecvTimeoutError::Timeout) => None,
                Err(crossbeam_channel::RecvTimeoutError::Disconnected) => break,
            },
        };
        match (chunk, &publish) {
            (Some(c), _) => nav.consume(c),
            (None, None) => break,
            (None, Some(_)) => {}
        }
        if let Some(p) = &publish
            && last.elapsed() >= PUBLISH_EVERY
        {
            last = Instant::now();
            *lock(&p.nav) = nav.report();
        }
    }
    nav.finish();
    let report = nav.report();
    if let Some(p) = &publish {
        *lock(&p.nav) = report.clone();
    }
    report
}

/// The sink thread: reads the workers' edges in the source's round-robin order, so pulses are
/// written in arrival order; records each pulse's latency from its arrival; with live
/// publishing, publishes the sink's report about four times a second and a copy of each pulse
/// the source marked for the waveform viewer ([`Pulse::qc_sample`]). Returns the end-to-end histogram and the sink's final report.
fn sink_loop<S, K: Report, N>(
    mut sink: Box<dyn PulseSink<Report = K>>,
    mut out_rxs: Vec<EdgeRx<WorkerOut>>,
    pool: &PulsePool,
    control: &RunControl<S, K, N>,
    fatal: &Fatal,
) -> (LatencyHistogram, K) {
    let live = &control.live;
    let publish = control.publish.as_deref();
    let mut e2e = LatencyHistogram::default();
    let mut last_publish = Instant::now();
    let mut finished = vec![false; out_rxs.len()];
    let mut k = 0usize;
    let mut failed = false;
    while !finished.iter().all(|f| *f) {
        if finished[k] {
            k = (k + 1) % out_rxs.len();
            continue;
        }
        let got = match publish {
            None => Ok(out_rxs[k].recv()),
            Some(_) => out_rxs[k].recv_deadline(last_publish + PUBLISH_EVERY),
        };
        let got = match got {
            Ok(g) => g,
            Err(_) => {
                // Quiet: publish what the last pulses changed.
                if let Some(pb) = publish {
                    last_publish = Instant::now();
                    publish_sink(pb, &e2e, sink.as_ref(), &out_rxs);
                }
                continue;
            }
        };
        let (p, last) = match got {
            Some(WorkerOut::Pulse(p)) => (p, false),
            Some(WorkerOut::Last(p)) => (p, true),
            Some(WorkerOut::Done) => {
                k = (k + 1) % out_rxs.len();
                continue;
            }
            None => {
                finished[k] = true;
                k = (k + 1) % out_rxs.len();
                continue;
            }
        };
        if !failed {
            if let Err(e) = sink.write(&p) {
                failed = true;
                fatal.set(format!("sink `{}`: {e}", sink.name()));
            } else {
                e2e.record(nanos(p.arrived.elapsed()));
                let n = live.pulses_out.load(Ordering::Relaxed);
                live.pulses_out.store(n + 1, Ordering::Relaxed);
            }
        }
        if let Some(pb) = publish {
            if last_publish.elapsed() >= PUBLISH_EVERY {
                last_publish = Instant::now();
                publish_sink(pb, &e2e, sink.as_ref(), &out_rxs);
            }
            // The pulse the source marked for the waveform viewer.
            if p.qc_sample {
                let mut slot = lock(&pb.sampled_pulse);
                match slot.as_mut() {
                    Some((t, q)) => {
                        *t = Instant::now();
                        q.copy_from(&p);
                    }
                    None => *slot = Some((Instant::now(), p.clone())),
                }
            }
        }
        pool.give(p);
        if last {
            k = (k + 1) % out_rxs.len();
        }
    }
    if let Err(e) = sink.finish() {
        fatal.set(format!("sink `{}`: {e}", sink.name()));
    }
    if let Some(pb) = publish {
        *lock(&pb.end_to_end) = e2e.clone();
        *lock(&pb.sink) = sink.report();
    }
    (e2e, sink.report())
}

/// Publishes the sink thread's part: the end-to-end latency, the sink's report and the fill of
/// the workers' output edges.
fn publish_sink<S, K: Report, N>(
    pb: &LivePublish<S, K, N>,
    e2e: &LatencyHistogram,
    sink: &dyn PulseSink<Report = K>,
    out_rxs: &[EdgeRx<WorkerOut>],
) {
    *lock(&pb.end_to_end) = e2e.clone();
    *lock(&pb.sink) = sink.report();
    *lock(&pb.output_queues) = out_rxs.iter().map(|rx| rx.len() as u64).collect();
}

/// The source thread: reads the source, numbers its pulses and deals them round-robin to the
/// workers' edges (a pulse dropped at a full edge does not advance the round), with live
/// publishing marks the first pulse queued in each publishing interval for the waveform viewer
/// ([`Pulse::qc_sample`]), hands the navigation bytes to the navigation thread; stops at the source's end, its error (fatal) or
/// the stop flag. Returns whether it was stopped early, and the source's report.
fn source_loop<S: Report, K, N>(
    mut source: Box<dyn Source<Report = S>>,
    mut in_txs: Vec<EdgeTx<Box<Pulse>>>,
    nav_tx: crossbeam_channel::Sender<NavChunk>,
    pool: &PulsePool,
    control: &RunControl<S, K, N>,
    fatal: &Fatal,
) -> (bool, S) {
    let live = &control.live;
    let mut stopped_early = false;
    let mut k = 0usize;
    let mut last_publish = Instant::now();
    // With live publishing, a pulse is marked for the QC page's waveform viewer once every
    // PUBLISH_EVERY (`Pulse::qc_sample`): the first one queued after the interval.
    let mut last_mark = Instant::now();
    loop {
        // One clock reading per turn, and only with live publishing.
        let now = control.publish.as_ref().map(|_| Instant::now());
        if let (Some(pb), Some(now)) = (&control.publish, now)
            && now.duration_since(last_publish) >= PUBLISH_EVERY
        {
            last_publish = now;
            *lock(&pb.source) = source.report();
            *lock(&pb.input_queues) = in_txs
                .iter()
                .map(|tx| (tx.len() as u64, tx.stats().capacity() as u64))
                .collect();
        }
        if control.stop.load(Ordering::Relaxed) {
            stopped_early = true;
            break;
        }
        let ev = source.next(pool);
        if let Some((done, total)) = source.progress() {
            live.progress_done.store(done, Ordering::Relaxed);
            live.progress_total.store(total, Ordering::Relaxed);
        }
        match ev {
            Ok(SourceEvent::Pulse(mut p)) => {
                let n = live.pulses_in.load(Ordering::Relaxed);
                p.seq = control.seq_base + n;
                live.pulses_in.store(n + 1, Ordering::Relaxed);
                let mark = now.is_some_and(|t| t.duration_since(last_mark) >= PUBLISH_EVERY);
                p.qc_sample = mark;
                match in_txs[k].send(p) {
                    Sent::Queued => {
                        if let (true, Some(t)) = (mark, now) {
                            last_mark = t;
                        }
                        k = (k + 1) % in_txs.len();
                    }
                    Sent::Dropped(p) => {
                        live.input_dropped.fetch_add(1, Ordering::Relaxed);
                        pool.give(p);
                    }
                    Sent::Closed(p) => {
                        pool.give(p);
                        break;
                    }
                }
            }
            Ok(SourceEvent::Nav(chunk)) => {
                if nav_tx.send(chunk).is_err() {
                    break;
                }
            }
            Ok(SourceEvent::Idle) => {}
            Ok(SourceEvent::End) => break,
            Err(e) => {
                fatal.set(format!("source `{}`: {e}", source.name()));
                break;
            }
        }
    }
    in_txs.clear();
    drop(nav_tx);
    if let Some(pb) = &control.publish {
        *lock(&pb.source) = source.report();
    }
    (stopped_early, source.report())
}

/// What the threads of a finished run returned.
struct Ended<S, K, N> {
    stopped_early: bool,
    source: S,
    sinks: K,
    nav: N,
    end_to_end: LatencyHistogram,
    stages: Vec<StageTelemetry>,
    fatal: Option<String>,
}

impl<S: Report, K: Report, N: Report> Ended<S, K, N> {
    /// The run's report: counts, drops by reason (the input edge's and the stages'), errors,
    /// telemetry, the ports' reports, wall time and rate since `started`.
    fn report(
        self,
        workers: usize,
        live: &LiveCounters,
        pool: &PulsePool,
        started: Instant,
    ) -> RunReport<S, K, N> {
        let mut dropped = BTreeMap::new();
        let input_dropped = live.input_dropped.load(Ordering::Relaxed);
        if input_dropped > 0 {
            dropped.insert(INPUT_QUEUE_FULL.to_string(), input_dropped);
        }
        let mut errors = 0;
        for s in &self.stages {
            errors += s.errors;
            for (r, c) in s.dropped.iter() {
                *dropped.entry(format!("{}.{r}", s.name)).or_insert(0) += c;
            }
        }
        let wall = started.elapsed().as_secs_f64();
        let pulses_out = live.pulses_out.load(Ordering::Relaxed);
        RunReport {
            fwlidar_version: env!("CARGO_PKG_VERSION").to_string(),
            workers,
            pulses_in: live.pulses_in.load(Ordering::Relaxed),
            pulses_out,
            dropped_total: dropped.values().sum(),
            dropped,
            errors,
            stages: self.stages.iter().map(|s| s.report()).collect(),
            end_to_end: self.end_to_end.summary(),
            source: self.source,
            nav: self.nav,
            sinks: self.sinks,
            pool_allocations: pool.allocated(),
            stopped_early: self.stopped_early,
            fatal: self.fatal,
            wall_time_s: wall,
            pulses_per_s: if wall > 0.0 {
                pulses_out as f64 / wall
            } else {
                0.0
            },
        }
    }
}

/// Where worker `i` publishes its telemetry (with live publishing on).
type WorkerPublish<S, K, N> = (usize, Arc<LivePublish<S, K, N>>);

/// One worker thread: runs every pulse it receives through the whole chain.
fn worker<S, K, N>(
    mut rx: EdgeRx<Box<Pulse>>,
    mut tx: EdgeTx<WorkerOut>,
    mut stages: Vec<Box<dyn Stage>>,
    pool: &PulsePool,
    set_fatal: &dyn Fn(String),
    publish: Option<&WorkerPublish<S, K, N>>,
) -> Vec<StageTelemetry> {
    let mut tel: Vec<StageTelemetry> = stages
        .iter()
        .map(|s| StageTelemetry::new(s.name()))
        .collect();
    let mut cur: Vec<Box<Pulse>> = Vec::with_capacity(16);
    let mut next: Vec<Box<Pulse>> = Vec::with_capacity(16);
    let mut ok = true;
    let mut last_publish = Instant::now();
    let publish_tel = |tel: &[StageTelemetry]| {
        if let Some((i, pb)) = publish {
            let mut w = lock(&pb.workers);
            if w.len() <= *i {
                w.resize_with(*i + 1, Vec::new);
            }
            w[*i] = tel.to_vec();
        }
    };
    loop {
        let p = match publish {
            None => rx.recv(),
            Some(_) => match rx.recv_deadline(last_publish + PUBLISH_EVERY) {
                Ok(p) => p,
                Err(_) => {
                    // Quiet: publish what the last pulses changed.
                    last_publish = Instant::now();
                    publish_tel(&tel);
                    continue;
                }
            },
        };
        let Some(p) = p else { break };
        if publish.is_some() && last_publish.elapsed() >= PUBLISH_EVERY {
            last_publish = Instant::now();
            publish_tel(&tel);
        }
        cur.push(p);
        if let Err(e) = run_chain(&mut stages, &mut tel, &mut cur, &mut next, pool, 0) {
            set_fatal(e.to_string());
            ok = false;
        }
        if !forward(&mut tx, &mut cur, pool, true) || !ok {
            break;
        }
    }
    // End of stream: flush each stage in order, running what it emits through the rest.
    if ok {
        for j in 0..stages.len() {
            let t = &mut tel[j];
            let mut em = Emitter::new(&mut cur, pool, &mut t.dropped, &mut t.errors)
                .with_notes(&mut t.notes);
            let flushed = stages[j].flush(&mut em);
            t.sent += cur.len() as u64;
            let res = flushed
                .and_then(|()| run_chain(&mut stages, &mut tel, &mut cur, &mut next, pool, j + 1));
            if let Err(e) = res {
                set_fatal(e.to_string());
                break;
            }
            forward(&mut tx, &mut cur, pool, false);
        }
    }
    for p in cur.drain(..) {
        pool.give(p);
    }
    // Anything still queued for us goes back to the pool.
    drop(rx);
    publish_tel(&tel);
    tel
}

/// Sends every pulse in `cur` to the sink; with `end_group`, marks the end of one input's
/// outputs (the last pulse as `Last`, or a lone `Done`). False when the sink is gone.
fn forward(
    tx: &mut EdgeTx<WorkerOut>,
    cur: &mut Vec<Box<Pulse>>,
    pool: &PulsePool,
    end_group: bool,
) -> bool {
    let n = cur.len();
    let mut open = true;
    for (i, p) in cur.drain(..).enumerate() {
        if !open {
            pool.give(p);
            continue;
        }
        let msg = if end_group && i + 1 == n {
            WorkerOut::Last(p)
        } else {
            WorkerOut::Pulse(p)
        };
        if let Sent::Closed(WorkerOut::Pulse(p) | WorkerOut::Last(p)) = tx.send(msg) {
            pool.give(p);
            open = false;
        }
    }
    if open && end_group && n == 0 && matches!(tx.send(WorkerOut::Done), Sent::Closed(_)) {
        open = false;
    }
    open
}

/// Runs the pulses in `cur` through stages `from..`, leaving the survivors in `cur`.
fn run_chain(
    stages: &mut [Box<dyn Stage>],
    tel: &mut [StageTelemetry],
    cur: &mut Vec<Box<Pulse>>,
    next: &mut Vec<Box<Pulse>>,
    pool: &PulsePool,
    from: usize,
) -> Result<(), StageError> {
    // One clock reading per stage and pulse: a stage's service time runs from the end of the
    // previous one (the few nanoseconds of hand-over between stages are counted to the next).
    let mut clock = Instant::now();
    for j in from..stages.len() {
        let t = &mut tel[j];
        for p in cur.drain(..) {
            t.received += 1;
            let arrived = p.arrived;
            let before = next.len();
            let start = clock;
            let mut em =
                Emitter::new(next, pool, &mut t.dropped, &mut t.errors).with_notes(&mut t.notes);
            stages[j].process(p, &mut em)?;
            let end = Instant::now();
            clock = end;
            t.sent += (next.len() - before) as u64;
            t.service.record(nanos(end - start));
            t.since_arrival
                .record(nanos(end.saturating_duration_since(arrived)));
        }
        std::mem::swap(cur, next);
    }
    Ok(())
}
