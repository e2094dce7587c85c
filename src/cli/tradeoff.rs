//! `fwlidar tradeoff`: what accuracy costs in time. Sweeps raw, denoise only, and every
//! deconvolution method at several settings over simulated pulses with known truth
//! ([`crate::eval::tradeoff`]), and writes `tradeoff.csv`, `tradeoff.md` and `tradeoff.svg` into
//! the output folder, each atomically (complete or not at all), after the whole sweep ran.
//! Progress goes to stderr, one line per case.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use crate::cli::Failure;
use crate::eval::report::{Machine, csv, markdown};
use crate::eval::tradeoff::{SweepConfig, default_settings, run_sweep, summarise};
use crate::eval::{plot, report};
use crate::sim::truth::TruthFamily;
use crate::sink::atomic_file::write_atomic;

/// Pulses per case of `--quick`.
pub const QUICK_PULSES: usize = 24;

/// Arguments of `fwlidar tradeoff`.
#[derive(Debug, clap::Args)]
pub struct TradeoffArgs {
    /// Output folder (created if missing): `tradeoff.csv`, `tradeoff.md`, `tradeoff.svg`.
    #[arg(long, default_value = "out/tradeoff")]
    pub out: PathBuf,
    /// Simulated pulses per (pulse width, truth family) case. Default 1000 (24 with `--quick`).
    #[arg(long)]
    pub pulses: Option<usize>,
    /// A fast run for checks: 24 pulses per case unless `--pulses` says otherwise.
    #[arg(long)]
    pub quick: bool,
    /// Outgoing pulse widths, FWHM, ns (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = vec![4.0, 8.0, 16.0])]
    pub widths_ns: Vec<f64>,
    /// Uniform noise half-range, as a fraction of the noise-free received peak.
    #[arg(long, default_value_t = 0.03)]
    pub noise: f32,
    /// Peaks not above this fraction of their waveform's maximum are not counted (0 = every
    /// sign change of the derivative, the seed's literal rule).
    #[arg(long, default_value_t = 0.05)]
    pub peak_floor: f32,
    /// A detected peak agrees with a truth peak within this many bins (0 = the same bin).
    #[arg(long, default_value_t = 1)]
    pub peak_tolerance_bins: usize,
    /// Seed of the simulated truth and noise.
    #[arg(long, default_value_t = 2012)]
    pub seed: u64,
}

/// Runs the sweep and writes the three files.
pub fn run(args: TradeoffArgs) -> Result<(), Failure> {
    let pulses = args
        .pulses
        .unwrap_or(if args.quick { QUICK_PULSES } else { 1000 });
    let config = SweepConfig {
        pulses,
        widths_ns: args.widths_ns.clone(),
        families: TruthFamily::ALL.to_vec(),
        noise_fraction: args.noise,
        peak_floor: args.peak_floor,
        peak_tolerance_bins: args.peak_tolerance_bins,
        seed: args.seed,
        ..SweepConfig::default()
    };
    config.validate().map_err(Failure::usage)?;
    std::fs::create_dir_all(&args.out).map_err(|e| {
        Failure::job(format!(
            "cannot create output folder {}: {e}",
            args.out.display()
        ))
    })?;
    let machine = Machine::detect();
    let settings = default_settings();
    eprintln!(
        "tradeoff: {} settings × {} pulse widths × {} families, {} pulses each, one thread \
         ({} cores, rates for {} worker(s))",
        settings.len(),
        config.widths_ns.len(),
        config.families.len(),
        pulses,
        machine.cores,
        machine.workers
    );
    let start = Instant::now();
    let stderr = std::io::stderr();
    let cases = run_sweep(&config, &settings, |p| {
        let _ = writeln!(
            stderr.lock(),
            "[{:>3}/{}] {:>5} ns {:<8} {:<24} RMSE {:.4}  {:>9.2} µs/pulse",
            p.done,
            p.total,
            p.case.width_ns,
            p.case.family.name(),
            p.setting.label(),
            p.case.rmse.rmse(),
            p.case.median_ns() / 1e3
        );
    })
    .map_err(Failure::job)?;
    let summary = summarise(&settings, &cases);

    let plot_name = "tradeoff.svg";
    let files = [
        ("tradeoff.csv", csv(&settings, &cases, machine.workers)),
        (
            "tradeoff.md",
            markdown(&config, &settings, &cases, &summary, &machine, plot_name),
        ),
        (plot_name, plot::svg(&settings, &summary, machine.workers)),
    ];
    for (name, text) in &files {
        let path = args.out.join(name);
        write_atomic(&path, text.as_bytes()).map_err(Failure::job)?;
    }
    let best = summary
        .iter()
        .filter(|s| s.pareto)
        .map(|s| {
            format!(
                "{} ({} max)",
                settings[s.setting].label(),
                report::rate(s.max_rate_hz(machine.workers))
            )
        })
        .collect::<Vec<_>>();
    eprintln!(
        "tradeoff: done in {:.1} s; Pareto front: {}; wrote {}/{{tradeoff.csv,tradeoff.md,tradeoff.svg}}",
        start.elapsed().as_secs_f64(),
        best.join(", "),
        args.out.display()
    );
    Ok(())
}
