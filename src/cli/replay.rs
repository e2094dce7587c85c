//! `fwlidar replay`: a recorded capture through the processing chain into an output folder, with
//! a progress bar, `summary.json`, and a one-screen summary at the end.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::config::{RunConfig, WaveformFormat};
use crate::pipeline::runner::{LiveCounters, PipelineSpec};
use crate::pipeline::{RunControl, RunReport, run as run_pipeline};
use crate::sink::atomic_file::write_atomic;
use crate::sink::hyper_points::HyperPointSink;
use crate::sink::las_wave::{LasWaveOptions, LasWaveSink};
use crate::sink::nav_decode::NavDecode;
use crate::sink::returns_csv::ReturnsCsvSink;
use crate::sink::voxel_tiles::{CrsSource, VoxelTilesSink};
use crate::sink::waveform_csv::WaveformCsvSink;
use crate::sink::waveform_npy::WaveformNpySink;
use crate::sink::{FanOut, PulseSink};
use crate::voxel::zarr::StoreInfo;

/// The sample replayed when no input is named.
pub const DEFAULT_SAMPLE: &str = "replay/two_layer.fwcap";

/// Arguments of `fwlidar replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// Capture file to replay.
    #[arg(default_value = DEFAULT_SAMPLE)]
    pub input: PathBuf,
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
    /// Override a key of the run configuration, `KEY=VALUE` (dotted key with list indices,
    /// TOML value), checked like the file, e.g. `--set output.las=true --set
    /// 'pipeline.stages[1].max_taps=128'`. Repeatable; a later one wins.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
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

