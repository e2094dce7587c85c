//! `fwlidar simulate`: a scene file into a capture (digitizer frames and the navigation bytes a
//! receiver would have sent), deterministic for a given seed.

use std::path::PathBuf;

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
    /// Capture file to write (must not exist: captures are never overwritten).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Number of pulses (overrides the scene).
    #[arg(long)]
    pub pulses: Option<u64>,
    /// Random seed (overrides the scene).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
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
    let mut writer = CaptureWriter::create(&args.out, &header.to_text(), FlushPolicy::default())
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
        args.out.display(),
        args.scene.display(),
        scene.seed
    );
    Ok(())
}
