//! `fwlidar trees INPUT --out DIR`: stems and first-order branches as cylinders from waveform
//! points (`crate::trees`, `docs/trees.md`).
//!
//! INPUT is a hyper point cloud (`hyper_points.las`, or a replay's output folder holding one),
//! or anything `replay` reads (a capture, LAS/LAZ or PulseWaves waveforms, a GEDI granule): that
//! is first replayed into `DIR/replay/` with `output.hyper_points = true` and the other outputs
//! off. A non-empty DIR is refused unless `--force`, which replaces only these products.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::cli::Failure;
use crate::trees::output::write_all;
use crate::trees::points::read_hyper_points;
use crate::trees::score::{Score, read_truth_branches, read_truth_trees, score};
use crate::trees::{Reconstruction, Threshold, TreesOptions, reconstruct};

/// Which processed waveform the points come from when INPUT is replayed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum WaveformChoice {
    /// As the run configuration says (the embedded default deconvolves by Richardson-Lucy).
    Deconvolved,
    /// The configuration's `deconvolve` stages left out: denoised only.
    Raw,
}

/// Arguments of `fwlidar trees`.
#[derive(Debug, clap::Args)]
pub struct TreesArgs {
    /// `hyper_points.las`, a replay output folder holding one, or a capture (or other waveform
    /// file `replay` reads) to replay first.
    pub input: PathBuf,
    /// Output folder (created if missing; must be empty unless --force).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Run configuration for the replay of a capture (default: the embedded one).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Change a key of the run configuration, e.g. `--set 'pipeline.stages[1].method.iterations=50'`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Points from the deconvolved or the raw (denoised) waveforms, when INPUT is replayed.
    #[arg(long, value_enum, default_value = "deconvolved")]
    pub waveform: WaveformChoice,
    /// Floor of the replay's hyper point cloud, V: samples below it are not written.
    #[arg(long, default_value_t = 0.002)]
    pub floor_v: f32,
    /// Intensity threshold: `auto` (the most branch-sized clusters, from a scan) or volts.
    #[arg(long, default_value = "auto")]
    pub threshold: String,
    /// DBSCAN radius, m (default 1.5 × the beam spacing, at least 0.3 m).
    #[arg(long)]
    pub eps_m: Option<f64>,
    /// DBSCAN core size (default 5).
    #[arg(long)]
    pub min_points: Option<usize>,
    /// Least points of a branch cluster.
    #[arg(long, default_value_t = 8)]
    pub min_branch_points: usize,
    /// Stem positions instead of finding trees: a CSV with columns `x` and `y` (e.g. the
    /// simulator's `<stem>.trees.csv`).
    #[arg(long)]
    pub stems: Option<PathBuf>,
    /// Score against the simulator's truth: `<stem>.branches.csv` (its `<stem>.trees.csv` is
    /// read from beside it).
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Leave out the foliage filter (local point geometry).
    #[arg(long)]
    pub no_foliage_filter: bool,
    /// Replace the products of an earlier run in a non-empty --out.
    #[arg(long)]
    pub force: bool,
}

/// The products `fwlidar trees` writes into its folder.
pub const PRODUCTS: [&str; 9] = [
    "cylinders.csv",
    "trees.svg",
    "cylinders.ply",
    "clustered_points.las",
    "threshold.csv",
    "threshold.svg",
    "scores.csv",
    "trees.json",
    "replay",
];

fn is_hyper_las(path: &Path) -> bool {
    let mut head = [0u8; 105];
    std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok()
        && &head[..4] == b"LASF"
        && (6..=8).contains(&(head[104] & 0x3f))
}

/// The stem positions of a CSV with `x` and `y` columns.
fn read_stems(path: &Path) -> Result<Vec<[f64; 2]>, Failure> {
    read_truth_trees(path)
        .map(|t| t.into_iter().map(|t| t.xy).collect())
        .or_else(|_| {
            let text = std::fs::read_to_string(path)
                .map_err(|e| Failure::usage(format!("{}: {e}", path.display())))?;
            let mut lines = text.lines();
            let head: Vec<&str> = lines
                .next()
                .unwrap_or("")
                .split(',')
                .map(str::trim)
                .collect();
            let (Some(xi), Some(yi)) = (
                head.iter().position(|h| *h == "x"),
                head.iter().position(|h| *h == "y"),
            ) else {
                return Err(Failure::usage(format!(
                    "{}: no columns \"x\" and \"y\"",
                    path.display()
                )));
            };
            lines
                .enumerate()
                .filter(|(_, l)| !l.trim().is_empty())
                .map(|(r, l)| {
                    let f: Vec<&str> = l.split(',').map(str::trim).collect();
                    let g = |i: usize, n: &str| {
                        f.get(i)
                            .and_then(|v| v.parse::<f64>().ok())
                            .filter(|v| v.is_finite())
                            .ok_or_else(|| {
                                Failure::usage(format!(
                                    "{}: row {}: \"{n}\" is not a number",
                                    path.display(),
                                    r + 2
                                ))
                            })
                    };
                    Ok([g(xi, "x")?, g(yi, "y")?])
                })
                .collect()
        })
}

