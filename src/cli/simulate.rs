//! `fwlidar simulate`: a scene file into a capture (digitizer frames and the navigation bytes a
//! receiver would have sent), deterministic for a given seed (or, with `--live`, played in real
//! time into the on-board daemon's inputs: [`crate::sim::live`]). A described scene also writes its
//! truth beside the capture: the truth waveforms as a capture of their own (same shots and
//! navigation, a 2 ns pulse), every scatterer met as CSV, and a JSON summary.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::core::sensor::SensorProfile;
use crate::format::{CaptureHeader, CaptureWriter, FlushPolicy};
use crate::pulse::{Pulse, SegmentKind};
use crate::sim::analytic_scene::Scene;
use crate::sim::world::scene::WorldScene;
use crate::sim::world::{ShotTruth, WorldItems, WorldSim};
use crate::sim::{SimItem, SimItems};

/// Arguments of `fwlidar simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Scene file (TOML with a `[scene]` table; see `config/scenes/`). Not with `--from`.
    #[arg(long, required_unless_present = "from", conflicts_with = "from")]
    pub scene: Option<PathBuf>,
    /// Live: play a capture written by `fwlidar simulate --out` (its frames and navigation
    /// bytes, paced by their GPS times) instead of simulating a scene: playback costs a frame
    /// encoding and a send per pulse, so pulse rates beyond what the simulator computes in
    /// real time on this machine can be played (e.g. the 400 kHz survey line into the daemon).
    #[arg(long, requires = "live", value_name = "CAPTURE")]
    pub from: Option<PathBuf>,
    /// Capture file to write (must not exist: captures are never overwritten). Exactly one of
    /// `--out` and `--live`.
    #[arg(long, short, required_unless_present = "live", conflicts_with = "live")]
    pub out: Option<PathBuf>,
    /// Number of pulses (overrides the scene; for a described scene, the most to generate).
    #[arg(long)]
    pub pulses: Option<u64>,
    /// Random seed (overrides the scene).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
    /// Override a key of a described scene, `KEY=VALUE` (dotted key with list indices, TOML
    /// value), e.g. `--set sensor.outgoing_fwhm_ns=8 --set 'tree[0].height_m=20'`. Repeatable;
    /// a later one wins.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Do not voxelise the truth (a described scene writes `<stem>.truth/voxels.zarr`).
    #[arg(long)]
    pub no_truth_voxels: bool,
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

/// Runs `fwlidar simulate`: an analytic scene (a `[scene]` table) or a described one (a
/// `[flight]` table, [`crate::sim::world`]), which also writes its truth beside the capture.
pub fn run(args: SimulateArgs) -> Result<(), Failure> {
    let Some(scene_path) = args.scene.clone() else {
        let from = args.from.clone().unwrap_or_default();
        let mut items = crate::sim::capture_items::CaptureItems::open(&from)
            .map_err(|e| Failure::usage(e.to_string()))?;
        run_live(&args, &mut items)?;
        return match items.error() {
            Some(e) => Err(Failure::job(e.to_string())),
            None => Ok(()),
        };
    };
    let text = crate::core::toml_load::read_bounded(&scene_path)
        .map_err(|e| Failure::usage(format!("cannot read {}: {e}", scene_path.display())))?;
    let described = toml::from_str::<toml::Table>(&String::from_utf8_lossy(&text))
        .is_ok_and(|t| t.contains_key("flight"));
    if described {
        return run_world(args);
    }
    if !args.sets.is_empty() {
        return Err(Failure::usage(format!(
            "--set applies to described scenes (a [flight] table); {} is an analytic scene: \
             edit its [scene] table",
            scene_path.display()
        )));
    }
    let (mut scene, sensor) = Scene::load(&scene_path).map_err(Failure::usage)?;
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
    let header = CaptureHeader::simulated(&sensor, scene_table, "simulated");
    let mut writer = CaptureWriter::create(&out, &header.to_text(), FlushPolicy::default())
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
        out.display(),
        scene_path.display(),
        scene.seed
    );
    Ok(())
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
/// `<stem>.scatterers.csv`, `<stem>.truth.json`, the folder `<stem>.truth/` (the truth
/// voxelised: `voxels.zarr`), `<stem>.trees.csv` (every tree in map coordinates) and
/// `<stem>.branches.csv` (every first-order branch).
pub fn truth_paths(out: &Path) -> [PathBuf; 6] {
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
        with(".trees.csv"),
        with(".branches.csv"),
    ]
}

