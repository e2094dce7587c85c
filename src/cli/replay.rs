//! `fwlidar replay`: a recorded capture through the processing chain into an output folder, with
//! a progress bar, `summary.json`, and a one-screen summary at the end.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::config::{RunConfig, WaveformFormat};
use crate::core::atomic_file::write_atomic;
use crate::nav::consumer::NavDecode;
use crate::pipeline::ports::{FanOut, PulseSink};
use crate::pipeline::runner::{LiveCounters, PipelineSpec};
use crate::pipeline::warnings::{log_warnings, run_warnings, warnings_block};
use crate::pipeline::{RunControl, RunReport, run as run_pipeline};
use crate::sink::hyper_points::HyperPointSink;
use crate::sink::las_wave::{LasWaveOptions, LasWaveSink};
use crate::sink::pulse_metrics_csv::PulseMetricsCsvSink;
use crate::sink::returns_csv::ReturnsCsvSink;
use crate::sink::voxel_tiles::{CrsSource, VoxelTilesSink, replay_run_key};
use crate::sink::waveform_csv::WaveformCsvSink;
use crate::sink::waveform_npy::WaveformNpySink;
use crate::source::shard::Shard;
use crate::voxel::zarr::StoreInfo;

/// The sample replayed when no input is named.
pub const DEFAULT_SAMPLE: &str = "replay/two_layer.fwcap";

/// Arguments of `fwlidar replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// Capture file to replay (or any file `replay` reads). Several are replayed one after
    /// another into the one output folder and voxel store, as one recording (each georeferenced
    /// by its own navigation; they must share the sensor and the output CRS).
    #[arg(default_value = DEFAULT_SAMPLE, num_args = 1..)]
    pub inputs: Vec<PathBuf>,
    /// Output folder (created if missing; files in it are replaced only by complete new ones).
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
    use crate::pipeline::registry::StageConfig;
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

/// Runs `fwlidar replay`: open the input, build the stages and the sinks, run with a progress
/// bar, then report (summary.json, the one-screen summary, the warnings).
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
    let Prepared {
        spec,
        source,
        sinks,
    } = prepare(&args.inputs, args.shard, &out_dir, &config, args.workers)?;
    let control = RunControl::default();
    install_signal_handlers(&control)?;
    let label = inputs_label(&args.inputs, args.shard);
    tracing::info!(
        input = %label,
        out = %out_dir.display(),
        workers = spec.workers,
        stages = ?spec.stage_names,
        "replay started"
    );
    let mut report = run_with_progress(&spec, source, sinks, &config, &control, &args);
    report.warnings = run_warnings(&report, &config);
    finish(&report, &label, &out_dir)
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
    let Prepared {
        spec,
        source,
        sinks,
    } = prepare(&[input.to_path_buf()], None, out_dir, config, workers)?;
    let control = RunControl::default();
    Ok(run_pipeline(
        &spec,
        source,
        sinks,
        Box::new(nav_consumer(config)),
        &control,
        |_| {},
    ))
}

/// What both [`run`] and [`replay_quiet`] set up: the input opened and georeferenced, the
/// output folder prepared, the stages and the sinks.
struct Prepared {
    spec: PipelineSpec,
    source: Box<dyn crate::pipeline::ports::Source>,
    sinks: Box<dyn PulseSink>,
}

fn prepare(
    inputs: &[PathBuf],
    shard: Option<Shard>,
    out_dir: &Path,
    config: &RunConfig,
    workers: Option<usize>,
) -> Result<Prepared, Failure> {
    let opened = open_inputs(inputs, shard, config)?;
    prepare_out_dir(out_dir)?;
    let spec = build_spec(config, workers, &opened.source.facts(), opened.dem.as_ref());
    let key = replay_run_key(inputs, shard, config);
    let sinks = build_sinks(config, &spec, &opened, &inputs[0], &key, out_dir)?;
    Ok(Prepared {
        spec,
        source: opened.source,
        sinks,
    })
}

/// The navigation consumer of a replay: decodes the navigation bytes for the summary.
fn nav_consumer(config: &RunConfig) -> NavDecode {
    NavDecode::new(
        config.georeference.leap_seconds,
        config.navigation.earliest_days(),
    )
}