/// `<stem>.trees.csv` beside `<stem>.branches.csv`.
pub fn trees_beside(branches: &Path) -> PathBuf {
    let name = branches
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_default();
    let stem = name.strip_suffix(".branches.csv").unwrap_or(&name);
    branches.with_file_name(format!("{stem}.trees.csv"))
}

/// FWHM of the first outgoing pulse of `path` and its sample interval (ns), `None` when no
/// pulse has one.
pub fn first_outgoing_fwhm_ns(path: &Path) -> Option<(f64, f64)> {
    use crate::pipeline::ports::SourceEvent;
    let mut source = crate::source::open_file(path).ok()?;
    let pool = crate::pulse::PulsePool::new(4);
    for _ in 0..10_000 {
        match source.next(&pool).ok()? {
            SourceEvent::Pulse(p) => {
                if let Some(k) = p.outgoing() {
                    let seg = &p.segments[k];
                    let (a, n) = (seg.first as usize, seg.len as usize);
                    let raw = p.raw.get(a..a + n)?;
                    return fwhm_samples(raw).map(|w| (w * p.sample_ns, p.sample_ns));
                }
            }
            SourceEvent::End => return None,
            _ => {}
        }
    }
    None
}

/// Full width at half maximum of a short pulse above its smallest sample, samples (linear
/// interpolation at the half-maximum crossings; the ends count as crossings).
pub fn fwhm_samples(x: &[u16]) -> Option<f64> {
    let base = f64::from(*x.iter().min()?);
    let (k, peak) = x
        .iter()
        .enumerate()
        .max_by_key(|(_, v)| **v)
        .map(|(i, v)| (i, f64::from(*v)))?;
    if peak <= base {
        return None;
    }
    let half = base + (peak - base) / 2.0;
    let v = |i: usize| f64::from(x[i]);
    let mut l = k;
    while l > 0 && v(l - 1) > half {
        l -= 1;
    }
    let mut r = k;
    while r + 1 < x.len() && v(r + 1) > half {
        r += 1;
    }
    let left = if l > 0 {
        l as f64 - (v(l) - half) / (v(l) - v(l - 1))
    } else {
        0.0
    };
    let right = if r + 1 < x.len() {
        r as f64 + (v(r) - half) / (v(r) - v(r + 1))
    } else {
        r as f64
    };
    Some(right - left)
}

/// The low-pass cut-off that keeps a Gaussian pulse of FWHM `fwhm_ns`: where its spectrum has
/// fallen to 1 % of its peak, `√(ln 100 / 2π²) / σ` = 1.14 / FWHM (GHz). A cut-off below it rings
/// (Gibbs) at its own period, and the rings above the ground echo become points.
pub fn pulse_cutoff_ghz(fwhm_ns: f64) -> f64 {
    let sigma = fwhm_ns / (8.0 * std::f64::consts::LN_2).sqrt();
    (100f64.ln() / (2.0 * std::f64::consts::PI.powi(2))).sqrt() / sigma
}