/// Header of `<stem>.branches.csv`.
pub const BRANCHES_CSV_HEADER: &str = "tree_id,branch_id,x,y,base_height_m,end_x,end_y,\
end_height_m,azimuth_deg,zenith_deg,length_m,radius_m";

/// Header of `<stem>.trees.csv`.
pub const TREES_CSV_HEADER: &str = "tree_id,x,y,epsg,height_m,crown_shape,crown_base_m,\
crown_radius_m,stem_radius_m,leaf_area_density,scene_x,scene_y";

/// Writes every tree of the scene (its `[[tree]]`s, then each `[[forest]]` stand's) to `path`:
/// the stem's position in the UTM zone of the scene's origin (the CRS a replay of the capture
/// decides, EPSG code in `epsg`), height and crown above the terrain (m), the crown's shape,
/// the stem radius (m), the leaf area density (m²/m³) and the position in the scene's frame
/// (m east and north of the origin). Returns the number of trees.
///
/// Beside it, `branches_path`: every first-order branch the simulator traces
/// ([`crate::sim::world::geometry::tree_branches`]): its tree, its base (on the stem, x, y in the
/// same UTM, height above the terrain, m) and end, its azimuth (degrees clockwise from the
/// scene's north), zenith (degrees from vertical), length and radius (m).
fn write_tree_truth(
    scene: &WorldScene,
    path: &Path,
    branches_path: &Path,
) -> Result<usize, Failure> {
    use crate::geo::crs::{OutputCrs, utm_epsg};
    use crate::sim::world::flight::Frames;
    use crate::sim::world::scene::CrownShape;
    use std::fmt::Write as _;
    let o = &scene.origin;
    let code = utm_epsg(o.lat_deg, o.lon_deg);
    let crs = OutputCrs::from_epsg(code).map_err(Failure::job)?;
    let frames = Frames::new(o.lat_deg, o.lon_deg, o.height_m);
    let mut trees = scene.tree.clone();
    for (i, f) in scene.forest.iter().enumerate() {
        trees.extend(f.trees(scene.seed, i));
    }
    let utm = |sx: f64, sy: f64| -> Result<[f64; 2], Failure> {
        let g = frames.geodetic([sx, sy, 0.0]);
        let [x, y, _] = crs
            .project(g.lat_deg, g.lon_deg, g.height_m)
            .map_err(Failure::job)?;
        Ok([x, y])
    };
    let mut text = String::from(TREES_CSV_HEADER);
    text.push('\n');
    let mut branches = String::from(BRANCHES_CSV_HEADER);
    branches.push('\n');
    for (i, t) in trees.iter().enumerate() {
        let [sx, sy] = t.position_m;
        let [x, y] = utm(sx, sy)?;
        for (k, b) in crate::sim::world::geometry::tree_branches(scene.seed, i as u32, t)
            .iter()
            .enumerate()
        {
            let (z, a) = (b.zenith_deg.to_radians(), b.azimuth_deg.to_radians());
            let (ex, ey) = (
                sx + b.length_m * z.sin() * a.sin(),
                sy + b.length_m * z.sin() * a.cos(),
            );
            let [ux, uy] = utm(ex, ey)?;
            let _ = writeln!(
                branches,
                "{i},{k},{x:.3},{y:.3},{:.3},{ux:.3},{uy:.3},{:.3},{:.3},{:.3},{:.3},{}",
                b.height_m,
                b.height_m + b.length_m * z.cos(),
                b.azimuth_deg,
                b.zenith_deg,
                b.length_m,
                b.radius_m
            );
        }
        let shape = match t.crown.shape {
            CrownShape::Ellipsoid => "ellipsoid",
            CrownShape::Cone => "cone",
            CrownShape::Cylinder => "cylinder",
        };
        let _ = writeln!(
            text,
            "{i},{x:.3},{y:.3},{code},{},{shape},{},{},{},{},{sx},{sy}",
            t.height_m, t.crown.base_m, t.crown.radius_m, t.stem_radius_m, t.leaf_area_density
        );
    }
    std::fs::write(path, text)
        .map_err(|e| Failure::job(format!("cannot write {}: {e}", path.display())))?;
    std::fs::write(branches_path, branches)
        .map_err(|e| Failure::job(format!("cannot write {}: {e}", branches_path.display())))?;
    Ok(trees.len())
}