/// The opened input: the source (georeferenced per `[georeference]`), the DEM, and where the
/// georeferencing puts the CRS it decides.
struct Input {
    source: Box<dyn crate::pipeline::ports::Source>,
    dem: Option<std::sync::Arc<crate::geo::dem::Dem>>,
    decided_crs: Option<std::sync::Arc<std::sync::OnceLock<String>>>,
}

/// Opens the input files (only the shard's pulses of them when `shard` is given), wraps each
/// in the georeferencing (its own trajectory), and chains them when there are several.
fn open_inputs(
    paths: &[PathBuf],
    shard: Option<Shard>,
    config: &RunConfig,
) -> Result<Input, Failure> {
    let dem = open_dem(config)?;
    let several = paths.len() > 1;
    if several
        && config.georeference.enabled
        && config.georeference.output_epsg.is_none()
        && dem.as_ref().and_then(|d| d.epsg).is_none()
    {
        return Err(Failure::usage(
            "several inputs are replayed into one CRS, and the configuration names none (each \
             line would get the UTM zone of its own first fix): set [georeference] output_epsg, \
             e.g. --set georeference.output_epsg=32736",
        ));
    }
    // The shard's pulse range over the inputs in sequence, and each input's share of it.
    let ranges: Option<Vec<(u64, u64)>> = match shard {
        None => None,
        Some(s) => {
            let counts = paths
                .iter()
                .map(|p| crate::source::shard::count_pulses(p))
                .collect::<Result<Vec<u64>, String>>()
                .map_err(Failure::job)?;
            let total: u64 = counts.iter().sum();
            let (lo, hi) = s.range(total);
            if lo == hi {
                return Err(Failure::usage(format!(
                    "--shard {s}: the input holds {total} pulses, so shard {s} holds none; \
                     give fewer shards than pulses"
                )));
            }
            let mut offset = 0;
            let mut r = Vec::new();
            for c in counts {
                r.push((
                    lo.clamp(offset, offset + c) - offset,
                    hi.clamp(offset, offset + c) - offset,
                ));
                offset += c;
            }
            tracing::info!(shard = %s, first_pulse = lo, end_pulse = hi, "replaying one shard");
            Some(r)
        }
    };
    let mut sources = Vec::new();
    let mut decided = None;
    for (k, path) in paths.iter().enumerate() {
        let mut source = crate::source::open_file(path).map_err(Failure::job)?;
        if let Some(r) = &ranges {
            let (lo, hi) = r[k];
            if lo == hi && several {
                continue; // none of this input's pulses is in the shard
            }
            source = Box::new(crate::source::shard::ShardSource::new(source, lo, hi));
        }
        let (source, cell) = georeference_with(source, config, dem.clone())?;
        decided = decided.or(cell);
        sources.push((path.display().to_string(), source));
    }
    let source: Box<dyn crate::pipeline::ports::Source> = if sources.len() == 1 {
        sources.pop().map(|(_, s)| s).expect("one source")
    } else {
        Box::new(crate::source::chain::ChainSource::new(sources).map_err(Failure::usage)?)
    };
    Ok(Input {
        source,
        dem,
        decided_crs: decided,
    })
}

/// The pipeline: the configured stages with the keys left to the input (the calibrate stage's
/// system constant and time origin) filled from what it states, and the run's DEM handed to
/// a metrics stage that takes its ground from it.
fn build_spec(
    config: &RunConfig,
    workers: Option<usize>,
    facts: &crate::core::facts::SourceFacts,
    dem: Option<&std::sync::Arc<crate::geo::dem::Dem>>,
) -> PipelineSpec {
    let p = &config.pipeline;
    let mut stages = p.stages.clone();
    for stage in &mut stages {
        stage.resolve_from_input(facts);
        stage.attach_dem(dem);
        if let crate::pipeline::registry::StageConfig::Calibrate(c) = stage {
            tracing::info!(
                system_constant = c.system_constant_value.unwrap_or(1.0),
                t0_is_emission = c.t0_is_emission.unwrap_or(false),
                "calibrate stage resolved from the input"
            );
        }
    }
    PipelineSpec::from_config(
        workers.unwrap_or(p.workers),
        p.queue_capacity,
        p.input_edge,
        stages,
    )
}