/// Replays `input` into `dir` with the hyper point cloud on; returns its path.
fn replay_points(args: &TreesArgs, dir: &Path) -> Result<PathBuf, Failure> {
    use crate::stages::StageConfig;
    let mut config = crate::config::load_run_config_with(args.config.as_deref(), &args.sets)
        .map_err(Failure::usage)?;
    if !(args.floor_v.is_finite() && args.floor_v > 0.0) {
        return Err(Failure::usage(format!(
            "--floor-v must be a positive number of volts, got {}",
            args.floor_v
        )));
    }
    config.output.hyper_points = true;
    config.output.hyper_threshold_v = Some(args.floor_v);
    config.output.waveforms = false;
    config.output.las = false;
    config.output.returns = false;
    config.output.metrics = false;
    config.output.rasters = false;
    config.voxels.enabled = false;
    config
        .pipeline
        .stages
        .retain(|s| !matches!(s, StageConfig::Metrics(_)));
    // A denoise cut-off below the pulse's own band rings: raise it to the pulse's, unless set.
    if !args.sets.iter().any(|s| s.contains("cutoff_ghz"))
        && let Some((w, sample_ns)) = first_outgoing_fwhm_ns(&args.input)
    {
        // Not at or above Nyquist (the stage drops such pulses): just below it, the filter
        // passes the pulse whole.
        let want = pulse_cutoff_ghz(w).min(0.95 * 0.5 / sample_ns);
        for st in &mut config.pipeline.stages {
            if let StageConfig::Denoise(d) = st
                && d.cutoff_ghz < want
            {
                eprintln!(
                    "denoise cut-off raised from {} to {want:.3} GHz for the {w:.2} ns outgoing \
                     pulse (set `pipeline.stages[i].cutoff_ghz` to choose)",
                    d.cutoff_ghz
                );
                d.cutoff_ghz = want;
            }
        }
    }
    if args.waveform == WaveformChoice::Raw {
        config
            .pipeline
            .stages
            .retain(|s| !matches!(s, StageConfig::Deconvolve(_)));
    }
    eprintln!(
        "replaying {} into {} (hyper points above {} V, {} waveforms)",
        args.input.display(),
        dir.display(),
        args.floor_v,
        match args.waveform {
            WaveformChoice::Raw => "raw",
            WaveformChoice::Deconvolved => "deconvolved",
        }
    );
    let report = crate::cli::replay::replay_quiet(&args.input, dir, &config, None)?;
    if let Some(e) = report.fatal.as_ref() {
        return Err(Failure::job(format!(
            "replay of {}: {e}",
            args.input.display()
        )));
    }
    Ok(dir.join(crate::sink::hyper_points::FILE_NAME))
}

/// The process's peak resident memory (`VmHWM` of `/proc/self/status`), MB; `None` where
/// there is no such file.
fn peak_rss_mb() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// Runs `fwlidar trees`.
pub fn run(args: TreesArgs) -> Result<(), Failure> {
    let started = Instant::now();
    let threshold = parse_threshold(&args.threshold)?;
    check_input_and_out(&args)?;
    // Truth and stems read before the long part, so a typo fails fast.
    let truth = match &args.truth {
        Some(b) => {
            let trees = read_truth_trees(&trees_beside(b)).map_err(Failure::usage)?;
            let branches = read_truth_branches(b).map_err(Failure::usage)?;
            Some((trees, branches))
        }
        None => None,
    };
    let stems = args.stems.as_deref().map(read_stems).transpose()?;
    let las = points_file(&args)?;
    let t_read = Instant::now();
    let set = read_hyper_points(&las).map_err(Failure::job)?;
    eprintln!("{}: {} points", las.display(), set.points.len());
    let opts = TreesOptions {
        threshold,
        eps_m: args.eps_m,
        min_points: args.min_points,
        stems,
        min_branch_points: args.min_branch_points,
        foliage_radius_m: if args.no_foliage_filter {
            0.0
        } else {
            TreesOptions::default().foliage_radius_m
        },
        ..TreesOptions::default()
    };
    let t_rec = Instant::now();
    let r = reconstruct(&set.points, &opts).map_err(Failure::job)?;
    let rec_s = t_rec.elapsed().as_secs_f64();
    let sc = truth.as_ref().map(|(t, b)| score(&r, t, b));
    write_all(
        &args.out,
        &set.points,
        set.crs_wkt.as_deref(),
        &r,
        sc.as_ref(),
        truth.as_ref().map(|(_, b)| b.as_slice()),
    )
    .map_err(Failure::job)?;
    let seconds = Seconds {
        total: started.elapsed().as_secs_f64(),
        read: t_rec.duration_since(t_read).as_secs_f64(),
        reconstruct: rec_s,
        per_tree: if r.trees.is_empty() {
            f64::NAN
        } else {
            rec_s / r.trees.len() as f64
        },
    };
    write_trees_json(&args, &las, &r, sc.as_ref(), seconds)?;
    print_outcome(&args, &r, sc.as_ref());
    Ok(())
}

/// `--threshold`: `auto`, or volts.
fn parse_threshold(text: &str) -> Result<Threshold, Failure> {
    match text {
        "auto" => Ok(Threshold::Auto),
        v => match v.parse::<f32>() {
            Ok(t) if t.is_finite() && t >= 0.0 => Ok(Threshold::Fixed(t)),
            _ => Err(Failure::usage(format!(
                "--threshold must be \"auto\" or a number of volts ≥ 0, got {v:?}"
            ))),
        },
    }
}

