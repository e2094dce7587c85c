//! `fwlidar run`: the on-board daemon (`src/daemon/`). Records every digitizer frame and every
//! navigation byte into a new capture segment, processes what it can keep up with, writes voxel
//! tiles (and LAS returns) as the aircraft flies, and serves live QC. Stops cleanly on
//! SIGINT/SIGTERM; a restart continues the same survey (next segment, same voxel store).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cli::Failure;
use crate::cli::replay::{install_signal_handlers, print_summary};
use crate::config::RunConfig;
use crate::core::atomic_file::write_atomic;
use crate::core::facts::SourceFacts;
use crate::core::sensor::SensorFile;
use crate::core::toml_load::load_file;
use crate::daemon::frames::{FrameReceiver, channels};
use crate::daemon::recorder::{LiveInputs, LiveSource, RecorderState};
use crate::daemon::sampler::{InputView, Sampler, SamplerSetup};
use crate::daemon::{InputState, now_ns};
use crate::format::capture::{FlushPolicy, FsyncPolicy};
use crate::format::capture_writer::CaptureWriter;
use crate::format::header::CaptureHeader;
use crate::nav::consumer::NavDecode;
use crate::pipeline::ports::Source;
use crate::pipeline::ports::{FanOut, PulseSink};
use crate::pipeline::runner::PipelineSpec;
use crate::pipeline::{LivePublish, RunControl, run as run_pipeline};
use crate::qc::QcHub;
use crate::sink::las_wave::{LasWaveOptions, LasWaveSink};
use crate::sink::voxel_tiles::{CrsSource, VoxelTilesSink};
use crate::source::serial::SerialReader;
use crate::voxel::zarr::StoreInfo;

/// Closed voxel tiles waiting for the tile writer thread at most (then the sink waits).
const TILE_WRITER_QUEUE: usize = 32;

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