/// The outputs `[output]` and `[voxels]` ask for (returns and LAS only after a decompose
/// stage).
fn build_sinks(
    config: &RunConfig,
    spec: &PipelineSpec,
    input: &Input,
    input_path: &Path,
    run_key: &str,
    out_dir: &Path,
) -> Result<Box<dyn PulseSink>, Failure> {
    let out = &config.output;
    let facts = input.source.facts();
    let decomposes = spec.stage_names.contains(&"decompose");
    let mut sinks: Vec<Box<dyn PulseSink>> = Vec::new();
    if out.waveforms {
        sinks.push(match out.waveform_format {
            WaveformFormat::Npy => {
                Box::new(WaveformNpySink::create(out_dir).map_err(Failure::job)?)
            }
            WaveformFormat::Csv => {
                Box::new(WaveformCsvSink::create(out_dir).map_err(Failure::job)?)
            }
        });
    }
    if out.returns && decomposes {
        sinks.push(Box::new(
            ReturnsCsvSink::create_with_dem(out_dir, input.dem.clone()).map_err(Failure::job)?,
        ));
    }
    if out.las && decomposes {
        sinks.push(las_sink(config, &facts, input, out_dir)?);
    }
    if out.hyper_points {
        sinks.push(Box::new(
            HyperPointSink::create(
                out_dir,
                out.hyper_threshold_v.unwrap_or(f32::INFINITY),
                las_options(&facts).crs_wkt.as_deref(),
                out.las_flush_s,
            )
            .map_err(Failure::job)?,
        ));
    }
    if out.metrics {
        let metrics = config.pipeline.stages.iter().find_map(|s| match s {
            crate::pipeline::registry::StageConfig::Metrics(c) => Some(c),
            _ => None,
        });
        if let Some(m) = metrics {
            sinks.push(Box::new(
                PulseMetricsCsvSink::create(
                    out_dir,
                    is_hdf5(input_path),
                    m.profile_bins,
                    m.profile_bin_m,
                    input.dem.clone(),
                )
                .map_err(Failure::job)?,
            ));
        }
    }
    let has_metrics = config
        .pipeline
        .stages
        .iter()
        .any(|s| matches!(s, crate::pipeline::registry::StageConfig::Metrics(_)));
    if out.rasters && has_metrics {
        use crate::sink::metrics_rasters::{MetricsRastersSink, RasterCrs, RasterSettings};
        let crs = match (facts.crs.clone(), input.decided_crs.clone()) {
            (Some(c), _) => RasterCrs::Known(Some(c)),
            (None, Some(cell)) => RasterCrs::Decided(cell),
            (None, None) => RasterCrs::Known(None),
        };
        sinks.push(Box::new(MetricsRastersSink::new(
            out_dir,
            RasterSettings {
                chm_cell_m: out.chm_cell_m,
                profile_cell_m: out.profile_cell_m,
                tile_m: out.raster_tile_m,
                // Raster tiles close behind the flight by the voxel tiles' rule.
                close_after_s: config.voxels.close_after_s,
                max_open_tiles: config.voxels.max_open_tiles,
            },
            crs,
        )));
    }
    if config.voxels.enabled {
        sinks.push(voxel_sink(config, spec, input, &facts, run_key, out_dir)?);
    }
    Ok(Box::new(FanOut(sinks)))
}

/// Whether `path` is an HDF5 file (GEDI input: `pulse_metrics.csv` gains `shot_number`).
fn is_hdf5(path: &Path) -> bool {
    let mut head = [0u8; 8];
    std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok()
        && head == *b"\x89HDF\r\n\x1a\n"
}

/// `returns.las` (or its rotated files), with the CRS and time base the input states, or the
/// CRS the georeferencing decides during the run.
fn las_sink(
    config: &RunConfig,
    facts: &crate::core::facts::SourceFacts,
    input: &Input,
    out_dir: &Path,
) -> Result<Box<dyn PulseSink>, Failure> {
    if facts.crs.is_none() && input.decided_crs.is_none() {
        tracing::warn!(
            "returns.las will have no CRS record: the input states none before it is read \
             and no georeferencing decides it; set [georeference] output_epsg to name it"
        );
    }
    let out = &config.output;
    let sink = LasWaveSink::create(
        out_dir,
        LasWaveOptions {
            point_format: out.las_point_format,
            rotate_s: out.las_rotate_s,
            flush_s: out.las_flush_s,
            crs_decided: input.decided_crs.clone(),
            ..las_options(facts)
        },
    )
    .map_err(Failure::job)?;
    Ok(Box::new(sink))
}

