//! `fwlidar simulate`: a scene file into a capture (digitizer frames and the navigation bytes a
//! receiver would have sent), deterministic for a given seed; or, with `--live`, the same
//! stream played in real time into the on-board daemon's inputs ([`crate::sim::live`]).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::format::{CaptureHeader, CaptureMeta, CaptureWriter, FlushPolicy};
use crate::sim::scene::Scene;
use crate::sim::{SimItem, SimItems};

/// Arguments of `fwlidar simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Scene file (TOML with a `[scene]` table; see `config/scenes/`).
    #[arg(long)]
    pub scene: PathBuf,
    /// Capture file to write (must not exist: captures are never overwritten). Exactly one of
    /// `--out` and `--live`.
    #[arg(long, short, required_unless_present = "live", conflicts_with = "live")]
    pub out: Option<PathBuf>,
    /// Number of pulses (overrides the scene).
    #[arg(long)]
    pub pulses: Option<u64>,
    /// Random seed (overrides the scene).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
    /// Play the stream in real time into a daemon's inputs instead of writing a capture
    /// (`--frames` and/or `--nav-tty` / `--nav-pty-link`).
    #[arg(long)]
    pub live: bool,
    /// Live: where digitizer frames go, `udp:HOST:PORT` (one datagram per pulse to that
    /// destination), `tcp-listen:HOST:PORT` (serve the daemon that connects; port 0 = any free
    /// port, printed) or `tcp-connect:HOST:PORT` (connect to a listening daemon).
    #[arg(long, requires = "live", value_name = "TARGET")]
    pub frames: Option<String>,
    /// Live: write navigation bytes into this existing terminal device (e.g. a socat pty).
    #[arg(
        long,
        requires = "live",
        conflicts_with = "nav_pty_link",
        value_name = "PATH"
    )]
    pub nav_tty: Option<PathBuf>,
    /// Live: create a pseudo-terminal pair and symlink its slave at PATH for the daemon to open
    /// as its serial navigation device (an existing symlink there is replaced).
    #[arg(long, requires = "live", value_name = "PATH")]
    pub nav_pty_link: Option<PathBuf>,
    /// Live: baud rate set on `--nav-tty`, bits per second.
    #[arg(long, requires = "live", default_value_t = 115_200)]
    pub nav_baud: u32,
    /// Live: playback speed, a multiple of real time (1 = real time, 2 = twice as fast, 0 = as
    /// fast as possible).
    #[arg(long, requires = "live", default_value_t = 1.0, value_parser = parse_speed)]
    pub speed: f64,
}

fn parse_speed(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!(
            "{text:?} is not a speed: a finite number >= 0 (0 = as fast as possible)"
        )),
    }
}

