//! The whole chain per pulse, as `fwlidar replay` runs it: the survey-line scene
//! (`config/scenes/survey_line.toml`: 400 kHz, ±15° oscillating mirror, trees, grass, buildings
//! and open ground, so the real mix of empty, sparse and canopy pulses) simulated once into a
//! capture, then replayed in-process with the embedded configuration (`config/replay.toml`:
//! denoise → Richardson-Lucy 20 → decompose → calibrate, georeferencing, LAS returns and voxel
//! tiles) and `[output] waveforms = false`.
//!
//! One criterion iteration is one whole replay of the capture; the throughput is pulses, so
//! criterion's time per iteration divided by the pulses is the wall time per pulse and its
//! "thrpt" line is pulses per second. After each benchmark the per-stage service times of the
//! last replay (mean, p50, p99, p99.9 per pulse: the mean decides throughput, the tail the
//! latency) are printed and written to `target/bench-chain/<name>.json`.
//!
//! `FWLIDAR_BENCH_CHAIN_PULSES` sets the pulses (default 50 000; the figure is 200 000).
//! Run: `cargo bench --bench chain -- --warm-up-time 1 --measurement-time 20`.

use std::path::{Path, PathBuf};
use std::process::Command;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use fwlidar::cli::replay::replay_quiet;
use fwlidar::config::{RunConfig, load_run_config_with};
use fwlidar::run::RunReport;

fn bench_dir() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("target"));
    target.join("bench-chain")
}

/// The survey-line capture of `pulses` pulses, simulated by the real `fwlidar simulate` unless
/// it is already there.
fn survey_line(pulses: u64) -> PathBuf {
    let dir = bench_dir();
    std::fs::create_dir_all(&dir).expect("create bench dir");
    let capture = dir.join(format!("survey_line_{pulses}.fwcap"));
    if !capture.exists() {
        let status = Command::new(env!("CARGO_BIN_EXE_fwlidar"))
            .args(["simulate", "--scene", "config/scenes/survey_line.toml"])
            .arg("--pulses")
            .arg(pulses.to_string())
            .arg("--out")
            .arg(&capture)
            .args(["--no-progress"])
            .status()
            .expect("run fwlidar simulate");
        assert!(status.success(), "fwlidar simulate failed");
    }
    capture
}

fn config(sets: &[&str]) -> RunConfig {
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    load_run_config_with(None, &sets).expect("embedded configuration")
}

fn replay(capture: &Path, out: &Path, config: &RunConfig, workers: usize) -> RunReport {
    if out.exists() {
        std::fs::remove_dir_all(out).expect("clear the previous output");
    }
    let report = replay_quiet(capture, out, config, Some(workers))
        .unwrap_or_else(|e| panic!("replay failed: {e:?}"));
    assert!(report.fatal.is_none(), "replay failed: {:?}", report.fatal);
    report
}

fn print_stages(name: &str, report: &RunReport) {
    println!(
        "{name}: {} pulses, {:.0} pulses/s wall, workers {}",
        report.pulses_out, report.pulses_per_s, report.workers
    );
    println!(
        "  {:<12} {:>9} {:>9} {:>9} {:>9}   (service time per pulse, µs)",
        "stage", "mean", "p50", "p99", "p99.9"
    );
    for s in &report.stages {
        let v = &s.service;
        println!(
            "  {:<12} {:>9.2} {:>9.2} {:>9.2} {:>9.2}",
            s.name,
            v.mean_ns / 1e3,
            v.p50_ns as f64 / 1e3,
            v.p99_ns as f64 / 1e3,
            v.p999_ns as f64 / 1e3
        );
    }
    let json = serde_json::to_vec_pretty(report).expect("encode report");
    std::fs::write(bench_dir().join(format!("{name}.json")), json).expect("write report");
}

fn chain(c: &mut Criterion) {
    let pulses: u64 = std::env::var("FWLIDAR_BENCH_CHAIN_PULSES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(50_000);
    let capture = survey_line(pulses);
    let mut g = c.benchmark_group("chain_per_pulse");
    g.sample_size(10);
    g.throughput(Throughput::Elements(pulses));
    let cases: [(&str, Vec<&str>); 2] = [
        ("embedded", vec!["output.waveforms=false"]),
        (
            "embedded_no_outputs",
            vec![
                "output.waveforms=false",
                "output.las=false",
                "voxels.enabled=false",
            ],
        ),
    ];
    for (case, sets) in cases {
        let cfg = config(&sets);
        for workers in [1usize, 2] {
            let name = format!("survey_line_{case}_workers{workers}");
            let out = bench_dir().join(&name);
            let mut last = None;
            g.bench_function(format!("survey_line/{case}/workers={workers}"), |b| {
                b.iter(|| last = Some(replay(&capture, &out, &cfg, workers)))
            });
            if let Some(report) = last {
                assert_eq!(report.pulses_out, pulses, "every pulse through the chain");
                print_stages(&name, &report);
            }
        }
    }
    g.finish();
}

criterion_group!(benches, chain);
criterion_main!(benches);