fn run_world(args: SimulateArgs) -> Result<(), Failure> {
    let scene_path = args.scene.clone().unwrap_or_default();
    let (mut scene, sensor) =
        WorldScene::load_with(&scene_path, &args.sets).map_err(Failure::usage)?;
    if let Some(n) = args.pulses {
        scene.flight.max_pulses = Some(n);
    }
    if let Some(s) = args.seed {
        scene.seed = s;
    }
    let base = scene_path.parent().unwrap_or(Path::new("."));
    let sim = WorldSim::new(&scene, &sensor, base).map_err(Failure::usage)?;
    let out = match (&args.out, args.live) {
        (Some(out), false) => out.clone(),
        _ => {
            let items = WorldItems::new(sim).map_err(Failure::usage)?;
            return run_live(&args, items);
        }
    };
    let paths = WorldPaths::new(out)?;
    let total = sim.plan().pulses();
    let mut items = WorldItems::new(sim).map_err(Failure::usage)?;
    let mut files = WorldFiles::create(&scene, &sensor, &paths)?;
    let bar = progress(args.no_progress, total);
    let written = files.write_stream(&mut items, &sensor, &bar)?;
    let bytes = files.finish()?;
    let summary = world_summary(
        &scene,
        &scene_path,
        &paths,
        total,
        &written,
        items.lost().len(),
    );
    let (pulses, nav) = (written.pulses, written.nav);
    write_tree_truth(&scene, &paths.trees, &paths.branches)?;
    std::fs::write(
        &paths.json,
        serde_json::to_string_pretty(&summary).unwrap_or_default(),
    )
    .map_err(|e| Failure::job(format!("cannot write {}: {e}", paths.json.display())))?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    if !args.no_truth_voxels {
        voxelise_truth(&paths.truth, &paths.truth_dir)?;
    }
    println!(
        "wrote {}: {pulses} pulses ({} lost), {nav} navigation records, {bytes} bytes (scene {}, seed {}); truth in {} and {}",
        paths.out.display(),
        items.lost().len(),
        scene_path.display(),
        scene.seed,
        paths.truth.display(),
        paths.csv.display()
    );
    Ok(())
}

/// The files a described scene's simulation writes ([`truth_paths`] of the capture's).
struct WorldPaths {
    /// The capture.
    out: PathBuf,
    /// The truth capture (2 ns pulse).
    truth: PathBuf,
    /// Every scatterer met, CSV.
    csv: PathBuf,
    /// The JSON summary.
    json: PathBuf,
    /// Where the truth voxels go.
    truth_dir: PathBuf,
    /// The trees, CSV.
    trees: PathBuf,
    /// The trees' branches, CSV.
    branches: PathBuf,
}