/// Runs `fwlidar simulate`.
pub fn run(args: SimulateArgs) -> Result<(), Failure> {
    let (mut scene, sensor) = Scene::load(&args.scene).map_err(Failure::usage)?;
    if let Some(n) = args.pulses {
        scene.pulses = n;
    }
    if let Some(s) = args.seed {
        scene.seed = s;
    }
    scene.validate().map_err(Failure::usage)?;
    let items = SimItems::new(&scene, &sensor).map_err(Failure::usage)?;
    let out = match (&args.out, args.live) {
        (Some(out), false) => out.clone(),
        _ => return run_live(&args, items),
    };
    let scene_table = scene
        .to_toml_string()
        .ok()
        .and_then(|t| toml::from_str::<toml::Table>(&t).ok())
        .and_then(|t| t.get("scene").and_then(|s| s.as_table()).cloned());
    let header = CaptureHeader {
        capture: CaptureMeta {
            software: format!("fwlidar {}", env!("CARGO_PKG_VERSION")),
            // Deterministic output: a simulated capture's creation time is its scene's GPS
            // start, not the wall clock, so the same scene and seed give identical bytes.
            created_unix_s: 0,
            time_base: "gps_seconds_of_week".into(),
            origin: "simulated".into(),
            crs: None,
            source_file: None,
        },
        sensor: sensor.clone(),
        scene: scene_table,
    };
    let mut writer = CaptureWriter::create(&out, &header.to_text(), FlushPolicy::default())
        .map_err(Failure::job)?;
    let bar = (!args.no_progress).then(|| {
        let bar = ProgressBar::new(scene.pulses);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} pulses",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    });
    let (mut pulses, mut nav) = (0u64, 0u64);
    for item in items {
        match item {
            SimItem::Pulse(p) => {
                writer.write_pulse(&p).map_err(Failure::job)?;
                pulses += 1;
                if let Some(b) = &bar
                    && pulses % 1024 == 0
                {
                    b.set_position(pulses);
                }
            }
            SimItem::Nav {
                receive_time_ns,
                bytes,
            } => {
                writer
                    .write_nav(0, receive_time_ns, &bytes)
                    .map_err(Failure::job)?;
                nav += 1;
            }
        }
    }
    let bytes = writer.bytes_written();
    writer.finish().map_err(Failure::job)?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    println!(
        "wrote {}: {pulses} pulses, {nav} navigation records, {bytes} bytes (scene {}, seed {})",
        out.display(),
        args.scene.display(),
        scene.seed
    );
    Ok(())
}

/// `fwlidar simulate --live`: opens the outputs (printing where they are), plays the stream,
/// prints the report. Unreachable ports and missing terminals fail the job (exit 1).
fn run_live(args: &SimulateArgs, items: SimItems) -> Result<(), Failure> {
    use crate::sim::live::{self, FrameListener, FrameOutput, FrameTarget, NavOutput};

    let target = args
        .frames
        .as_deref()
        .map(str::parse::<FrameTarget>)
        .transpose()
        .map_err(Failure::usage)?;
    if target.is_none() && args.nav_tty.is_none() && args.nav_pty_link.is_none() {
        return Err(Failure::usage(
            "--live needs somewhere to send: --frames TARGET and/or --nav-tty PATH / --nav-pty-link PATH",
        ));
    }
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 130, stop.clone())
            .and_then(|_| signal_hook::flag::register(sig, stop.clone()))
            .map_err(|e| Failure::job(format!("cannot install signal handler: {e}")))?;
    }
    let mut nav = match (&args.nav_tty, &args.nav_pty_link) {
        (Some(path), _) => Some(NavOutput::open_tty(path, args.nav_baud).map_err(Failure::job)?),
        (None, Some(link)) => Some(NavOutput::create_pty_link(link).map_err(Failure::job)?),
        (None, None) => None,
    };
    if let Some(n) = &nav {
        println!("navigation: {}", n.describe());
    }
    let mut frames = match target {
        None => None,
        Some(FrameTarget::Udp(addr)) => Some(FrameOutput::udp(addr).map_err(Failure::job)?),
        Some(FrameTarget::TcpConnect(addr)) => {
            Some(FrameOutput::tcp_connect(addr).map_err(Failure::job)?)
        }
        Some(FrameTarget::TcpListen(addr)) => {
            let listener = FrameListener::bind(addr).map_err(Failure::job)?;
            println!(
                "digitizer frames: listening on tcp {}, waiting for the daemon to connect",
                listener.local_addr()
            );
            match listener.accept(&stop).map_err(Failure::job)? {
                Some(out) => Some(out),
                None => {
                    println!("stopped before a daemon connected; nothing sent");
                    return Ok(());
                }
            }
        }
    };
    if let Some(f) = &frames {
        println!("digitizer frames: sending to {}", f.target());
    }
    let report = live::play(
        items,
        frames.as_mut(),
        nav.as_mut(),
        args.speed,
        &stop,
        &mut |r| tracing::info!("live: {r}"),
    )
    .map_err(Failure::job)?;
    println!("sent {report}");
    Ok(())
}