/// Runs the daemon until SIGINT/SIGTERM.
pub fn run(args: RunArgs) -> Result<(), Failure> {
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
    let d = config.daemon.clone();

    // The sensor: live frames do not describe it.
    let profile = config.sensor_profile.as_deref().ok_or_else(|| {
        Failure::usage(format!(
            "{}: sensor_profile: the daemon needs the sensor profile (live frames do not describe \
             their sensor)",
            args.config.display()
        ))
    })?;
    let profile_path = args.config.parent().unwrap_or(Path::new(".")).join(profile);
    let sensor = load_file::<SensorFile>(&profile_path)
        .map_err(Failure::usage)?
        .sensor;

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

    let mut header = CaptureHeader::simulated(&sensor, None, "flight");
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
    let writer = CaptureWriter::create(&segment, &header.to_text(), policy)
        .map_err(|e| Failure::job(format!("cannot start the recording: {e}")))?;
    tracing::info!(segment = %segment.display(), "recording into a new capture segment");

    // Inputs: frames from the network, navigation from serial ports.
    let mut views = Vec::new();
    let frames = match &d.frames {
        Some(spec) => {
            let input = crate::daemon::FrameInput::parse(spec).map_err(Failure::usage)?;
            let ((tx, rx), (free_tx, free_rx)) = channels(d.recorder_queue);
            let state = Arc::new(InputState::default());
            views.push(InputView {
                name: "frames".into(),
                detail: input.to_string(),
                state: state.clone(),
            });
            let receiver =
                FrameReceiver::spawn(input, Duration::from_millis(d.retry_ms), tx, free_rx, state)
                    .map_err(|e| Failure::job(format!("cannot start the frame receiver: {e}")))?;
            Some((rx, free_tx, receiver))
        }
        None => {
            tracing::warn!("no [daemon] frames input: recording navigation only");
            None
        }
    };
    let recorder_queue = frames
        .as_ref()
        .map(|(rx, _, _)| (rx.clone(), d.recorder_queue as u64));
    let (serial_tx, serial_rx) = crossbeam_channel::bounded(4096);
    let mut serial_readers = Vec::new();
    let mut serial_states = BTreeMap::new();
    for s in &config.navigation.serial {
        let state = Arc::new(InputState::default());
        state.error(format!(
            "navigation port {}: waiting for {}",
            s.port,
            s.device.display()
        ));
        views.push(InputView {
            name: format!("serial:{}", s.port),
            detail: format!("{} @ {} bit/s", s.device.display(), s.baud),
            state: state.clone(),
        });
        serial_states.insert(s.port, state);
        serial_readers.push(
            SerialReader::spawn(s.clone(), serial_tx.clone())
                .map_err(|e| Failure::job(format!("cannot start the serial reader: {e}")))?,
        );
    }
    drop(serial_tx);

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
        sensor: Some(sensor.clone()),
        time_base: Some("gps_seconds_of_week".into()),
        crs: None,
        t0_is_emission: Some(true),
    };
    let source: Box<dyn Source> = Box::new(LiveSource::new(
        LiveInputs {
            frames,
            serial: serial_rx,
            serial_readers,
            serial_states,
        },
        writer,
        segment.clone(),
        recorder.clone(),
        control.stop.clone(),
        facts,
    ));

    let (source, dem, decided_crs) = crate::cli::replay::georeferenced(source, &config)?;

    let p = &config.pipeline;
    if p.input_edge != crate::pipeline::edge::FullPolicy::DropNewest {
        tracing::warn!(
            "[pipeline] input_edge is \"block\": when processing falls behind, the recorder \
             waits too (TCP slows the digitizer, UDP frames are lost); \"drop_newest\" keeps \
             the recording whole"
        );
    }
    let facts = source.facts();
    let mut stages = p.stages.clone();
    for stage in &mut stages {
        stage.resolve_from_input(&facts);
        stage.attach_dem(dem.as_ref());
    }
    // Live, automatic workers leave a core to the receivers and the recorder: with one worker
    // per core a chain that falls behind takes every core and the kernel drops UDP datagrams
    // before they are recorded (measured: 17 % of frames lost at 12.5 kHz on two cores).
    let workers = match args.workers.unwrap_or(p.workers) {
        0 => crate::pipeline::runner::resolve_live_workers(),
        n => n,
    };
    let spec = PipelineSpec::from_config(workers, p.queue_capacity, p.input_edge, stages.clone());

    // Outputs: the survey's voxel store (continued across restarts) and the segment's LAS.
    let mut sinks: Vec<Box<dyn PulseSink>> = Vec::new();
    if config.voxels.enabled {
        let crs = match (facts.crs.clone(), decided_crs.clone()) {
            (Some(c), _) => CrsSource::Known(Some(c)),
            (None, Some(cell)) => CrsSource::Decided(cell),
            (None, None) => CrsSource::Known(None),
        };
        let mut keyed = config.clone();
        keyed.output.dir.clear();
        keyed.daemon = Default::default();
        keyed.navigation = Default::default();
        let info = StoreInfo {
            crs_wkt: None,
            epsg: None,
            intensity_units: if spec.stage_names.contains(&"calibrate") {
                "calibrated backscatter (docs/calibration.md)".into()
            } else {
                "V".into()
            },
            run_key: format!(
                "survey {}, configuration crc32c {:08x}",
                d.survey,
                crc32c::crc32c(toml::to_string(&keyed).unwrap_or_default().as_bytes())
            ),
            configuration: toml::to_string(&config).unwrap_or_default(),
        };
        sinks.push(Box::new(
            VoxelTilesSink::create(
                &out_dir,
                config.voxels.clone(),
                crs,
                info,
                dem.clone(),
                Some(sensor.beam_divergence_mrad),
            )
            .map_err(Failure::job)?
            .continuing()
            .with_coverage()
            .with_tile_writer(TILE_WRITER_QUEUE),
        ));
    }
    if config.output.las && spec.stage_names.contains(&"decompose") {
        let dir = out_dir.join("returns").join(&segment_stem);
        create_dir(&dir, "LAS folder")?;
        sinks.push(Box::new(
            LasWaveSink::create(
                &dir,
                LasWaveOptions {
                    point_format: config.output.las_point_format,
                    rotate_s: if config.output.las_rotate_s > 0.0 {
                        config.output.las_rotate_s
                    } else {
                        60.0
                    },
                    flush_s: config.output.las_flush_s,
                    crs_wkt: facts.crs.clone().filter(|c| !c.starts_with("EPSG:")),
                    crs_decided: decided_crs.clone(),
                    ..LasWaveOptions::default()
                },
            )
            .map_err(Failure::job)?,
        ));
    }

    // QC.
    let mut sampler = Sampler::new(
        hub.clone(),
        control.clone(),
        SamplerSetup {
            cfg: d.clone(),
            inputs: views,
            serial_ports: config.navigation.serial.iter().map(|s| s.port).collect(),
            recorder,
            recorder_queue,
            capture_dir: capture_dir.clone(),
            segment: segment
                .file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_default(),
            georeference: config.georeference.enabled,
            drop_missed: config.georeference.on_missing
                == crate::geo::georeferencing_source::OnMissing::Drop,
            stages,
        },
    );
    tracing::info!(
        survey = %d.survey,
        segment = %segment.display(),
        out = %out_dir.display(),
        workers = spec.workers,
        stages = ?spec.stage_names,
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
    let report = run_pipeline(
        &spec,
        source,
        Box::new(FanOut(sinks)),
        Box::new(NavDecode::new(
            config.georeference.leap_seconds,
            config.navigation.earliest_days(),
        )),
        &control,
        |_| {
            if last_sample.elapsed() >= Duration::from_secs(1) {
                last_sample = Instant::now();
                sampler.tick();
            }
        },
    );
    let last = sampler.tick();
    drop(server);

    let summary_path = out_dir.join(format!("{segment_stem}.summary.json"));
    let mut summary = serde_json::to_value(&report).unwrap_or_default();
    summary["daemon"] = serde_json::json!({
        "survey": d.survey,
        "segment": segment.display().to_string(),
        "seq_base": control.seq_base,
        "frames_received": last.pulses.frames_received,
        "frames_recorded": last.pulses.frames_recorded,
        "frames_lost": last.pulses.frames_lost,
        "frames_bad": last.pulses.frames_bad,
        "drops": last.drops,
        "dropped_total": last.pulses.dropped_total,
    });
    let json = serde_json::to_vec_pretty(&summary)
        .map_err(|e| Failure::job(format!("cannot encode summary: {e}")))?;
    let written = write_atomic(&summary_path, &json);
    print_summary(
        &report,
        &segment.display().to_string(),
        &out_dir,
        &summary_path,
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