impl WorldPaths {
    /// The files beside capture `out`; refused when any of them exists (simulated captures
    /// and their truth are never overwritten).
    fn new(out: PathBuf) -> Result<Self, Failure> {
        let [truth, csv, json, truth_dir, trees, branches] = truth_paths(&out);
        let paths = WorldPaths {
            out,
            truth,
            csv,
            json,
            truth_dir,
            trees,
            branches,
        };
        for p in [
            &paths.out,
            &paths.truth,
            &paths.csv,
            &paths.json,
            &paths.truth_dir,
            &paths.trees,
            &paths.branches,
        ] {
            if p.exists() {
                return Err(Failure::usage(format!(
                    "{} exists: simulated captures and their truth are never overwritten",
                    p.display()
                )));
            }
        }
        Ok(paths)
    }
}

/// The open outputs of a described scene's simulation: the capture, the truth capture and the
/// scatterers' CSV.
struct WorldFiles {
    writer: CaptureWriter<std::fs::File>,
    truth_writer: CaptureWriter<std::fs::File>,
    csv: std::io::BufWriter<std::fs::File>,
    csv_path: PathBuf,
    /// Lost pulses already written to the CSV.
    lost_written: usize,
}

impl WorldFiles {
    /// Creates the capture and the truth capture (headers with the scene's table) and the
    /// scatterers' CSV with its header line.
    fn create(
        scene: &WorldScene,
        sensor: &SensorProfile,
        paths: &WorldPaths,
    ) -> Result<Self, Failure> {
        let table = toml::to_string(scene)
            .ok()
            .and_then(|t| toml::from_str::<toml::Table>(&t).ok());
        let header = CaptureHeader::simulated(sensor, table.clone(), "simulated");
        let writer = CaptureWriter::create(&paths.out, &header.to_text(), FlushPolicy::default())
            .map_err(Failure::job)?;
        let truth_header = CaptureHeader::simulated(sensor, table, "simulated truth (2 ns pulse)");
        let truth_writer = CaptureWriter::create(
            &paths.truth,
            &truth_header.to_text(),
            FlushPolicy::default(),
        )
        .map_err(Failure::job)?;
        let csv_file = std::fs::File::create_new(&paths.csv)
            .map_err(|e| Failure::job(format!("cannot create {}: {e}", paths.csv.display())))?;
        let mut files = WorldFiles {
            writer,
            truth_writer,
            csv: std::io::BufWriter::new(csv_file),
            csv_path: paths.csv.clone(),
            lost_written: 0,
        };
        writeln!(
            files.csv,
            "seq,gps_time_s,kind,object,range_m,range_end_m,east_m,north_m,up_m,fraction,reflectance,amplitude_dn,ray"
        )
        .map_err(|e| files.io(e))?;
        Ok(files)
    }

    /// A write error of the CSV.
    fn io(&self, e: std::io::Error) -> Failure {
        Failure::job(format!("{}: {e}", self.csv_path.display()))
    }

    /// Writes every item of `items`: pulses to the capture, their truth to the truth capture
    /// and their scatterers (and the lost pulses) to the CSV, navigation to both captures.
    fn write_stream(
        &mut self,
        items: &mut WorldItems,
        sensor: &SensorProfile,
        bar: &Option<ProgressBar>,
    ) -> Result<Written, Failure> {
        let (mut pulses, mut nav) = (0u64, 0u64);
        let mut truth_pulse = Pulse::default();
        let truth_steps = truth_steps_per_count(sensor.bits_per_sample);
        while let Some(item) = items.next() {
            self.write_lost(items)?;
            match item {
                SimItem::Pulse(p) => {
                    self.writer.write_pulse(&p).map_err(Failure::job)?;
                    let t = items.last_truth();
                    truth_pulse_of(&p, t, sensor, truth_steps, &mut truth_pulse);
                    self.truth_writer
                        .write_pulse(&truth_pulse)
                        .map_err(Failure::job)?;
                    self.write_scatterers(t)?;
                    pulses += 1;
                    tick(bar, pulses);
                }
                SimItem::Nav {
                    receive_time_ns,
                    bytes,
                } => {
                    self.writer
                        .write_nav(0, receive_time_ns, &bytes)
                        .map_err(Failure::job)?;
                    self.truth_writer
                        .write_nav(0, receive_time_ns, &bytes)
                        .map_err(Failure::job)?;
                    nav += 1;
                }
            }
        }
        self.write_lost(items)?;
        Ok(Written {
            pulses,
            nav,
            truth_steps,
        })
    }

