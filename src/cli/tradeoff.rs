//! `fwlidar tradeoff`: what accuracy costs in time. Sweeps raw, denoise only, and every
//! deconvolution method at several settings over simulated pulses with known truth
//! ([`crate::eval::tradeoff`]), with each `--chain FILE`'s stages beside them
//! ([`crate::eval::chain`]), and writes `tradeoff.csv`, `tradeoff_summary.csv`, `tradeoff.md`
//! and `tradeoff.svg` into the output folder, each atomically (complete or not at all), after
//! the whole sweep ran. Progress goes to stderr, one line per case.

use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use crate::cli::Failure;
use crate::core::atomic_file::write_atomic;
use crate::eval::chain::ChainSpec;
use crate::eval::report::{Machine, csv, markdown, summary_csv};
use crate::eval::tradeoff::{Setting, SweepConfig, default_settings, run_sweep, summarise};
use crate::eval::{plot, report};
use crate::sim::truth::TruthFamily;

/// Pulses per case of `--quick`.
pub const QUICK_PULSES: usize = 24;

/// Arguments of `fwlidar tradeoff`.
#[derive(Debug, clap::Args)]
pub struct TradeoffArgs {
    /// Output folder (created if missing): `tradeoff.csv`, `tradeoff_summary.csv`,
    /// `tradeoff.md`, `tradeoff.svg`.
    #[arg(long, default_value = "out/tradeoff")]
    pub out: PathBuf,
    /// A run configuration (e.g. `config/onboard.toml`) whose `[[pipeline.stages]]` are scored
    /// beside the built-in settings as `chain:<file stem>`: its stages that change the waveform
    /// (denoise, deconvolve) run as replay runs them on each simulated pulse, recorded as a
    /// 16-bit digitizer would with its outgoing pulse. Repeatable.
    #[arg(long = "chain", value_name = "FILE", conflicts_with = "scene")]
    pub chains: Vec<PathBuf>,
    /// Simulated pulses per (pulse width, truth family) case. Default 1000 (24 with `--quick`).
    #[arg(long)]
    pub pulses: Option<usize>,
    /// A fast run for checks: 24 pulses per case unless `--pulses` says otherwise.
    #[arg(long)]
    pub quick: bool,
    /// Outgoing pulse widths, FWHM, ns (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = vec![4.0, 8.0, 16.0])]
    pub widths_ns: Vec<f64>,
    /// Uniform noise half-range, as a fraction of the noise-free received peak.
    #[arg(long, default_value_t = 0.03)]
    pub noise: f32,
    /// Peaks not above this fraction of their waveform's maximum are not counted (0 = every
    /// sign change of the derivative, the seed's literal rule).
    #[arg(long, default_value_t = 0.05)]
    pub peak_floor: f32,
    /// A detected peak agrees with a truth peak within this many bins (0 = the same bin).
    #[arg(long, default_value_t = 1)]
    pub peak_tolerance_bins: usize,
    /// The noise-aware detector: a detected peak counts only when what its echo adds to the
    /// received waveform is at least this many times the waveform's noise σ (0 = no test, the
    /// floor alone).
    #[arg(long, default_value_t = 0.0)]
    pub peak_snr: f32,
    /// Seed of the simulated truth and noise.
    #[arg(long, default_value_t = 2012)]
    pub seed: u64,
    /// A described scene (`config/scenes/*.toml` with `[flight]`): score its pulses step by
    /// step (raw, denoise, each deconvolution, voxelised) against the scene's truth instead of
    /// the sweep; writes `scene_steps.md` and `scene_steps.csv`. `--pulses` (default 1600) and
    /// `--set` apply to it.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Scene override `KEY=VALUE` (with `--scene`), as `fwlidar simulate --set`.
    #[arg(long = "set", value_name = "KEY=VALUE", requires = "scene")]
    pub sets: Vec<String>,
    /// With `--scene`: the seed's experiment matrix, every combination of `--widths-ns`
    /// (outgoing pulse FWHM), `--zeniths-deg` and `--azimuths-deg` (a fixed scan, off nadir
    /// towards the azimuth from the heading); writes `scene_matrix.csv` and `.md`.
    #[arg(long, requires = "scene")]
    pub matrix: bool,
    /// Zenith angles of `--matrix`, degrees (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = vec![0.0, 5.0, 10.0, 15.0, 20.0])]
    pub zeniths_deg: Vec<f64>,
    /// Azimuths of `--matrix`, degrees clockwise from the heading (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = vec![0.0, 90.0, 180.0, 270.0])]
    pub azimuths_deg: Vec<f64>,
}