/// The input exists; the output folder is empty (or `--force`) and is created.
fn check_input_and_out(args: &TreesArgs) -> Result<(), Failure> {
    if !args.input.exists() {
        return Err(Failure::usage(format!(
            "{}: no such file or folder",
            args.input.display()
        )));
    }
    if args.out.exists() && !args.force {
        let busy = std::fs::read_dir(&args.out)
            .map(|mut d| d.next().is_some())
            .unwrap_or(true);
        if busy {
            return Err(Failure::usage(format!(
                "{}: not empty; --force replaces the products of an earlier `fwlidar trees` \
                 ({})",
                args.out.display(),
                PRODUCTS.join(", ")
            )));
        }
    }
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::job(format!("cannot create {}: {e}", args.out.display())))
}

/// The hyper point cloud to reconstruct from: the input's, a replay folder's, or one replayed
/// from the input now (into `OUT/replay`).
fn points_file(args: &TreesArgs) -> Result<PathBuf, Failure> {
    Ok(if args.input.is_dir() {
        let p = args.input.join(crate::sink::hyper_points::FILE_NAME);
        if !p.exists() {
            return Err(Failure::usage(format!(
                "{}: no {} in this folder (replay with `--set output.hyper_points=true --set \
                 output.hyper_threshold_v=0.002`)",
                args.input.display(),
                crate::sink::hyper_points::FILE_NAME
            )));
        }
        p
    } else if is_hyper_las(&args.input) {
        args.input.clone()
    } else {
        let dir = args.out.join("replay");
        if dir.exists() {
            std::fs::remove_dir_all(&dir)
                .map_err(|e| Failure::job(format!("cannot clear {}: {e}", dir.display())))?;
        }
        replay_points(args, &dir)?
    })
}

/// Seconds taken, for `trees.json`.
#[derive(serde::Serialize)]
struct Seconds {
    total: f64,
    read: f64,
    reconstruct: f64,
    per_tree: f64,
}

/// `trees.json`: the input, the points file, the waveform, the reconstruction, its scores, the
/// seconds taken and the peak memory (keys in sorted order, through a JSON value).
fn write_trees_json(
    args: &TreesArgs,
    las: &Path,
    r: &Reconstruction,
    sc: Option<&Score>,
    seconds: Seconds,
) -> Result<(), Failure> {
    let summary = serde_json::json!({
        "input": args.input.display().to_string(),
        "points_file": las.display().to_string(),
        "waveform": format!("{:?}", args.waveform).to_lowercase(),
        "reconstruction": r,
        "score": sc.map(|s| &s.summary),
        "tree_scores": sc.map(|s| &s.trees),
        "seconds": seconds,
        "peak_memory_mb": peak_rss_mb(),
    });
    let path = args.out.join("trees.json");
    std::fs::write(
        &path,
        serde_json::to_string_pretty(&summary).unwrap_or_default() + "\n",
    )
    .map_err(|e| Failure::job(format!("cannot write {}: {e}", path.display())))
}

/// The trees, branches and threshold found, the scores against the truth, the files written.
fn print_outcome(args: &TreesArgs, r: &Reconstruction, sc: Option<&Score>) {
    let branches: usize = r.trees.iter().map(|t| t.cylinders.len() - 1).sum();
    println!(
        "{} trees, {} branches from {} points (threshold {:.4} V: {}); foliage removed {}; \
         DBSCAN eps {:.2} m, min {} points",
        r.trees.len(),
        branches,
        r.input_points,
        r.threshold.chosen_v,
        if r.threshold.curve.is_empty() {
            "given"
        } else {
            "chosen from threshold.svg"
        },
        r.foliage_points,
        r.eps_m,
        r.min_points
    );
    if let Some(s) = sc {
        let m = &s.summary;
        println!(
            "truth: {}/{} trees; branches > 1 m found {}/{} ({:.0} %), {} extra; median |error|: \
             azimuth {:.1}°, zenith {:.1}°, length {:.0} %, base {:.2} m; stem position {:.2} m, \
             height {:.2} m",
            m.trees_found,
            m.trees,
            m.branches_found,
            m.branches,
            100.0 * m.found_fraction,
            m.extra_branches,
            m.azimuth_err_deg,
            m.zenith_err_deg,
            100.0 * m.length_err_rel,
            m.base_err_m,
            m.stem_position_err_m,
            m.height_err_m
        );
    }
    println!(
        "wrote {} (cylinders.csv, cylinders.ply, clustered_points.las, trees.svg, threshold.svg{})",
        args.out.display(),
        if sc.is_some() { ", scores.csv" } else { "" }
    );
}
