//! `fwlidar replay`: a recorded capture through the processing chain into an output folder, with
//! a progress bar, `summary.json`, and a one-screen summary at the end. Parse the command line,
//! put the run together (`run::assemble`), run it, print the summary (`run::summary`).

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::config::RunConfig;
use crate::pipeline::run as run_pipeline;
use crate::pipeline::runner::LiveCounters;
use crate::run::assemble::{Assembled, Workers, assemble};
use crate::run::input::Input;
use crate::run::learn::{LEARN_PULSES, ResponseReport, learn_from_file, response_report};
use crate::run::outputs::{prepare_out_dir, replay_run_key, replay_sinks};
use crate::run::summary::{Summary, print_summary, write_summary};
use crate::run::warnings::{log_warnings, run_warnings};
use crate::run::{RunControl, RunReport};
use crate::source::shard::Shard;
use crate::stages::wants_learned_response;

/// The sample replayed when no input is named, relative to the repository's root.
pub const DEFAULT_SAMPLE: &str = "replay/two_layer.fwcap";

/// Arguments of `fwlidar replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// File to replay: a capture, LAS or LAZ (+ .wdp), PulseWaves (.pls + .wvs) or GEDI L1B
    /// (.h5). Several are replayed one after another into the one output folder and voxel
    /// store, as one recording (each georeferenced by its own navigation; they must share the
    /// sensor and the output CRS). Default: the sample capture `replay/two_layer.fwcap` of the
    /// repository (looked for in the working folder, then in the source tree this program was
    /// built from).
    pub inputs: Vec<PathBuf>,
    /// Output folder (created if missing; files in it are replaced only by complete new ones).
    /// Default: the configuration's `[output] dir`, `out` in the embedded configuration.
    #[arg(long, short)]
    pub out: Option<PathBuf>,
    /// Run configuration file (default: the embedded `config/replay.toml`).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Worker threads for the per-pulse stages (overrides the configuration; 0 = automatic).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
    /// Replay only the `i`-th of `n` contiguous ranges of the input's pulses (1 ≤ i ≤ n; the
    /// inputs in sequence count as one), e.g. `--shard 2/4`: a line too long for one node
    /// split across nodes. All navigation is still read. The `n` shards' voxel stores merge
    /// (`fwlidar merge`) into exactly the whole input's.
    #[arg(long, value_name = "I/N")]
    pub shard: Option<Shard>,
    /// Override a key of the run configuration, `KEY=VALUE` (dotted key with list indices,
    /// TOML value), checked like the file, e.g. `--set output.las=true --set
    /// 'pipeline.stages[1].max_taps=128'`. Repeatable; a later one wins.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Deconvolve to a Gaussian target pulse of this FWHM, ns (e.g. 2): sets `target_fwhm_ns`
    /// of the configuration's last deconvolve stage (the one by the outgoing pulse; see
    /// `docs/signal.md`). Refused when the configuration has no deconvolve stage.
    #[arg(long)]
    pub target_fwhm_ns: Option<f64>,
}

/// Sets `target_fwhm_ns` of the last deconvolve stage of `config` (`--target-fwhm-ns`).
pub fn set_target_fwhm(config: &mut RunConfig, fwhm_ns: f64) -> Result<(), Failure> {
    use crate::stages::StageConfig;
    crate::signal::deconvolve::target::check_target_fwhm("--target-fwhm-ns", fwhm_ns)
        .map_err(Failure::usage)?;
    let last = config
        .pipeline
        .stages
        .iter_mut()
        .rev()
        .find_map(|s| match s {
            StageConfig::Deconvolve(c) => Some(c),
            _ => None,
        })
        .ok_or_else(|| {
            Failure::usage(
                "--target-fwhm-ns needs a deconvolve stage in the run configuration, and it has none",
            )
        })?;
    last.target_fwhm_ns = Some(fwhm_ns);
    Ok(())
}

/// Registers SIGINT and SIGTERM: the first sets `control.stop` (clean shutdown, every sink
/// flushed); a second one exits at once with code 130.
pub fn install_signal_handlers(control: &RunControl) -> Result<(), Failure> {
    use signal_hook::consts::{SIGINT, SIGTERM};
    for sig in [SIGINT, SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 130, control.stop.clone())
            .and_then(|_| signal_hook::flag::register(sig, control.stop.clone()))
            .map_err(|e| Failure::job(format!("cannot install signal handler: {e}")))?;
    }
    Ok(())
}

/// Runs `fwlidar replay`: put the run together, run it with a progress bar, then report
/// (summary.json, the one-screen summary, the warnings).
pub fn run(args: ReplayArgs) -> Result<(), Failure> {
    let mut config: RunConfig =
        crate::config::load_run_config_with(args.config.as_deref(), &args.sets)
            .map_err(Failure::usage)?;
    if let Some(f) = args.target_fwhm_ns {
        set_target_fwhm(&mut config, f)?;
    }
    let out_dir = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(&config.output.dir));
    let inputs = if args.inputs.is_empty() {
        vec![default_sample()?]
    } else {
        args.inputs.clone()
    };
    let (run, response) = put_together(&inputs, args.shard, &out_dir, &config, args.workers)?;
    let control = RunControl::default();
    install_signal_handlers(&control)?;
    let label = inputs_label(&inputs, args.shard);
    tracing::info!(
        "replaying {label} into {} with {} workers: {}",
        out_dir.display(),
        run.spec.workers,
        run.spec.stage_names.join(" → ")
    );
    let chain = run.chain.clone();
    let report = run_with_progress(run, &control, args.no_progress);
    let warnings = run_warnings(&report, &chain, &config);
    finish(
        &report,
        &warnings,
        &chain,
        &label,
        &out_dir,
        response.as_ref(),
    )
}