/// `fwlidar tradeoff --scene --matrix`: the stepwise evaluation at every pulse width, zenith
/// and azimuth (the seed's experiments), one CSV row per (combination, step).
fn run_matrix(args: &TradeoffArgs, scene_path: &std::path::Path) -> Result<(), Failure> {
    use crate::eval::scene_steps;
    use crate::sim::world::scene::WorldScene;
    let pulses = args.pulses.unwrap_or(if args.quick { 200 } else { 1600 });
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", args.out.display())))?;
    let mut csv = String::from("width_ns,zenith_deg,azimuth_deg,");
    csv.push_str(scene_steps::csv(&[]).trim_end());
    csv.push('\n');
    let mut md = format!(
        "# Experiment matrix of {} ({pulses} pulses each)\n\n\
         | width (ns) | zenith (°) | azimuth (°) | raw RMSE | RL RMSE | raw SAM (°) | RL SAM (°) | RL false peaks | voxel RMSE | voxel SAM (°) | voxel peaks found |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
        scene_path.display()
    );
    let total = args.widths_ns.len() * args.zeniths_deg.len() * args.azimuths_deg.len();
    let started = Instant::now();
    let mut done = 0;
    for &w in &args.widths_ns {
        for &z in &args.zeniths_deg {
            for &a in &args.azimuths_deg {
                // At nadir every azimuth is the same view: one run.
                if z == 0.0 && a != args.azimuths_deg[0] {
                    continue;
                }
                let mut sets = args.sets.clone();
                sets.push(format!("sensor.outgoing_fwhm_ns={w}"));
                sets.push("flight.scan.pattern=\"fixed\"".into());
                sets.push(format!("flight.scan.zenith_deg={z}"));
                sets.push(format!("flight.scan.azimuth_deg={a}"));
                let (mut scene, sensor) =
                    WorldScene::load_with(scene_path, &sets).map_err(Failure::usage)?;
                if !scene
                    .effects
                    .contains(&crate::sim::world::scene::Effect::OffNadir)
                {
                    scene
                        .effects
                        .push(crate::sim::world::scene::Effect::OffNadir);
                }
                let r = steps_of(args, scene_path, &scene, &sensor, pulses)?;
                for line in scene_steps::csv(&r).lines().skip(1) {
                    csv.push_str(&format!("{w},{z},{a},{line}\n"));
                }
                let step = |name: &str| r.iter().find(|s| s.step.starts_with(name));
                if let (Some(raw), Some(rl), Some(vox)) =
                    (step("raw"), step("rl "), step("voxelise"))
                {
                    md.push_str(&format!(
                        "| {w} | {z} | {a} | {:.4} | {:.4} | {:.1} | {:.1} | {:.2} | {:.4} | {:.1} | {:.1} % |\n",
                        raw.rmse,
                        rl.rmse_2ns,
                        raw.sam_deg,
                        rl.sam_deg,
                        rl.false_per_pulse,
                        vox.rmse,
                        vox.sam_deg,
                        100.0 * vox.detection_rate
                    ));
                }
                done += 1;
                eprintln!("[{done}/{total}] width {w} ns, zenith {z}°, azimuth {a}°");
            }
        }
    }
    md.push_str("\nRL: Richardson-Lucy, 20 iterations, after denoise, RMSE through the truth's 2 ns pulse. At nadir the azimuth does not matter: one run.\n");
    for (name, body) in [
        ("scene_matrix.md", md.as_bytes()),
        ("scene_matrix.csv", csv.as_bytes()),
    ] {
        let path = args.out.join(name);
        write_atomic(&path, body).map_err(|e| Failure::job(format!("{}: {e}", path.display())))?;
    }
    print!("{md}");
    println!(
        "{} s; wrote {}/scene_matrix.md and scene_matrix.csv",
        started.elapsed().as_secs(),
        args.out.display()
    );
    Ok(())
}