/// `voxels.zarr`, in the CRS the input states or the georeferencing decides.
fn voxel_sink(
    config: &RunConfig,
    spec: &PipelineSpec,
    input: &Input,
    facts: &crate::core::facts::SourceFacts,
    run_key: &str,
    out_dir: &Path,
) -> Result<Box<dyn PulseSink>, Failure> {
    let crs = match (facts.crs.clone(), input.decided_crs.clone()) {
        (Some(c), _) => CrsSource::Known(Some(c)),
        (None, Some(cell)) => CrsSource::Decided(cell),
        (None, None) => CrsSource::Known(None),
    };
    let info = StoreInfo {
        crs_wkt: None,
        epsg: None,
        intensity_units: intensity_units(&spec.stage_names).into(),
        run_key: run_key.to_string(),
        configuration: toml::to_string(config).unwrap_or_default(),
    };
    let sink = VoxelTilesSink::create(
        out_dir,
        config.voxels.clone(),
        crs,
        info,
        input.dem.clone(),
        facts.sensor.as_ref().map(|s| s.beam_divergence_mrad),
    )
    .map_err(Failure::job)?
    // Closed tiles are compressed and committed off the sink thread (the store is the same).
    .with_tile_writer(TILE_WRITER_QUEUE);
    Ok(Box::new(sink))
}

/// Closed voxel tiles waiting for the tile writer threads at most (then the sink waits).
const TILE_WRITER_QUEUE: usize = 32;

