//! `fwlidar run`: the on-board daemon (`src/daemon/`). Records every digitizer frame and every
//! navigation byte into a new capture segment, processes what it can keep up with, writes voxel
//! tiles (and LAS returns) as the aircraft flies, and serves live QC. Stops cleanly on
//! SIGINT/SIGTERM; a restart continues the same survey (next segment, same voxel store).
//!
//! Parse the command line, start the recording and the inputs, put the run together
//! (`run::assemble`, as replay does), run it with the QC sampler ticking, print the summary.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cli::Failure;
use crate::cli::replay::install_signal_handlers;
use crate::config::RunConfig;
use crate::core::atomic_file::write_atomic;
use crate::core::facts::SourceFacts;
use crate::core::sensor::{SensorFile, SensorProfile};
use crate::core::toml_load::load_file;
use crate::daemon::inputs::start_inputs;
use crate::daemon::now_ns;
use crate::daemon::recorder::{LiveSource, RecorderState};
use crate::daemon::sampler::{Sampler, SamplerSetup};
use crate::format::capture::{FlushPolicy, FsyncPolicy};
use crate::format::capture_writer::CaptureWriter;
use crate::format::header::CaptureHeader;
use crate::pipeline::edge::FullPolicy;
use crate::pipeline::run as run_pipeline;
use crate::qc::QcHub;
use crate::run::assemble::{Workers, assemble};
use crate::run::input::Input;
use crate::run::outputs::daemon_sinks;
use crate::run::summary::{Summary, print_summary};
use crate::run::{LivePublish, RunControl};
use crate::source::georeferencing::OnMissing;

/// Arguments of `fwlidar run`.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// Run configuration with a `[daemon]` table (e.g. `config/onboard.toml`).
    #[arg(long)]
    pub config: PathBuf,
    /// Output folder (overrides `[output] dir`): capture segments, voxel store, summaries.
    #[arg(long, short)]
    pub out: Option<PathBuf>,
    /// Frame input (overrides `[daemon] frames`): udp:HOST:PORT, tcp-listen:HOST:PORT or
    /// tcp-connect:HOST:PORT.
    #[arg(long)]
    pub frames: Option<String>,
    /// QC server address (overrides `[daemon] qc`), or `off`.
    #[arg(long)]
    pub qc: Option<String>,
    /// Navigation serial device for port 0 (overrides the first `[[navigation.serial]]`
    /// device).
    #[arg(long)]
    pub nav_device: Option<PathBuf>,
    /// Worker threads (overrides `[pipeline] workers`; 0 = automatic).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Override a key of the run configuration, `KEY=VALUE` (dotted key with list indices,
    /// TOML value), checked like the file, e.g. `--set voxels.enabled=false`. Repeatable; a
    /// later one wins; the options above win over it.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
}

/// The next free segment `<survey>_NNNN.fwcap` in `dir`.
pub fn next_segment(dir: &Path, survey: &str) -> Result<(u32, PathBuf), Failure> {
    let mut highest: Option<u32> = None;
    let entries = std::fs::read_dir(dir)
        .map_err(|e| Failure::job(format!("cannot list capture folder {}: {e}", dir.display())))?;
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        if let Some(n) = name
            .strip_prefix(&format!("{survey}_"))
            .and_then(|r| r.strip_suffix(".fwcap"))
            .and_then(|n| n.parse::<u32>().ok())
        {
            highest = Some(highest.map_or(n, |h| h.max(n)));
        }
    }
    let n = highest.map_or(0, |h| h + 1);
    Ok((n, dir.join(format!("{survey}_{n:04}.fwcap"))))
}

fn create_dir(dir: &Path, what: &str) -> Result<(), Failure> {
    std::fs::create_dir_all(dir)
        .map_err(|e| Failure::job(format!("cannot create {what} {}: {e}", dir.display())))
}

/// A segment's `<survey>_NNNN.summary.json`: the run's summary and the daemon's part.
#[derive(serde::Serialize)]
struct DaemonSummary<'a> {
    #[serde(flatten)]
    run: Summary<'a>,
    daemon: SegmentSummary,
}

/// The daemon's part of a segment's summary: the survey, the segment and what the recording
/// received, kept and lost.
#[derive(serde::Serialize)]
struct SegmentSummary {
    survey: String,
    segment: String,
    seq_base: u64,
    frames_received: u64,
    frames_recorded: u64,
    frames_lost: u64,
    frames_bad: u64,
    drops: std::collections::BTreeMap<String, u64>,
    dropped_total: u64,
}