/// Runs `fwlidar replay`.
pub fn run(args: ReplayArgs) -> Result<(), Failure> {
    let config: RunConfig = crate::config::load_run_config_with(args.config.as_deref(), &args.sets)
        .map_err(Failure::usage)?;
    let out_dir = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(&config.output.dir));
    let source = crate::source::open_file(&args.input).map_err(Failure::job)?;
    let (source, dem, decided_crs) = georeferenced(source, &config)?;
    prepare_out_dir(&out_dir)?;

    let p = &config.pipeline;
    // Keys left to the input (the calibrate stage's system constant and time origin) are
    // filled from what the opened input states, before the stages are built.
    let facts = source.facts();
    let mut stages = p.stages.clone();
    for stage in &mut stages {
        stage.resolve_from_input(&facts);
        if let crate::pipeline::registry::StageConfig::Calibrate(c) = stage {
            tracing::info!(
                system_constant = c.system_constant_value.unwrap_or(1.0),
                t0_is_emission = c.t0_is_emission.unwrap_or(false),
                "calibrate stage resolved from the input"
            );
        }
    }
    let spec = PipelineSpec::from_config(
        args.workers.unwrap_or(p.workers),
        p.queue_capacity,
        p.input_edge,
        stages,
    );
    let mut sinks: Vec<Box<dyn PulseSink>> = Vec::new();
    if config.output.waveforms {
        sinks.push(match config.output.waveform_format {
            WaveformFormat::Npy => {
                Box::new(WaveformNpySink::create(&out_dir).map_err(Failure::job)?)
            }
            WaveformFormat::Csv => {
                Box::new(WaveformCsvSink::create(&out_dir).map_err(Failure::job)?)
            }
        });
    }
    let decomposes = spec.stage_names.contains(&"decompose");
    if config.output.returns && decomposes {
        sinks.push(Box::new(
            ReturnsCsvSink::create_with_dem(&out_dir, dem.clone()).map_err(Failure::job)?,
        ));
    }
    if config.output.las && decomposes {
        if source.facts().crs.is_none() && decided_crs.is_none() {
            tracing::warn!(
                "returns.las will have no CRS record: the input states none before it is read \
                 (georeferencing into the UTM zone of the first fix decides it too late; set \
                 [georeference] output_epsg to name it)"
            );
        }
        sinks.push(Box::new(
            LasWaveSink::create(
                &out_dir,
                LasWaveOptions {
                    point_format: config.output.las_point_format,
                    rotate_s: config.output.las_rotate_s,
                    flush_s: config.output.las_flush_s,
                    crs_decided: decided_crs.clone(),
                    ..las_options(&source.facts())
                },
            )
            .map_err(Failure::job)?,
        ));
    }
    if config.output.hyper_points {
        let facts = source.facts();
        let wkt = las_options(&facts).crs_wkt;
        sinks.push(Box::new(
            HyperPointSink::create(
                &out_dir,
                config.output.hyper_threshold_v.unwrap_or(f32::INFINITY),
                wkt.as_deref(),
                config.output.las_flush_s,
            )
            .map_err(Failure::job)?,
        ));
    }
    if config.voxels.enabled {
        let facts = source.facts();
        let crs = match (facts.crs.clone(), decided_crs) {
            (Some(c), _) => CrsSource::Known(Some(c)),
            (None, Some(cell)) => CrsSource::Decided(cell),
            (None, None) => CrsSource::Known(None),
        };
        let info = StoreInfo {
            crs_wkt: None,
            epsg: None,
            intensity_units: intensity_units(&spec.stage_names).into(),
            run_key: run_key(&args.input, &config),
            configuration: toml::to_string(&config).unwrap_or_default(),
        };
        sinks.push(Box::new(
            VoxelTilesSink::create(
                &out_dir,
                config.voxels.clone(),
                crs,
                info,
                dem.clone(),
                facts.sensor.as_ref().map(|s| s.beam_divergence_mrad),
            )
            .map_err(Failure::job)?,
        ));
    }
    let control = RunControl::default();
    install_signal_handlers(&control)?;
    tracing::info!(
        input = %args.input.display(),
        out = %out_dir.display(),
        workers = spec.workers,
        stages = ?spec.stage_names,
        "replay started"
    );

    let bar = (!args.no_progress).then(|| {
        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {bytes}/{total_bytes} {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.enable_steady_tick(Duration::from_millis(200));
        bar
    });
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
        &spec,
        source,
        Box::new(FanOut(sinks)),
        Box::new(NavDecode::new(
            config.georeference.leap_seconds,
            config.navigation.earliest_days(),
        )),
        &control,
        tick,
    );
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }

    let summary_path = out_dir.join("summary.json");
    let json = serde_json::to_vec_pretty(&report)
        .map_err(|e| Failure::job(format!("cannot encode summary: {e}")))?;
    // The run's own failure comes first: a full disk usually stops an output and then the
    // summary too.
    let summary_written = write_atomic(&summary_path, &json);
    print_summary(&report, &args.input, &out_dir, &summary_path);
    if let Some(f) = &report.fatal {
        return Err(Failure::job(format!(
            "replay of {} failed: {f}{}",
            args.input.display(),
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
    Box<dyn crate::source::Source>,
    Option<std::sync::Arc<crate::geo::dem::Dem>>,
    Option<std::sync::Arc<std::sync::OnceLock<String>>>,
);

/// Opens the DEM and wraps `source` in the georeferencing per `[georeference]` (replay and the
/// daemon alike). The output CRS is the DEM's own unless the configuration names one.
pub fn georeferenced(
    source: Box<dyn crate::source::Source>,
    config: &RunConfig,
) -> Result<Georeferenced, Failure> {
    let dem = match &config.georeference.dem {
        Some(path) => Some(std::sync::Arc::new(
            crate::geo::dem::Dem::open(Path::new(path)).map_err(Failure::job)?,
        )),
        None => None,
    };
    if !config.georeference.enabled {
        return Ok((source, dem, None));
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
    Ok((Box::new(g), dem, Some(decided)))
}

/// The LAS output's CRS and time base from what the input states: its WKT when it gave one (an
/// `EPSG:<code>` alone cannot be turned into the WKT LAS 1.4 requires without a CRS database, so
/// the file then has no CRS record and the summary of the input says which EPSG it was), and
/// adjusted standard GPS time when the input's times are in it.
fn las_options(facts: &crate::source::SourceFacts) -> LasWaveOptions {
    LasWaveOptions {
        crs_wkt: facts.crs.clone().filter(|c| !c.starts_with("EPSG:")),
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

/// Identifies a run for resuming its voxel store: the input's name and size and a checksum of
/// the configuration (apart from the output folder).
fn run_key(input: &Path, config: &RunConfig) -> String {
    let size = std::fs::metadata(input).map(|m| m.len()).unwrap_or(0);
    let mut c = config.clone();
    c.output.dir.clear();
    let text = toml::to_string(&c).unwrap_or_default();
    format!(
        "{} ({size} bytes), configuration crc32c {:08x}",
        input
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default(),
        crc32c::crc32c(text.as_bytes())
    )
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

/// Prints the one-screen summary of a run to stdout.
pub fn print_summary(r: &RunReport, input: &Path, out: &Path, summary: &Path) {
    println!();
    println!("fwlidar replay  {}  ->  {}", input.display(), out.display());
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
                "    passed  {n:>10}  {}.{note} (passed on unprocessed)",
                st.name
            );
        }
    }
    if let Some(skipped) = r.source.get("skipped") {
        let bytes = skipped
            .get("bytes_skipped")
            .and_then(|v| v.as_u64())
            .unwrap_or(0);
        let tail = skipped
            .get("truncated_tail_bytes")
            .and_then(|v| v.as_u64())
            .unwrap_or(0);
        let bad = skipped
            .get("bad_checksums")
            .and_then(|v| v.as_u64())
            .unwrap_or(0);
        println!(
            "  capture damage: {bytes} bytes skipped ({bad} bad checksums), {tail} bytes of truncated tail"
        );
    }
    if let Some(ports) = r.nav.get("ports").and_then(|p| p.as_object()) {
        for (port, v) in ports {
            let kinds: Vec<String> = v["by_kind"]
                .as_object()
                .map(|m| m.iter().map(|(k, n)| format!("{n} {k}")).collect())
                .unwrap_or_default();
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
            let reasons = match v["rejected_by_reason"].as_object() {
                Some(m) if !m.is_empty() => format!(
                    " ({})",
                    m.iter()
                        .map(|(k, n)| format!("{n} {k}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
                _ => String::new(),
            };
            println!(
                "  navigation port {port}: {} bytes, {} samples ({}){span}, {} rejected{reasons}",
                v["bytes"],
                v["records"],
                kinds.join(", "),
                v["rejected"],
            );
        }
    }
    if let Some(g) = r.source.get("georeference") {
        let missed = match g["missed"].as_object() {
            Some(m) if !m.is_empty() => m
                .iter()
                .map(|(k, n)| format!("{n} {k}"))
                .collect::<Vec<_>>()
                .join(", "),
            _ => "none".into(),
        };
        println!(
            "  georeference: {} pulses placed in {}, {} carried their own geometry, missed: {missed}",
            g["georeferenced"],
            g["output_crs"].as_str().unwrap_or("(no fix, no CRS)"),
            g["with_own_geometry"],
        );
    }
    if let Some(las) = r.sinks.get("las") {
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
    if let Some(h) = r.sinks.get("hyper_points") {
        println!(
            "  hyper_points.las: {} points above {} V from {} pulses; {} pulses without geometry \
             skipped",
            h["points"], h["threshold_v"], h["pulses_written"], h["pulses_without_geometry"]
        );
    }
    if let Some(v) = r.sinks.get("voxels") {
        let d = &v["deposits"];
        let t = &v["tiles"];
        let outside = [
            "bins_outside_extent",
            "bins_outside_heights",
            "bins_outside_dem",
        ]
        .iter()
        .map(|k| d[*k].as_u64().unwrap_or(0))
        .sum::<u64>();
        println!(
            "  voxels.zarr: {} bins of {} pulses deposited ({} outside the grid); tiles {} opened, \
             {} closed ({} early), {} merged with the store, at most {} open ({:.1} MB each){}",
            d["bins_deposited"],
            d["pulses_deposited"],
            outside,
            t["opened"],
            t["closed"],
            t["closed_early"],
            t["merged"],
            t["peak_open"],
            t["tile_bytes"].as_f64().unwrap_or(0.0) / 1e6,
            match d["bins_resumed"].as_u64() {
                Some(n) if n > 0 => format!("; resumed: {n} bins already in the store"),
                _ => String::new(),
            }
        );
        let skipped = d["pulses_no_geometry"].as_u64().unwrap_or(0)
            + d["pulses_non_finite"].as_u64().unwrap_or(0);
        if skipped > 0 {
            println!(
                "    voxels skipped {skipped} pulses ({} without geometry, {} non-finite)",
                d["pulses_no_geometry"], d["pulses_non_finite"]
            );
        }
    }
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
    println!(
        "  {:.2} s wall, {:.0} pulses/s, {} workers; summary in {}",
        r.wall_time_s,
        r.pulses_per_s,
        r.workers,
        summary.display()
    );
}