/// Runs the pipeline, drawing a progress bar unless `--no-progress`.
fn run_with_progress(
    spec: &PipelineSpec,
    source: Box<dyn crate::pipeline::ports::Source>,
    sinks: Box<dyn PulseSink>,
    config: &RunConfig,
    control: &RunControl,
    args: &ReplayArgs,
) -> RunReport {
    let bar = (!args.no_progress).then(progress_bar);
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
    let report = run_pipeline(
        spec,
        source,
        sinks,
        Box::new(nav_consumer(config)),
        control,
        tick,
    );
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
fn finish(report: &RunReport, input: &str, out_dir: &Path) -> Result<(), Failure> {
    let summary_path = out_dir.join("summary.json");
    let json = serde_json::to_vec_pretty(report)
        .map_err(|e| Failure::job(format!("cannot encode summary: {e}")))?;
    let summary_written = write_atomic(&summary_path, &json);
    print_summary(report, input, out_dir, &summary_path);
    log_warnings(&report.warnings);
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

/// What [`georeferenced`] gives: the source (wrapped when `[georeference] enabled`), the DEM
/// when one is configured, and the cell where the georeferencing will put the output CRS it
/// decides (the UTM zone of the first fix) when it was wrapped.
pub type Georeferenced = (
    Box<dyn crate::pipeline::ports::Source>,
    Option<std::sync::Arc<crate::geo::dem::Dem>>,
    Option<std::sync::Arc<std::sync::OnceLock<String>>>,
);

/// Opens the DEM and wraps `source` in the georeferencing per `[georeference]` (replay and the
/// daemon alike). The output CRS is the DEM's own unless the configuration names one.
pub fn georeferenced(
    source: Box<dyn crate::pipeline::ports::Source>,
    config: &RunConfig,
) -> Result<Georeferenced, Failure> {
    let dem = open_dem(config)?;
    let (source, decided) = georeference_with(source, config, dem.clone())?;
    Ok((source, dem, decided))
}

/// The DEM `[georeference] dem` names, opened.
fn open_dem(config: &RunConfig) -> Result<Option<std::sync::Arc<crate::geo::dem::Dem>>, Failure> {
    match &config.georeference.dem {
        Some(path) => Ok(Some(std::sync::Arc::new(
            crate::geo::dem::Dem::open(Path::new(path)).map_err(Failure::job)?,
        ))),
        None => Ok(None),
    }
}

/// [`georeferenced`] with the DEM already open: the source and the decided-CRS cell.
#[allow(clippy::type_complexity)]
fn georeference_with(
    source: Box<dyn crate::pipeline::ports::Source>,
    config: &RunConfig,
    dem: Option<std::sync::Arc<crate::geo::dem::Dem>>,
) -> Result<
    (
        Box<dyn crate::pipeline::ports::Source>,
        Option<std::sync::Arc<std::sync::OnceLock<String>>>,
    ),
    Failure,
> {
    if !config.georeference.enabled {
        return Ok((source, None));
    }
    let mut geo_cfg = config.georeference.clone();
    // Register to the ground in the DEM's own CRS unless an output CRS is named (a named one
    // that differs from the DEM's was refused when the configuration was loaded).
    if geo_cfg.output_epsg.is_none()
        && let Some(code) = dem.as_ref().and_then(|d| d.epsg)
    {
        geo_cfg.output_epsg = Some(code);
    }
    let mut g = crate::geo::georeferencing_source::GeoreferencingSource::new(source, geo_cfg)
        .map_err(Failure::usage)?
        .with_earliest_date(config.navigation.earliest_days());
    if let (Some(d), Some(path)) = (&dem, &config.georeference.dem) {
        g = g.with_dem(d.clone(), path.clone());
    }
    let decided = g.decided_crs();
    Ok((Box::new(g), Some(decided)))
}

/// The LAS output's CRS and time base from what the input states: its WKT when it gave one, or
/// the WKT of a WGS84 UTM zone named `EPSG:326zz`/`327zz` (other `EPSG:<code>`s cannot be
/// turned into the WKT LAS 1.4 requires without a CRS database, so the file then has no CRS
/// record and the summary of the input says which EPSG it was), and
/// adjusted standard GPS time when the input's times are in it.
fn las_options(facts: &crate::core::facts::SourceFacts) -> LasWaveOptions {
    LasWaveOptions {
        crs_wkt: facts
            .crs
            .as_deref()
            .and_then(|c| match c.strip_prefix("EPSG:") {
                // WGS84 UTM zones (GEDI input) are written from their parameters.
                Some(code) => code.parse().ok().and_then(crate::geo::crs::utm_wkt),
                None => Some(c.to_string()),
            }),
        adjusted_standard_gps_time: facts.time_base.as_deref() == Some("gps_adjusted_standard"),
        ..LasWaveOptions::default()
    }
}

/// Units of the deposited intensity: calibrated backscatter after a `calibrate` stage, volts
/// otherwise.
fn intensity_units(stages: &[&str]) -> &'static str {
    if stages.contains(&"calibrate") {
        "calibrated backscatter (docs/calibration.md)"
    } else {
        "V"
    }
}

fn prepare_out_dir(dir: &Path) -> Result<(), Failure> {
    if dir.exists() && !dir.is_dir() {
        return Err(Failure::job(format!(
            "output folder {} exists and is not a folder",
            dir.display()
        )));
    }
    std::fs::create_dir_all(dir).map_err(|e| {
        Failure::job(format!(
            "cannot create output folder {}: {e}",
            dir.display()
        ))
    })
}

fn us(ns: u64) -> f64 {
    ns as f64 / 1000.0
}

/// Prints the one-screen summary of a run to stdout, its warnings last.
pub fn print_summary(r: &RunReport, input: &str, out: &Path, summary: &Path) {
    println!();
    println!("fwlidar replay  {input}  ->  {}", out.display());
    print_pulses(r);
    print_capture_damage(&r.source);
    print_navigation_ports(&r.nav);
    print_georeference(&r.source);
    print_las(&r.sinks);
    print_hyper_points(&r.sinks);
    print_voxels(r);
    print_stage_times(r);
    println!(
        "  {:.2} s wall, {:.0} pulses/s, {} workers; summary in {}",
        r.wall_time_s,
        r.pulses_per_s,
        r.workers,
        summary.display()
    );
    print!("{}", warnings_block(&r.warnings));
}

/// Pulses in, out, dropped (by reason) and passed on with a note.
fn print_pulses(r: &RunReport) {
    println!(
        "  pulses: {} in, {} out, {} dropped, {} errors{}",
        r.pulses_in,
        r.pulses_out,
        r.dropped_total,
        r.errors,
        if r.stopped_early {
            "  (stopped early by signal)"
        } else {
            ""
        }
    );
    for (reason, n) in &r.dropped {
        println!("    dropped {n:>10}  {reason}");
    }
    for st in &r.stages {
        for (note, n) in &st.notes {
            println!(
                "    passed  {n:>10}  {}.{note} ({})",
                st.name,
                note_meaning(&st.name, note)
            );
        }
    }
}

/// What a stage's note means for the pulses it counts.
fn note_meaning(stage: &str, note: &str) -> &'static str {
    match (stage, note) {
        ("deconvolve", "kernel_over_max_taps") => "deconvolved with the kernel cut to max_taps",
        ("deconvolve", _) => "passed on un-deconvolved",
        ("calibrate", "range_unknown") => "calibrated without the range factor",
        ("calibrate", "return_before_emission") => {
            "a return at or before the emission: no backscatter"
        }
        ("calibrate", _) => "calibrated without the energy factor",
        _ => "passed on partly unprocessed",
    }
}