/// Runs the daemon until SIGINT/SIGTERM.
pub fn run(args: RunArgs) -> Result<(), Failure> {
    let config = load_config(&args)?;
    let d = config.daemon.clone();
    let sensor = load_sensor(&args.config, &config)?;
    let out_dir = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(&config.output.dir));
    create_dir(&out_dir, "output folder")?;
    let capture_dir = out_dir.join(&d.capture_dir);
    create_dir(&capture_dir, "capture folder")?;
    // The QC server first: an address in use is reported before anything is recorded.
    let hub = Arc::new(QcHub::default());
    let server = match d.qc_address() {
        Some(addr) => Some(start_qc(addr, hub.clone())?),
        None => None,
    };
    let (segment_no, segment) = next_segment(&capture_dir, &d.survey)?;
    let segment_stem = format!("{}_{segment_no:04}", d.survey);
    let writer = start_recording(&segment, &sensor, &config)?;
    let inputs = start_inputs(&d, &config.navigation.serial).map_err(Failure::job)?;

    let control = RunControl {
        // Pulse numbers continue across restarts of a survey: the host clock in ns outruns any
        // pulse rate, so a new run's numbers are above every earlier one's.
        seq_base: now_ns(),
        publish: Some(Arc::new(LivePublish::default())),
        ..RunControl::default()
    };
    install_signal_handlers(&control)?;
    let recorder = Arc::new(RecorderState::default());
    let facts = SourceFacts {
        sensor: Some(sensor),
        time_base: Some("gps_seconds_of_week".into()),
        crs: None,
        t0_is_emission: Some(true),
    };
    let source = Box::new(LiveSource::new(
        inputs.live,
        writer,
        segment.clone(),
        recorder.clone(),
        control.stop.clone(),
        facts,
    ));
    if config.pipeline.input_edge != FullPolicy::DropNewest {
        tracing::warn!(
            "[pipeline] input_edge is \"block\": when processing falls behind, the recorder \
             waits too (TCP slows the digitizer, UDP frames are lost); \"drop_newest\" keeps \
             the recording whole"
        );
    }
    let input = Input::georeferenced(source, &config)?;
    let workers = Workers::Live(args.workers.unwrap_or(config.pipeline.workers));
    let run = assemble(input, &config, None, workers, |chain, input| {
        daemon_sinks(&config, chain, input, &out_dir, &segment_stem)
    })?;

    let mut sampler = Sampler::new(
        hub.clone(),
        control.clone(),
        SamplerSetup {
            cfg: d.clone(),
            inputs: inputs.views,
            serial_ports: config.navigation.serial.iter().map(|s| s.port).collect(),
            recorder,
            recorder_queue: inputs.recorder_queue,
            capture_dir: capture_dir.clone(),
            segment: segment
                .file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_default(),
            georeference: config.georeference.enabled,
            drop_missed: config.georeference.on_missing == OnMissing::Drop,
            stages: run.chain.stages().to_vec(),
        },
    );
    tracing::info!(
        survey = %d.survey,
        segment = %segment.display(),
        out = %out_dir.display(),
        workers = run.spec.workers,
        stages = ?run.spec.stage_names,
        "on-board daemon running; SIGTERM or Ctrl-C stops it"
    );
    // Readiness line for scripts and tests (stdout).
    println!(
        "fwlidar run: recording {}{}",
        segment.display(),
        server.as_ref().map_or(String::new(), |s| format!(
            ", QC at http://{}/",
            s.local_addr()
        ))
    );

    let mut last_sample = Instant::now() - Duration::from_secs(1);
    let chain = run.chain.clone();
    let report = run_pipeline(&run.spec, run.source, run.sinks, run.nav, &control, |_| {
        if last_sample.elapsed() >= Duration::from_secs(1) {
            last_sample = Instant::now();
            sampler.tick();
        }
    });
    let last = sampler.tick();
    drop(server);

    let summary_path = out_dir.join(format!("{segment_stem}.summary.json"));
    let written =
        write_segment_summary(&summary_path, &report, &d.survey, &segment, &control, &last);
    print_summary(
        &report,
        &[],
        &chain,
        &segment.display().to_string(),
        &out_dir,
        &summary_path,
        None,
    );
    println!(
        "  recording: {} frames received, {} recorded, {} lost on the network; {} dropped from \
         processing",
        last.pulses.frames_received,
        last.pulses.frames_recorded,
        last.pulses.frames_lost,
        last.pulses.dropped_total
    );
    if let Some(f) = &report.fatal {
        return Err(Failure::job(format!("the daemon failed: {f}")));
    }
    written.map_err(Failure::job)?;
    Ok(())
}

