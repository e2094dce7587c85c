//! `fwlidar simulate`: a scene file into a capture (digitizer frames and the navigation bytes a
//! receiver would have sent), deterministic for a given seed. A described scene also writes its
//! truth beside the capture: the truth waveforms as a capture of their own (same shots and
//! navigation, a 2 ns pulse), every scatterer met as CSV, and a JSON summary.

use std::io::Write;
use std::path::{Path, PathBuf};

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::format::{CaptureHeader, CaptureMeta, CaptureWriter, FlushPolicy};
use crate::pulse::{Pulse, SegmentKind};
use crate::sim::scene::Scene;
use crate::sim::world::scene::WorldScene;
use crate::sim::world::{WorldItems, WorldSim};
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
    /// Number of pulses (overrides the scene; for a described scene, the most to generate).
    #[arg(long)]
    pub pulses: Option<u64>,
    /// Random seed (overrides the scene).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
    /// Override a key of a described scene, `KEY=VALUE` (dotted key, TOML value), e.g.
    /// `--set sensor.outgoing_fwhm_ns=8 --set flight.scan.zenith_deg=10`. Repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Do not voxelise the truth (a described scene writes `<stem>.truth/voxels.zarr`).
    #[arg(long)]
    pub no_truth_voxels: bool,
}