/// The sample capture replayed when no file is named: `replay/two_layer.fwcap` in the working
/// folder (a clone's root), else in the source tree the binary was built from; a usage error
/// saying where it is otherwise.
fn default_sample() -> Result<PathBuf, Failure> {
    let here = PathBuf::from(DEFAULT_SAMPLE);
    if here.is_file() {
        return Ok(here);
    }
    let built_from = Path::new(env!("CARGO_MANIFEST_DIR")).join(DEFAULT_SAMPLE);
    if built_from.is_file() {
        return Ok(built_from);
    }
    Err(Failure::usage(format!(
        "no file to replay was named, and the sample capture is not here: it is \
         {DEFAULT_SAMPLE} in the fwlidar repository (run from a clone's root, or name a capture, \
         LAS/LAZ, PulseWaves or GEDI L1B file: fwlidar replay FILE --out DIR)"
    )))
}

/// The inputs as the summary names them: their paths, and the shard.
fn inputs_label(inputs: &[PathBuf], shard: Option<Shard>) -> String {
    let names: Vec<String> = inputs.iter().map(|p| p.display().to_string()).collect();
    match shard {
        Some(s) => format!("{} (shard {s})", names.join(" + ")),
        None => names.join(" + "),
    }
}

/// A replay without the command's trimmings (no progress bar, signal handlers, summary or
/// warnings): `input` through the configured stages into the outputs under `out_dir`, as
/// `fwlidar replay` runs it. For benchmarks and embedding; `workers` overrides the
/// configuration's.
pub fn replay_quiet(
    input: &Path,
    out_dir: &Path,
    config: &RunConfig,
    workers: Option<usize>,
) -> Result<RunReport, Failure> {
    let (run, _) = put_together(&[input.to_path_buf()], None, out_dir, config, workers)?;
    Ok(run_pipeline(
        &run.spec,
        run.source,
        run.sinks,
        run.nav,
        &RunControl::default(),
        |_| {},
    ))
}

/// What both [`run`] and [`replay_quiet`] set up: the inputs opened and georeferenced, the
/// system response learned from the first input when the chain asks for one, the output folder
/// prepared, the stages, the outputs; and what the response is, for the summary.
fn put_together(
    inputs: &[PathBuf],
    shard: Option<Shard>,
    out_dir: &Path,
    config: &RunConfig,
    workers: Option<usize>,
) -> Result<(Assembled, Option<ResponseReport>), Failure> {
    let input = Input::open_files(inputs, shard, config)?;
    let (learned, not_learned) = if wants_learned_response(&config.pipeline.stages) {
        match learn_from_file(&inputs[0], LEARN_PULSES)? {
            Ok(f) => (Some(std::sync::Arc::new(f)), None),
            Err(why) => (None, Some(why)),
        }
    } else {
        (None, None)
    };
    prepare_out_dir(out_dir)?;
    let key = replay_run_key(inputs, shard, config);
    let workers = Workers::Replay(workers.unwrap_or(config.pipeline.workers));
    let run = assemble(input, config, learned, workers, |chain, input| {
        replay_sinks(config, chain, input, &inputs[0], &key, out_dir)
    })?;
    let response = response_report(&run.chain, not_learned.as_deref());
    Ok((run, response))
}

/// Runs the pipeline, drawing a progress bar unless `no_progress`.
fn run_with_progress(run: Assembled, control: &RunControl, no_progress: bool) -> RunReport {
    let bar = (!no_progress).then(progress_bar);
    let tick = |live: &LiveCounters| {
        if let Some(bar) = &bar {
            bar.set_length(live.progress_total.load(Ordering::Relaxed));
            bar.set_position(live.progress_done.load(Ordering::Relaxed));
            bar.set_message(format!(
                "{} pulses in, {} out",
                live.pulses_in.load(Ordering::Relaxed),
                live.pulses_out.load(Ordering::Relaxed)
            ));
        }
    };
    let report = run_pipeline(&run.spec, run.source, run.sinks, run.nav, control, tick);
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    report
}

fn progress_bar() -> ProgressBar {
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {bytes}/{total_bytes} {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

/// Writes `summary.json`, prints the summary and logs the warnings; the run's own failure
/// comes first (a full disk usually stops an output and then the summary too).
fn finish(
    report: &RunReport,
    warnings: &[crate::run::warnings::RunWarning],
    chain: &crate::stages::Chain,
    input: &str,
    out_dir: &Path,
    response: Option<&ResponseReport>,
) -> Result<(), Failure> {
    let summary_path = out_dir.join("summary.json");
    let summary_written = write_summary(
        &summary_path,
        &Summary {
            report,
            warnings,
            response,
        },
    );
    print_summary(
        report,
        warnings,
        chain,
        input,
        out_dir,
        &summary_path,
        response,
    );
    log_warnings(warnings);
    if let Some(f) = &report.fatal {
        return Err(Failure::job(format!(
            "replay of {input} failed: {f}{}",
            match &summary_written {
                Ok(()) => String::new(),
                Err(e) => format!(" (and the summary could not be written: {e})"),
            }
        )));
    }
    summary_written.map_err(Failure::job)?;
    if report.stopped_early {
        tracing::warn!("replay stopped by signal; outputs hold what was processed until then");
    }
    Ok(())
}