    /// The pulses `items` lost since the last call, one CSV line each.
    fn write_lost(&mut self, items: &WorldItems) -> Result<(), Failure> {
        for &seq in &items.lost()[self.lost_written..] {
            writeln!(self.csv, "{seq},,lost,,,,,,,,,,").map_err(|e| self.io(e))?;
        }
        self.lost_written = items.lost().len();
        Ok(())
    }

    /// One CSV line per scatterer of pulse truth `t` (ranges and positions in metres, scene
    /// frame; amplitudes in counts).
    fn write_scatterers(&mut self, t: &ShotTruth) -> Result<(), Failure> {
        for s in &t.scatterers {
            writeln!(
                self.csv,
                "{},{:.9},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.6},{:.4},{:.4},{}",
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
                s.amplitude_dn,
                s.ray
            )
            .map_err(|e| self.io(e))?;
        }
        Ok(())
    }

    /// Flushes the CSV and finishes both captures; returns the capture's bytes.
    fn finish(mut self) -> Result<u64, Failure> {
        self.csv.flush().map_err(|e| self.io(e))?;
        let bytes = self.writer.bytes_written();
        self.writer.finish().map_err(Failure::job)?;
        self.truth_writer.finish().map_err(Failure::job)?;
        Ok(bytes)
    }
}

/// What [`WorldFiles::write_stream`] wrote.
struct Written {
    /// Pulses recorded.
    pulses: u64,
    /// Navigation records.
    nav: u64,
    /// Steps per sensor count in the truth capture.
    truth_steps: f64,
}

/// The JSON summary of a described scene's simulation: the scene, its frame, effects, what
/// was written (`total` pulses generated, `lost` of them lost) and where.
fn world_summary(
    scene: &WorldScene,
    scene_path: &Path,
    paths: &WorldPaths,
    total: u64,
    written: &Written,
    lost: usize,
) -> serde_json::Value {
    let o = &scene.origin;
    serde_json::json!({
        "scene": scene_path.display().to_string(),
        "seed": scene.seed,
        "frame": {
            "description": "scene frame: metres east, north, up of the origin, tangent plane",
            "origin_lat_deg": o.lat_deg,
            "origin_lon_deg": o.lon_deg,
            "origin_height_m": o.height_m,
        },
        "effects": scene.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
        "pulses_generated": total,
        "pulses_recorded": written.pulses,
        "pulses_lost": lost,
        "navigation_records": written.nav,
        "truth_capture": paths.truth.display().to_string(),
        "truth_steps_per_count": written.truth_steps,
        "scatterers": paths.csv.display().to_string(),
        "trees": paths.trees.display().to_string(),
        "branches": paths.branches.display().to_string(),
    })
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
    sensor: &crate::core::sensor::SensorProfile,
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
        inputs: vec![truth.to_path_buf()],
        shard: None,
        out: Some(dir.to_path_buf()),
        config: Some(config),
        workers: Some(1),
        no_progress: true,
        sets: Vec::new(),
        target_fwhm_ns: None,
    })
}

/// `fwlidar simulate --live`: opens the outputs (printing where they are), plays the stream,
/// prints the report. Unreachable ports and missing terminals fail the job (exit 1).
fn run_live(args: &SimulateArgs, items: impl Iterator<Item = SimItem>) -> Result<(), Failure> {
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