/// `fwlidar tradeoff --scene`: the stepwise evaluation of one described scene.
fn run_scene(args: &TradeoffArgs, scene_path: &std::path::Path) -> Result<(), Failure> {
    use crate::eval::scene_steps;
    use crate::sim::world::scene::WorldScene;
    let (scene, sensor) = WorldScene::load_with(scene_path, &args.sets).map_err(Failure::usage)?;
    let pulses = args.pulses.unwrap_or(if args.quick { 200 } else { 1600 });
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", args.out.display())))?;
    let started = Instant::now();
    let results = steps_of(args, scene_path, &scene, &sensor, pulses)?;
    let machine = Machine::detect();
    let cpu = format!(
        "{} ({} logical cores)",
        machine.cpu.as_deref().unwrap_or("unknown CPU"),
        machine.cores
    );
    let md = format!(
        "# Stepwise evaluation of {} ({} pulses)\n\n{}\nMachine: {cpu}. Time per pulse: one thread, the step alone.\n",
        scene_path.display(),
        results.first().map_or(0, |r| r.scored),
        scene_steps::markdown(&results),
    );
    for (name, body) in [
        ("scene_steps.md", md.as_bytes()),
        ("scene_steps.csv", scene_steps::csv(&results).as_bytes()),
    ] {
        let path = args.out.join(name);
        write_atomic(&path, body).map_err(|e| Failure::job(format!("{}: {e}", path.display())))?;
    }
    print!("{}", scene_steps::markdown(&results));
    println!(
        "{} s; wrote {}/scene_steps.md and scene_steps.csv",
        started.elapsed().as_secs(),
        args.out.display()
    );
    Ok(())
}

/// The stepwise evaluation of `scene` (from the file `scene_path`) on `pulses` pulses, with a
/// scratch folder in the output folder for its capture and voxel stores (removed after).
fn steps_of(
    args: &TradeoffArgs,
    scene_path: &std::path::Path,
    scene: &crate::sim::world::scene::WorldScene,
    sensor: &crate::core::sensor::SensorProfile,
    pulses: usize,
) -> Result<Vec<crate::eval::scene_steps::StepResult>, Failure> {
    let base = scene_path.parent().unwrap_or(std::path::Path::new("."));
    let sim = crate::sim::world::WorldSim::new(scene, sensor, base).map_err(Failure::usage)?;
    let items = crate::sim::world::WorldItems::new(sim).map_err(Failure::usage)?;
    let scratch = tempfile_dir(&args.out)?;
    let r = crate::eval::scene_steps::run_scene_steps(
        items,
        pulses,
        args.peak_floor,
        args.peak_tolerance_bins,
        &scratch,
    );
    let _ = std::fs::remove_dir_all(&scratch);
    r.map_err(Failure::job)
}

/// A fresh scratch folder inside `out` (removed by the caller).
fn tempfile_dir(out: &std::path::Path) -> Result<PathBuf, Failure> {
    let dir = out.join(format!(".scene_steps_{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", dir.display())))?;
    Ok(dir)
}