/// Writes a segment's `<survey>_NNNN.summary.json`: the run's summary and the daemon's part
/// (what the recording received, kept and lost), every key in sorted order as the segment
/// summaries have them.
fn write_segment_summary(
    path: &Path,
    report: &crate::run::RunReport,
    survey: &str,
    segment: &Path,
    control: &RunControl,
    last: &crate::qc::QcSnapshot,
) -> Result<(), String> {
    let summary = DaemonSummary {
        run: Summary {
            response: None,
            report,
            warnings: &[],
        },
        daemon: SegmentSummary {
            survey: survey.to_string(),
            segment: segment.display().to_string(),
            seq_base: control.seq_base,
            frames_received: last.pulses.frames_received,
            frames_recorded: last.pulses.frames_recorded,
            frames_lost: last.pulses.frames_lost,
            frames_bad: last.pulses.frames_bad,
            drops: last.drops.clone(),
            dropped_total: last.pulses.dropped_total,
        },
    };
    let summary = serde_json::to_value(&summary).unwrap_or_default();
    let json =
        serde_json::to_vec_pretty(&summary).map_err(|e| format!("cannot encode summary: {e}"))?;
    write_atomic(path, &json).map_err(|e| e.to_string())
}

/// The run configuration with the command line's overrides (`--frames`, `--qc`,
/// `--nav-device` win over `--set` and the file).
fn load_config(args: &RunArgs) -> Result<RunConfig, Failure> {
    let mut config: RunConfig = crate::config::load_run_config_with(Some(&args.config), &args.sets)
        .map_err(Failure::usage)?;
    if let Some(f) = &args.frames {
        crate::daemon::FrameInput::parse(f)
            .map_err(|e| Failure::usage(format!("--frames: {e}")))?;
        config.daemon.frames = Some(f.clone());
    }
    if let Some(q) = &args.qc {
        if q != "off" && q.parse::<std::net::SocketAddr>().is_err() {
            return Err(Failure::usage(format!(
                "--qc: must be HOST:PORT or off, got {q:?}"
            )));
        }
        config.daemon.qc = q.clone();
    }
    if let Some(dev) = &args.nav_device {
        match config.navigation.serial.first_mut() {
            Some(s) => s.device = dev.clone(),
            None => {
                return Err(Failure::usage(
                    "--nav-device: the configuration has no [[navigation.serial]] port",
                ));
            }
        }
    }
    Ok(config)
}

/// The sensor profile the configuration names (live frames do not describe their sensor).
fn load_sensor(config_path: &Path, config: &RunConfig) -> Result<SensorProfile, Failure> {
    let profile = config.sensor_profile.as_deref().ok_or_else(|| {
        Failure::usage(format!(
            "{}: sensor_profile: the daemon needs the sensor profile (live frames do not describe \
             their sensor)",
            config_path.display()
        ))
    })?;
    let profile_path = config_path.parent().unwrap_or(Path::new(".")).join(profile);
    Ok(load_file::<SensorFile>(&profile_path)
        .map_err(Failure::usage)?
        .sensor)
}

/// Opens the new capture segment for writing, its header stating the sensor.
fn start_recording(
    segment: &Path,
    sensor: &SensorProfile,
    config: &RunConfig,
) -> Result<CaptureWriter<std::fs::File>, Failure> {
    let d = &config.daemon;
    let mut header = CaptureHeader::simulated(sensor, None, "flight");
    header.capture.created_unix_s = now_ns() / 1_000_000_000;
    let policy = FlushPolicy {
        every_records: 0,
        every_ms: d.flush_ms,
        fsync: if d.fsync {
            FsyncPolicy::OnFlush
        } else {
            FsyncPolicy::Never
        },
    };
    let writer = CaptureWriter::create(segment, &header.to_text(), policy)
        .map_err(|e| Failure::job(format!("cannot start the recording: {e}")))?;
    tracing::info!(segment = %segment.display(), "recording into a new capture segment");
    Ok(writer)
}

/// Starts the QC server; an address that cannot be bound is a configuration error.
fn start_qc(
    addr: std::net::SocketAddr,
    hub: Arc<QcHub>,
) -> Result<crate::qc::server::QcServer, Failure> {
    let server = crate::qc::server::spawn(addr, hub).map_err(|e| {
        Failure::usage(format!(
            "[daemon] qc = \"{addr}\": {e} (name another address, or \"off\")"
        ))
    })?;
    tracing::info!(addr = %server.local_addr(), "QC server listening (read-only)");
    Ok(server)
}
