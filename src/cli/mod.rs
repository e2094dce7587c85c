//! The command line (clap): one file per subcommand. Exit codes: 0 success, 1 the job failed
//! (bad input file, I/O error, fatal stage error), 2 usage or configuration error, 130 stopped by
//! a second SIGINT/SIGTERM.

use clap::{Parser, Subcommand, ValueEnum};

pub mod biomass;
pub mod campaign;
pub mod compare;
pub mod completions;
pub mod daemon;
pub mod import;
pub mod inspect;
pub mod inspect_nav;
pub mod learn_kernel;
pub mod man;
pub mod merge;
pub mod metrics;
pub mod metrics_plot;
pub mod process;
pub mod repair;
pub mod replay;
pub mod response;
pub mod simulate;
pub mod tradeoff;
pub mod trees;
pub mod validate;

/// fwlidar — streaming processing of airborne full-waveform LiDAR.
#[derive(Debug, Parser)]
#[command(name = "fwlidar", version, about, long_about = None)]
pub struct Cli {
    /// Log format on stderr.
    #[arg(long, value_enum, default_value_t = LogFormat::Human, global = true)]
    pub log_format: LogFormat,
    /// More log detail (-v debug, -vv trace); `RUST_LOG` overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    /// The command.
    #[command(subcommand)]
    pub command: Command,
}

/// Log output formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Human,
    /// One JSON object per line, for machines.
    Json,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// The on-board daemon: record digitizer frames (network) and navigation (serial ports),
    /// process them live into voxel tiles, serve QC; SIGTERM stops it.
    Run(daemon::RunArgs),
    /// Replay a recorded capture (or a LAS/LAZ, PulseWaves or GEDI L1B waveform file) through the
    /// processing chain into an output folder.
    Replay(replay::ReplayArgs),
    /// Rebuild the header of a LAS 1.4 file cut off by a crash (point count, bounds, per-return
    /// counts), after copying it to FILE.bak.
    Repair(repair::RepairArgs),
    /// Simulate a scene into a capture file.
    Simulate(simulate::SimulateArgs),
    /// Check configuration files (run configs, sensor profiles, scenes); report every error.
    Validate(validate::ValidateArgs),
    /// Describe a capture, LAS/LAZ, PulseWaves or GEDI L1B file: header, record counts, damage;
    /// optionally every pulse as JSON.
    Inspect(inspect::InspectArgs),
    /// Convert a LAS/LAZ, PulseWaves or GEDI L1B waveform file (or a capture) into a capture.
    Import(import::ImportArgs),
    /// Learn the system response (one echo of a hard target, tail included) of each channel
    /// from waveform files' own echoes, for finding echoes against it.
    Response(response::ResponseArgs),
    /// Denoise, deconvolve (and optionally decompose) a table of waveforms (CSV or .npy).
    Process(process::ProcessArgs),
    /// Measure what accuracy costs in time: every method and setting on simulated pulses with
    /// known truth; writes a CSV, a markdown report and an SVG plot.
    Tradeoff(tradeoff::TradeoffArgs),
    /// Combine voxel stores (voxels.zarr) of several flights or replays into one, independent
    /// of order.
    Merge(merge::MergeArgs),
    /// Biomass models from the per-pulse metrics: true plot biomass of a simulated scene,
    /// stepwise regression on plots, prediction to a raster.
    Biomass(biomass::BiomassArgs),
    /// Recompute the forest structure rasters (canopy height, RH, cover, PAI, FHD) from a voxel
    /// store after the flight: each cell's column of voxels is its waveform.
    Metrics(metrics::MetricsArgs),
    /// Draw the relative heights (RH25–RH98 above the ground) and cover of every waveform of a
    /// pulse_metrics.csv as an SVG figure.
    MetricsPlot(metrics_plot::MetricsPlotArgs),
    /// A survey campaign: plan its flight lines, run them (here with N processes) and merge
    /// their voxel stores exactly into one mosaic.
    Campaign(campaign::CampaignArgs),
    /// Reconstruct stems and first-order branches as cylinders from waveform points (a capture
    /// or a replay's hyper point cloud); score them against a simulated scene's trees.
    Trees(trees::TreesArgs),
    /// Compare our returns (a replay's returns.las) with another processor's points of the same
    /// pulses, e.g. the instrument maker's: echoes found, returns per pulse, offsets, intensity.
    Compare(compare::CompareArgs),
    /// Print the shell completion script (bash, zsh, fish, elvish, powershell).
    Completions(completions::CompletionsArgs),
    /// Write the manual pages (fwlidar.1 and one per command) into a folder.
    Man(man::ManArgs),
}

/// A failure to report: the message and the exit code.
#[derive(Debug)]
pub struct Failure {
    /// Exit code (1 job failed, 2 usage/configuration).
    pub code: i32,
    /// What to print after `error: `.
    pub message: String,
}

impl Failure {
    /// A failed job (exit 1).
    pub fn job(message: impl std::fmt::Display) -> Self {
        Failure {
            code: 1,
            message: message.to_string(),
        }
    }
    /// A usage or configuration error (exit 2).
    pub fn usage(message: impl std::fmt::Display) -> Self {
        Failure {
            code: 2,
            message: message.to_string(),
        }
    }
}

impl From<crate::run::RunError> for Failure {
    fn from(e: crate::run::RunError) -> Self {
        match e {
            crate::run::RunError::Usage(m) => Failure::usage(m),
            crate::run::RunError::Job(m) => Failure::job(m),
        }
    }
}

fn init_logging(format: LogFormat, verbose: u8) {
    use tracing_subscriber::EnvFilter;
    let default = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    use std::io::IsTerminal;
    // Colour only where a person reads it: not into a file, a pipe or a test's capture.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false);
    let _ = match format {
        LogFormat::Human => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

/// Runs the command line; returns the process exit code.
pub fn main() -> i32 {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() { 2 } else { 0 };
        }
    };
    init_logging(cli.log_format, cli.verbose);
    let result = match cli.command {
        Command::Run(a) => daemon::run(a),
        Command::Replay(a) => replay::run(a),
        Command::Repair(a) => repair::run(a),
        Command::Simulate(a) => simulate::run(a),
        Command::Validate(a) => validate::run(a),
        Command::Inspect(a) => inspect::run(a),
        Command::Import(a) => import::run(a),
        Command::Process(a) => process::run(a),
        Command::Response(a) => response::run(a),
        Command::Tradeoff(a) => tradeoff::run(a),
        Command::Merge(a) => merge::run(a),
        Command::Biomass(a) => biomass::run(a),
        Command::Metrics(a) => metrics::run(a),
        Command::MetricsPlot(a) => metrics_plot::run(a),
        Command::Trees(a) => trees::run(a),
        Command::Campaign(a) => campaign::run(a),
        Command::Compare(a) => compare::run(a),
        Command::Completions(a) => completions::run(a),
        Command::Man(a) => man::run(a),
    };
    match result {
        Ok(()) => 0,
        Err(f) => {
            eprintln!("error: {}", f.message);
            f.code
        }
    }
}