/// Runs the sweep and writes the three files.
pub fn run(args: TradeoffArgs) -> Result<(), Failure> {
    if let Some(scene) = args.scene.clone() {
        if args.peak_snr != 0.0 {
            return Err(Failure::usage(format!(
                "--peak-snr {} applies to the sweep; a scene's steps ({}) are scored with \
                 --peak-floor alone",
                args.peak_snr,
                scene.display()
            )));
        }
        if args.matrix {
            return run_matrix(&args, &scene);
        }
        return run_scene(&args, &scene);
    }
    let pulses = args
        .pulses
        .unwrap_or(if args.quick { QUICK_PULSES } else { 1000 });
    let config = SweepConfig {
        pulses,
        widths_ns: args.widths_ns.clone(),
        families: TruthFamily::ALL.to_vec(),
        noise_fraction: args.noise,
        peak_floor: args.peak_floor,
        peak_tolerance_bins: args.peak_tolerance_bins,
        peak_snr: args.peak_snr,
        seed: args.seed,
        ..SweepConfig::default()
    };
    config.validate().map_err(Failure::usage)?;
    let mut settings = default_settings();
    for path in &args.chains {
        let spec = ChainSpec::load(path).map_err(Failure::usage)?;
        if settings.iter().any(|s| s.method == spec.method()) {
            return Err(Failure::usage(format!(
                "--chain {}: a chain named `{}` is given twice (chains are named by their \
                 file's stem)",
                path.display(),
                spec.method()
            )));
        }
        eprintln!(
            "tradeoff: {} runs {} from {}{}",
            spec.method(),
            spec.stage_names().join(", "),
            path.display(),
            if spec.skipped.is_empty() {
                String::new()
            } else {
                format!(
                    " (not {}: they do not change the waveform)",
                    spec.skipped.join(", ")
                )
            }
        );
        settings.push(Setting::chain(spec));
    }
    std::fs::create_dir_all(&args.out).map_err(|e| {
        Failure::job(format!(
            "cannot create output folder {}: {e}",
            args.out.display()
        ))
    })?;
    let machine = Machine::detect();
    eprintln!(
        "tradeoff: {} settings × {} pulse widths × {} families, {} pulses each, one thread \
         ({} cores, rates for {} worker(s))",
        settings.len(),
        config.widths_ns.len(),
        config.families.len(),
        pulses,
        machine.cores,
        machine.workers
    );
    let start = Instant::now();
    let stderr = std::io::stderr();
    let cases = run_sweep(&config, &settings, |p| {
        let _ = writeln!(
            stderr.lock(),
            "[{:>3}/{}] {:>5} ns {:<8} {:<24} RMSE {:.4}  {:>9.2} µs/pulse",
            p.done,
            p.total,
            p.case.width_ns,
            p.case.family.name(),
            p.setting.label(),
            p.case.rmse.rmse(),
            p.case.median_ns() / 1e3
        );
    })
    .map_err(Failure::job)?;
    let summary = summarise(&settings, &cases);

    let plot_name = "tradeoff.svg";
    let files = [
        ("tradeoff.csv", csv(&settings, &cases, machine.workers)),
        (
            "tradeoff_summary.csv",
            summary_csv(&settings, &summary, machine.workers),
        ),
        (
            "tradeoff.md",
            markdown(&config, &settings, &cases, &summary, &machine, plot_name),
        ),
        (plot_name, plot::svg(&settings, &summary, machine.workers)),
    ];
    for (name, text) in &files {
        let path = args.out.join(name);
        write_atomic(&path, text.as_bytes()).map_err(Failure::job)?;
    }
    let best = summary
        .iter()
        .filter(|s| s.pareto)
        .map(|s| {
            format!(
                "{} ({} max)",
                settings[s.setting].label(),
                report::rate(s.max_rate_hz(machine.workers))
            )
        })
        .collect::<Vec<_>>();
    eprintln!(
        "tradeoff: done in {:.1} s; Pareto front: {}; wrote {}/{{tradeoff.csv,tradeoff_summary.csv,tradeoff.md,tradeoff.svg}}",
        start.elapsed().as_secs_f64(),
        best.join(", "),
        args.out.display()
    );
    Ok(())
}