fn u64_at(v: &serde_json::Value, key: &str) -> u64 {
    v.get(key).and_then(|x| x.as_u64()).unwrap_or(0)
}

/// `"3 a, 1 b"` of a JSON object of counts (`None` when empty or absent).
fn counts_list(v: &serde_json::Value) -> Option<String> {
    let m = v.as_object().filter(|m| !m.is_empty())?;
    Some(
        m.iter()
            .map(|(k, n)| format!("{n} {k}"))
            .collect::<Vec<_>>()
            .join(", "),
    )
}

/// What the capture reader skipped.
fn print_capture_damage(source: &serde_json::Value) {
    if let Some(skipped) = source.get("skipped") {
        println!(
            "  capture damage: {} bytes skipped ({} bad checksums), {} bytes of truncated tail",
            u64_at(skipped, "bytes_skipped"),
            u64_at(skipped, "bad_checksums"),
            u64_at(skipped, "truncated_tail_bytes")
        );
    }
}

/// One line per navigation port: bytes, samples by kind, GPS time span, rejections.
fn print_navigation_ports(nav: &serde_json::Value) {
    let Some(ports) = nav.get("ports").and_then(|p| p.as_object()) else {
        return;
    };
    for (port, v) in ports {
        let kinds = counts_list(&v["by_kind"]).unwrap_or_default();
        let span = match (
            v["first_gps_time"].get("sow"),
            v["last_gps_time"].get("sow"),
        ) {
            (Some(a), Some(b)) => format!(
                ", GPS week {} {:.1}..{:.1} s",
                v["first_gps_time"]["week"],
                a.as_f64().unwrap_or(f64::NAN),
                b.as_f64().unwrap_or(f64::NAN)
            ),
            _ => String::new(),
        };
        let reasons = counts_list(&v["rejected_by_reason"])
            .map(|l| format!(" ({l})"))
            .unwrap_or_default();
        println!(
            "  navigation port {port}: {} bytes, {} samples ({kinds}){span}, {} rejected{reasons}",
            v["bytes"], v["records"], v["rejected"],
        );
    }
}

/// Pulses placed by the georeferencing, and those it missed by reason.
fn print_georeference(source: &serde_json::Value) {
    if let Some(g) = source.get("georeference") {
        println!(
            "  georeference: {} pulses placed in {}, {} carried their own geometry, missed: {}",
            g["georeferenced"],
            g["output_crs"].as_str().unwrap_or("(no fix, no CRS)"),
            g["with_own_geometry"],
            counts_list(&g["missed"]).unwrap_or_else(|| "none".into()),
        );
    }
}

/// `returns.las`: points, pulses, skips and the waveform packets.
fn print_las(sinks: &serde_json::Value) {
    let Some(las) = sinks.get("las") else {
        return;
    };
    let files = las["files"].as_array().map_or(0, |f| f.len());
    let name = if files == 1 {
        las["files"][0]
            .as_str()
            .unwrap_or("returns.las")
            .to_string()
    } else {
        format!("returns_NNNN.las ({files} files)")
    };
    let wdp = if las["point_format"] == 9 {
        format!(
            "; .wdp: {} packets, {} bytes",
            las["packets"], las["wdp_bytes"]
        )
    } else {
        String::new()
    };
    println!(
        "  {name}: {} points (format {}) from {} pulses; {} pulses without geometry \
         skipped, {} returns unrepresentable{wdp}",
        las["points"],
        las["point_format"],
        las["pulses_written"],
        las["pulses_without_geometry"],
        las["returns_unrepresentable"],
    );
}