/// Runs `fwlidar simulate`: an analytic scene (a `[scene]` table) or a described one (a
/// `[flight]` table, [`crate::sim::world`]), which also writes its truth beside the capture.
pub fn run(args: SimulateArgs) -> Result<(), Failure> {
    let text = crate::config::load::read_bounded(&args.scene)
        .map_err(|e| Failure::usage(format!("cannot read {}: {e}", args.scene.display())))?;
    let described = toml::from_str::<toml::Table>(&String::from_utf8_lossy(&text))
        .is_ok_and(|t| t.contains_key("flight"));
    if described {
        return run_world(args);
    }
    if !args.sets.is_empty() {
        return Err(Failure::usage(format!(
            "--set applies to described scenes (a [flight] table); {} is an analytic scene: \
             edit its [scene] table",
            args.scene.display()
        )));
    }
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
    let header = capture_header(&sensor, scene_table, "simulated");
    let mut writer = CaptureWriter::create(&args.out, &header.to_text(), FlushPolicy::default())
        .map_err(Failure::job)?;
    let bar = progress(args.no_progress, scene.pulses);
    let (mut pulses, mut nav) = (0u64, 0u64);
    for item in items {
        match item {
            SimItem::Pulse(p) => {
                writer.write_pulse(&p).map_err(Failure::job)?;
                pulses += 1;
                tick(&bar, pulses);
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

fn capture_header(
    sensor: &crate::config::sensor::SensorProfile,
    scene: Option<toml::Table>,
    origin: &str,
) -> CaptureHeader {
    CaptureHeader {
        capture: CaptureMeta {
            software: format!("fwlidar {}", env!("CARGO_PKG_VERSION")),
            // Deterministic output: a simulated capture's creation time is not the wall
            // clock, so the same scene and seed give identical bytes.
            created_unix_s: 0,
            time_base: "gps_seconds_of_week".into(),
            origin: origin.into(),
            crs: None,
            source_file: None,
        },
        sensor: sensor.clone(),
        scene,
    }
}

fn progress(hidden: bool, len: u64) -> Option<ProgressBar> {
    (!hidden).then(|| {
        let bar = ProgressBar::new(len);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} pulses",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    })
}

fn tick(bar: &Option<ProgressBar>, pulses: u64) {
    if let Some(b) = bar
        && pulses.is_multiple_of(1024)
    {
        b.set_position(pulses);
    }
}

/// The files written beside a described scene's capture `out`: `<stem>.truth.fwcap`,
/// `<stem>.scatterers.csv`, `<stem>.truth.json`, and the folder `<stem>.truth/` (the truth
/// voxelised: `voxels.zarr`).
pub fn truth_paths(out: &Path) -> [PathBuf; 4] {
    let stem = out.with_extension("");
    let with = |suffix: &str| {
        let mut s = stem.as_os_str().to_owned();
        s.push(suffix);
        PathBuf::from(s)
    };
    [
        with(".truth.fwcap"),
        with(".scatterers.csv"),
        with(".truth.json"),
        with(".truth"),
    ]
}

fn run_world(args: SimulateArgs) -> Result<(), Failure> {
    let (mut scene, sensor) =
        WorldScene::load_with(&args.scene, &args.sets).map_err(Failure::usage)?;
    if let Some(n) = args.pulses {
        scene.flight.max_pulses = Some(n);
    }
    if let Some(s) = args.seed {
        scene.seed = s;
    }
    let base = args.scene.parent().unwrap_or(Path::new("."));
    let sim = WorldSim::new(&scene, &sensor, base).map_err(Failure::usage)?;
    let [truth_path, csv_path, json_path, truth_dir] = truth_paths(&args.out);
    for p in [&args.out, &truth_path, &csv_path, &json_path, &truth_dir] {
        if p.exists() {
            return Err(Failure::usage(format!(
                "{} exists: simulated captures and their truth are never overwritten",
                p.display()
            )));
        }
    }
    let total = sim.plan().pulses();
    let mut items = WorldItems::new(sim).map_err(Failure::usage)?;
    let table = toml::to_string(&scene)
        .ok()
        .and_then(|t| toml::from_str::<toml::Table>(&t).ok());
    let header = capture_header(&sensor, table.clone(), "simulated");
    let mut writer = CaptureWriter::create(&args.out, &header.to_text(), FlushPolicy::default())
        .map_err(Failure::job)?;
    let truth_header = capture_header(&sensor, table, "simulated truth (2 ns pulse)");
    let mut truth_writer =
        CaptureWriter::create(&truth_path, &truth_header.to_text(), FlushPolicy::default())
            .map_err(Failure::job)?;
    let csv_file = std::fs::File::create_new(&csv_path)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", csv_path.display())))?;
    let mut csv = std::io::BufWriter::new(csv_file);
    let io = |e: std::io::Error| Failure::job(format!("{}: {e}", csv_path.display()));
    writeln!(
        csv,
        "seq,gps_time_s,kind,object,range_m,range_end_m,east_m,north_m,up_m,fraction,reflectance,amplitude_dn"
    )
    .map_err(io)?;
    let bar = progress(args.no_progress, total);
    let (mut pulses, mut nav, mut lost_written) = (0u64, 0u64, 0usize);
    let mut truth_pulse = Pulse::default();
    let truth_steps = truth_steps_per_count(sensor.bits_per_sample);
    while let Some(item) = items.next() {
        for &seq in &items.lost()[lost_written..] {
            writeln!(csv, "{seq},,lost,,,,,,,,,").map_err(io)?;
        }
        lost_written = items.lost().len();
        match item {
            SimItem::Pulse(p) => {
                writer.write_pulse(&p).map_err(Failure::job)?;
                let t = items.last_truth();
                truth_pulse_of(&p, t, &sensor, truth_steps, &mut truth_pulse);
                truth_writer
                    .write_pulse(&truth_pulse)
                    .map_err(Failure::job)?;
                for s in &t.scatterers {
                    writeln!(
                        csv,
                        "{},{:.9},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.6},{:.4},{:.4}",
                        t.seq,
                        t.gps_time,
                        s.kind.name(),
                        s.object,
                        s.range_m,
                        s.range_end_m,
                        s.position[0],
                        s.position[1],
                        s.position[2],
                        s.fraction,
                        s.reflectance,
                        s.amplitude_dn
                    )
                    .map_err(io)?;
                }
                pulses += 1;
                tick(&bar, pulses);
            }
            SimItem::Nav {
                receive_time_ns,
                bytes,
            } => {
                writer
                    .write_nav(0, receive_time_ns, &bytes)
                    .map_err(Failure::job)?;
                truth_writer
                    .write_nav(0, receive_time_ns, &bytes)
                    .map_err(Failure::job)?;
                nav += 1;
            }
        }
    }
    for &seq in &items.lost()[lost_written..] {
        writeln!(csv, "{seq},,lost,,,,,,,,,").map_err(io)?;
    }
    csv.flush().map_err(io)?;
    let bytes = writer.bytes_written();
    writer.finish().map_err(Failure::job)?;
    truth_writer.finish().map_err(Failure::job)?;
    let o = &scene.origin;
    let summary = serde_json::json!({
        "scene": args.scene.display().to_string(),
        "seed": scene.seed,
        "frame": {
            "description": "scene frame: metres east, north, up of the origin, tangent plane",
            "origin_lat_deg": o.lat_deg,
            "origin_lon_deg": o.lon_deg,
            "origin_height_m": o.height_m,
        },
        "effects": scene.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
        "pulses_generated": total,
        "pulses_recorded": pulses,
        "pulses_lost": items.lost().len(),
        "navigation_records": nav,
        "truth_capture": truth_path.display().to_string(),
        "truth_steps_per_count": truth_steps,
        "scatterers": csv_path.display().to_string(),
    });
    std::fs::write(
        &json_path,
        serde_json::to_string_pretty(&summary).unwrap_or_default(),
    )
    .map_err(|e| Failure::job(format!("cannot write {}: {e}", json_path.display())))?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    if !args.no_truth_voxels {
        voxelise_truth(&truth_path, &truth_dir)?;
    }
    println!(
        "wrote {}: {pulses} pulses ({} lost), {nav} navigation records, {bytes} bytes (scene {}, seed {}); truth in {} and {}",
        args.out.display(),
        items.lost().len(),
        args.scene.display(),
        scene.seed,
        truth_path.display(),
        csv_path.display()
    );
    Ok(())
}

/// Steps per sensor count in a truth capture: room for 16× the sensor's range in 16 bits
/// (a 2 ns truth peak is up to 8× a 16 ns echo's).
pub fn truth_steps_per_count(bits: u8) -> f64 {
    2f64.powi((12 - bits.min(12) as i32).max(0))
}

/// The truth pulse of `p`: the same shot with a 2 ns outgoing pulse (peak 100 counts) and the
/// truth waveform as its return, baseline 0, `steps` steps per sensor count.
fn truth_pulse_of(
    p: &Pulse,
    t: &crate::sim::world::ShotTruth,
    sensor: &crate::config::sensor::SensorProfile,
    steps: f64,
    out: &mut Pulse,
) {
    out.reset();
    out.seq = p.seq;
    out.pulse_id = p.pulse_id;
    out.gps_time = p.gps_time;
    out.scan_angle_deg = p.scan_angle_deg;
    out.sample_ns = p.sample_ns;
    out.gain_v_per_dn = (sensor.digitizer_gain_v_per_dn / steps) as f32;
    out.offset_v = 0.0;
    out.bits = 16;
    let sigma = 2.0 / crate::sim::analytic::FWHM_PER_SIGMA;
    let n_out = ((10.0 * sigma / p.sample_ns).ceil() as usize).max(3) | 1;
    let start = -((n_out / 2) as f64) * p.sample_ns;
    let to_raw = |v: f64| (v * steps).round().clamp(0.0, 65_535.0) as u16;
    let first = out.raw.len();
    for i in 0..n_out {
        let z = (start + i as f64 * p.sample_ns) / sigma;
        out.raw.push(to_raw(100.0 * (-0.5 * z * z).exp()));
    }
    let seg = out.push_segment(SegmentKind::Outgoing, 0, start, []);
    out.segments[seg].first = first as u32;
    out.segments[seg].len = n_out as u32;
    let first = out.raw.len();
    for &v in &t.truth {
        out.raw.push(to_raw(v));
    }
    let seg = out.push_segment(SegmentKind::Return, 0, t.return_start_ns, []);
    out.segments[seg].first = first as u32;
    out.segments[seg].len = t.truth.len() as u32;
}

/// The configuration that voxelises a truth capture (`config/truth_voxels.toml`).
pub const TRUTH_VOXELS_CONFIG: &str = include_str!("../../config/truth_voxels.toml");

/// Replays the truth capture through georeferencing into `dir/voxels.zarr` (with a copy of
/// the configuration used beside it).
fn voxelise_truth(truth: &Path, dir: &Path) -> Result<(), Failure> {
    std::fs::create_dir_all(dir)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", dir.display())))?;
    let config = dir.join("truth_voxels.toml");
    std::fs::write(&config, TRUTH_VOXELS_CONFIG)
        .map_err(|e| Failure::job(format!("cannot write {}: {e}", config.display())))?;
    crate::cli::replay::run(crate::cli::replay::ReplayArgs {
        input: truth.to_path_buf(),
        out: Some(dir.to_path_buf()),
        config: Some(config),
        workers: Some(1),
        no_progress: true,
    })
}