/// `hyper_points.las`: points above the threshold.
fn print_hyper_points(sinks: &serde_json::Value) {
    if let Some(h) = sinks.get("hyper_points") {
        println!(
            "  hyper_points.las: {} points above {} V from {} pulses; {} pulses without geometry \
             skipped",
            h["points"], h["threshold_v"], h["pulses_written"], h["pulses_without_geometry"]
        );
    }
}

/// `voxels.zarr`: bins and tiles, or why nothing was deposited.
fn print_voxels(r: &RunReport) {
    let Some(v) = r.sinks.get("voxels") else {
        return;
    };
    let d = &v["deposits"];
    let t = &v["tiles"];
    let outside = [
        "bins_outside_extent",
        "bins_outside_heights",
        "bins_outside_dem",
    ]
    .iter()
    .map(|k| u64_at(d, k))
    .sum::<u64>();
    if u64_at(d, "bins_deposited") + u64_at(d, "bins_resumed") == 0 {
        println!(
            "  voxels.zarr: nothing deposited ({})",
            nothing_deposited_reason(r.pulses_out, d, outside)
        );
    } else {
        println!(
            "  voxels.zarr: {} bins of {} pulses deposited ({} outside the grid); tiles {} opened, \
             {} closed ({} early), {} merged with the store, at most {} open ({} height chunks \
             of {:.1} MB in memory at most); {:.1} MB compressed into {:.1} MB ({} chunk files, \
             {} inner chunks){}",
            d["bins_deposited"],
            d["pulses_deposited"],
            outside,
            u64_at(t, "opened"),
            u64_at(t, "closed"),
            u64_at(t, "closed_early"),
            u64_at(t, "merged"),
            u64_at(t, "peak_open"),
            u64_at(t, "peak_chunks"),
            t["chunk_bytes"].as_f64().unwrap_or(0.0) / 1e6,
            t["bytes_written"].as_f64().unwrap_or(0.0) / 1e6,
            t["bytes_stored"].as_f64().unwrap_or(0.0) / 1e6,
            u64_at(t, "chunks_written"),
            u64_at(t, "inner_chunks_written"),
            match u64_at(d, "bins_resumed") {
                n if n > 0 => format!("; resumed: {n} bins already in the store"),
                _ => String::new(),
            }
        );
    }
    let skipped = u64_at(d, "pulses_no_geometry") + u64_at(d, "pulses_non_finite");
    if skipped > 0 {
        println!(
            "    voxels skipped {skipped} pulses ({} without geometry, {} non-finite)",
            d["pulses_no_geometry"], d["pulses_non_finite"]
        );
    }
}

/// Why the voxel sink deposited nothing, in words.
fn nothing_deposited_reason(pulses_out: u64, d: &serde_json::Value, outside: u64) -> String {
    let no_geometry = u64_at(d, "pulses_no_geometry") + u64_at(d, "pulses_non_finite");
    if pulses_out == 0 {
        "no pulse reached it".into()
    } else if no_geometry >= pulses_out {
        format!("none of the {pulses_out} pulses had geometry: not georeferenced")
    } else if outside > 0 {
        format!("all {outside} return bins fell outside the grid")
    } else {
        format!("the {pulses_out} pulses had no return bins to deposit")
    }
}

/// Service time per stage, and the end-to-end latency.
fn print_stage_times(r: &RunReport) {
    println!(
        "  {:<14} {:>10} {:>10} {:>10} {:>10} {:>10}   (service time, µs)",
        "stage", "received", "p50", "p99", "p99.9", "max"
    );
    for s in &r.stages {
        println!(
            "  {:<14} {:>10} {:>10.2} {:>10.2} {:>10.2} {:>10.2}",
            s.name,
            s.received,
            us(s.service.p50_ns),
            us(s.service.p99_ns),
            us(s.service.p999_ns),
            us(s.service.max_ns)
        );
    }
    let e = &r.end_to_end;
    println!(
        "  end-to-end latency µs: p50 {:.1}  p99 {:.1}  p99.9 {:.1}  max {:.1}",
        us(e.p50_ns),
        us(e.p99_ns),
        us(e.p999_ns),
        us(e.max_ns)
    );
}
