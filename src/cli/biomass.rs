//! `fwlidar biomass`: biomass models from the per-pulse metrics (`docs/forest.md`, "Biomass").
//!
//! - `biomass truth --scene S --plots OUT.csv`: tiles the scene's `[[forest]]` stands into
//!   square plots and writes each plot's true above-ground woody biomass (Chave et al. 2014 on
//!   the scene's trees), in the CRS a replay of the scene's capture places its pulses in.
//! - `biomass fit --plots P.csv --metrics pulse_metrics.csv --out MODEL.json`: stepwise linear
//!   regression with leave-one-out and an optional hold-out ([`crate::forest::biomass`]).
//! - `biomass predict --model MODEL.json --metrics pulse_metrics.csv --out biomass.tif`: the
//!   model per raster cell, a Cloud-Optimized GeoTIFF.
//!
//! Every output is written complete or not at all (under `NAME.partial`, then renamed), only
//! after all input has been read and checked, and never over an existing file.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::cli::Failure;
use crate::forest::biomass::{
    self, BiomassModel, DEFAULT_COLUMNS, FitOptions, chave2014_agb_kg, holdout_by_fraction,
};
use crate::geo::crs::{OutputCrs, utm_epsg};
use crate::raster::{CogOptions, Raster, write_cog};
use crate::sim::world::flight::Frames;
use crate::sim::world::scene::WorldScene;

/// Nodata value of the biomass raster.
pub const NODATA: f32 = -9999.0;

/// Arguments of `fwlidar biomass`.
#[derive(Debug, clap::Args)]
pub struct BiomassArgs {
    /// What to do.
    #[command(subcommand)]
    pub command: BiomassCommand,
}

/// `fwlidar biomass` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum BiomassCommand {
    /// Tile a scene's [[forest]] stands into square plots and write each plot's true woody
    /// biomass (Chave et al. 2014 on the scene's trees), Mg/ha.
    Truth(TruthArgs),
    /// Fit a stepwise linear model of plot biomass on aggregated pulse metrics (BIC,
    /// leave-one-out, optional hold-out); write it as JSON.
    Fit(FitArgs),
    /// Apply a model per raster cell to pulse metrics; write a Cloud-Optimized GeoTIFF.
    Predict(PredictArgs),
}

/// Arguments of `fwlidar biomass truth`.
#[derive(Debug, clap::Args)]
pub struct TruthArgs {
    /// The described scene (TOML with [[forest]] stands).
    #[arg(long)]
    pub scene: PathBuf,
    /// The plot table to write (CSV: plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha,...).
    #[arg(long)]
    pub plots: PathBuf,
    /// Side of the square plots, metres; each stand is tiled from its south-west corner.
    #[arg(long, default_value_t = 30.0)]
    pub plot_size: f64,
    /// Wood density ρ for the allometry, g/cm³.
    #[arg(long, default_value_t = 0.6)]
    pub wood_density: f64,
    /// CRS of the plot coordinates (default: the WGS84 UTM zone of the scene's origin, the CRS
    /// a replay of its capture decides).
    #[arg(long)]
    pub epsg: Option<u32>,
    /// Override a scene key (as `simulate --set`), e.g. `forest[0].trees_per_ha=300`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
}

/// Arguments of `fwlidar biomass fit`.
#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// Plot table: plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha or
    /// plot_id,x,y,radius_m,biomass_mg_ha (coordinates in the metrics' CRS).
    #[arg(long)]
    pub plots: PathBuf,
    /// `pulse_metrics.csv` of `fwlidar replay`.
    #[arg(long)]
    pub metrics: PathBuf,
    /// The model to write (JSON).
    #[arg(long)]
    pub out: PathBuf,
    /// Hold out this fraction of the plots, evenly spread in file order (0.5: every second
    /// plot), and score the model on them.
    #[arg(long, conflicts_with = "train_ids")]
    pub holdout: Option<f64>,
    /// Fit on these plot ids only (comma-separated); the others are the hold-out.
    #[arg(long, value_delimiter = ',')]
    pub train_ids: Option<Vec<String>>,
    /// Candidate pulse-metric columns (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_COLUMNS.map(String::from))]
    pub columns: Vec<String>,
    /// Most predictors (default: a fifth of the training plots, at least 1).
    #[arg(long)]
    pub max_predictors: Option<usize>,
    /// Least pulses with metrics for a plot to enter the fit.
    #[arg(long, default_value_t = 10)]
    pub min_pulses: usize,
}

/// Arguments of `fwlidar biomass predict`.
#[derive(Debug, clap::Args)]
pub struct PredictArgs {
    /// The model written by `biomass fit`.
    #[arg(long)]
    pub model: PathBuf,
    /// `pulse_metrics.csv` of `fwlidar replay`.
    #[arg(long)]
    pub metrics: PathBuf,
    /// The raster to write (Cloud-Optimized GeoTIFF).
    #[arg(long)]
    pub out: PathBuf,
    /// Cell side, metres (best the plot size the model was fitted on).
    #[arg(long, default_value_t = 30.0)]
    pub cell: f64,
    /// EPSG code of the metrics' CRS (default: read from the summary.json beside the metrics).
    #[arg(long)]
    pub epsg: Option<u32>,
}

/// Runs `fwlidar biomass`.
pub fn run(args: BiomassArgs) -> Result<(), Failure> {
    match args.command {
        BiomassCommand::Truth(a) => truth(a),
        BiomassCommand::Fit(a) => fit(a),
        BiomassCommand::Predict(a) => predict(a),
    }
}

/// Refuses an output that exists (as `simulate`, `import` and `man` do).
fn refuse_existing(path: &Path) -> Result<(), Failure> {
    if path.exists() {
        return Err(Failure::job(format!(
            "{} exists; fwlidar biomass never writes over a file (remove it or choose another name)",
            path.display()
        )));
    }
    Ok(())
}

/// Writes `bytes` to `path` through `path.partial` and a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Failure> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, bytes)
        .and_then(|_| std::fs::rename(&tmp, path))
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            Failure::job(format!("{}: {e}", path.display()))
        })
}

fn truth(a: TruthArgs) -> Result<(), Failure> {
    refuse_existing(&a.plots)?;
    if !(a.plot_size.is_finite() && a.plot_size > 0.0) {
        return Err(Failure::usage(format!(
            "--plot-size must be a positive number of metres, got {}",
            a.plot_size
        )));
    }
    if !(a.wood_density.is_finite() && a.wood_density > 0.0) {
        return Err(Failure::usage(format!(
            "--wood-density must be positive (g/cm³), got {}",
            a.wood_density
        )));
    }
    let (scene, _) = WorldScene::load_with(&a.scene, &a.sets).map_err(Failure::usage)?;
    if scene.forest.is_empty() {
        return Err(Failure::usage(format!(
            "{}: no [[forest]] stand to tile into plots",
            a.scene.display()
        )));
    }
    let o = &scene.origin;
    let code = a.epsg.unwrap_or_else(|| utm_epsg(o.lat_deg, o.lon_deg));
    let crs = OutputCrs::from_epsg(code).map_err(|e| Failure::usage(format!("--epsg: {e}")))?;
    let frames = Frames::new(o.lat_deg, o.lon_deg, o.height_m);
    let mut trees = scene.tree.clone();
    for (i, f) in scene.forest.iter().enumerate() {
        trees.extend(f.trees(scene.seed, i));
    }
    let s = a.plot_size;
    let area_ha = s * s / 10_000.0;
    let mut csv = String::from(
        "plot_id,x_min,y_min,x_max,y_max,biomass_mg_ha,trees,stand,scene_x_min,scene_y_min\n",
    );
    let mut n = 0usize;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (i, f) in scene.forest.iter().enumerate() {
        let r = f.rectangle_m;
        let nx = ((r[2] - r[0]) / s + 1e-9).floor() as usize;
        let ny = ((r[3] - r[1]) / s + 1e-9).floor() as usize;
        for iy in 0..ny {
            for ix in 0..nx {
                let (x0, y0) = (r[0] + ix as f64 * s, r[1] + iy as f64 * s);
                let inside = |t: &&crate::sim::world::scene::Tree| {
                    let [x, y] = t.position_m;
                    x >= x0 && x < x0 + s && y >= y0 && y < y0 + s
                };
                let (count, kg) = trees.iter().filter(inside).fold((0, 0.0), |(c, kg), t| {
                    let dbh_cm = 2.0 * t.stem_radius_m * 100.0;
                    (
                        c + 1,
                        kg + chave2014_agb_kg(a.wood_density, dbh_cm, t.height_m),
                    )
                });
                let mg_ha = kg / 1000.0 / area_ha;
                let g = frames.geodetic([x0 + s / 2.0, y0 + s / 2.0, 0.0]);
                let [cx, cy, _] = crs
                    .project(g.lat_deg, g.lon_deg, g.height_m)
                    .map_err(Failure::job)?;
                let h = s / 2.0;
                let _ = writeln!(
                    csv,
                    "s{i:02}_{ix}_{iy},{:.3},{:.3},{:.3},{:.3},{mg_ha:.3},{count},{i},{x0},{y0}",
                    cx - h,
                    cy - h,
                    cx + h,
                    cy + h
                );
                n += 1;
                lo = lo.min(mg_ha);
                hi = hi.max(mg_ha);
            }
        }
    }
    if n == 0 {
        return Err(Failure::usage(format!(
            "{}: no stand holds a whole {s} m plot (use a smaller --plot-size)",
            a.scene.display()
        )));
    }
    write_atomic(&a.plots, csv.as_bytes())?;
    println!(
        "wrote {}: {n} plots of {s} m in EPSG:{code}, true biomass {lo:.1}..{hi:.1} Mg/ha \
         (Chave et al. 2014, wood density {} g/cm³)",
        a.plots.display(),
        a.wood_density
    );
    Ok(())
}

fn fit(a: FitArgs) -> Result<(), Failure> {
    refuse_existing(&a.out)?;
    if let Some(f) = a.holdout
        && !(f.is_finite() && (0.0..1.0).contains(&f))
    {
        return Err(Failure::usage(format!(
            "--holdout must be a fraction in [0, 1), got {f}"
        )));
    }
    if a.columns.is_empty() {
        return Err(Failure::usage("--columns: name at least one metric column"));
    }
    let plots = biomass::read_plots(&a.plots).map_err(Failure::job)?;
    let holdout = match (&a.train_ids, a.holdout) {
        (Some(ids), _) => {
            for id in ids {
                if !plots.iter().any(|p| p.id == *id) {
                    return Err(Failure::usage(format!(
                        "--train-ids: no plot {id:?} in {}",
                        a.plots.display()
                    )));
                }
            }
            plots.iter().map(|p| !ids.contains(&p.id)).collect()
        }
        (None, Some(f)) => holdout_by_fraction(plots.len(), f),
        (None, None) => vec![false; plots.len()],
    };
    let table = biomass::read_pulse_metrics(&a.metrics, &a.columns).map_err(Failure::job)?;
    let opt = FitOptions {
        columns: a.columns.clone(),
        max_predictors: a.max_predictors,
        min_pulses: a.min_pulses,
        holdout,
    };
    let model = biomass::fit(&plots, &table, &opt).map_err(Failure::job)?;
    let json = serde_json::to_string_pretty(&model)
        .map_err(|e| Failure::job(format!("cannot encode the model: {e}")))?;
    write_atomic(&a.out, json.as_bytes())?;
    print_model(&model, &a.out);
    Ok(())
}

fn print_model(m: &BiomassModel, out: &Path) {
    let excluded = m.plots.iter().filter(|p| p.set == "excluded").count();
    println!(
        "biomass model -> {}  ({} training plots, {} held out, {} excluded: fewer than {} pulses)",
        out.display(),
        m.fit.plots,
        m.holdout.map_or(0, |h| h.plots),
        excluded,
        m.min_pulses
    );
    let mut eq = format!("  biomass_mg_ha = {:.3}", m.intercept);
    for p in &m.predictors {
        let _ = write!(eq, " {:+.4} × {}", p.coefficient, p.name);
    }
    println!("{eq}");
    println!(
        "  selection: stepwise by {} (at most {} predictors), {} steps",
        m.criterion,
        m.max_predictors,
        m.steps.len()
    );
    println!(
        "  fit:       R² {:.3}  adj. R² {:.3}  RMSE {:.1} Mg/ha",
        m.fit.r2, m.fit.adj_r2, m.fit.rmse
    );
    println!(
        "  LOO:       R² {:.3}  RMSE {:.1} Mg/ha (selection repeated in each fold)",
        m.fit.loo_r2, m.fit.loo_rmse
    );
    if let Some(h) = m.holdout {
        println!(
            "  hold-out:  R² {:.3}  RMSE {:.1} Mg/ha on {} plots",
            h.r2, h.rmse, h.plots
        );
    }
}

/// The EPSG code of the metrics' CRS from the replay's `summary.json` beside them.
fn epsg_from_summary(metrics: &Path) -> Option<u32> {
    let dir = metrics.parent()?;
    let text = std::fs::read_to_string(dir.join("summary.json")).ok()?;
    let v: SummaryCrs = serde_json::from_str(&text).ok()?;
    v.sinks.metrics_rasters.epsg.or_else(|| {
        v.source
            .georeference
            .output_crs
            .as_deref()
            .and_then(crate::geo::crs::epsg_of)
    })
}

/// What a replay's `summary.json` says of the output CRS: the metrics rasters' EPSG code, or
/// the georeferencing's output CRS.
#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct SummaryCrs {
    sinks: SummarySinks,
    source: SummarySource,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct SummarySinks {
    metrics_rasters: SummaryRasters,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct SummaryRasters {
    epsg: Option<u32>,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct SummarySource {
    georeference: SummaryGeoreference,
}

#[derive(Default, serde::Deserialize)]
#[serde(default)]
struct SummaryGeoreference {
    output_crs: Option<String>,
}

fn predict(a: PredictArgs) -> Result<(), Failure> {
    if !(a.cell.is_finite() && a.cell > 0.0) {
        return Err(Failure::usage(format!(
            "--cell must be a positive number of metres, got {}",
            a.cell
        )));
    }
    refuse_existing(&a.out)?;
    let model = BiomassModel::read(&a.model).map_err(Failure::job)?;
    let code = match a.epsg.or_else(|| epsg_from_summary(&a.metrics)) {
        Some(c) => c,
        None => {
            return Err(Failure::usage(format!(
                "{}: no CRS known for these metrics (no summary.json beside them naming one); \
                 give --epsg CODE",
                a.metrics.display()
            )));
        }
    };
    OutputCrs::from_epsg(code).map_err(|e| Failure::usage(format!("--epsg: {e}")))?;
    let terms = model.terms();
    let mut columns: Vec<String> = Vec::new();
    for t in &terms {
        if !columns.contains(&t.column) {
            columns.push(t.column.clone());
        }
    }
    let table = biomass::read_pulse_metrics(&a.metrics, &columns).map_err(Failure::job)?;
    let (cells, b) = biomass::cells_of(&table, a.cell);
    let width = (b[2] - b[0] + 1) as usize;
    let height = (b[3] - b[1] + 1) as usize;
    if width.max(height) > crate::raster::MAX_DIMENSION / 16 {
        return Err(Failure::usage(format!(
            "{}: the pulses span {width} × {height} cells of {} m; use a larger --cell",
            a.metrics.display(),
            a.cell
        )));
    }
    let mut bio = vec![NODATA; width * height];
    let mut count = vec![NODATA; width * height];
    let (mut predicted, mut clamped) = (0usize, 0usize);
    for (&(cx, cy), idx) in &cells {
        let k = (b[3] - cy) as usize * width + (cx - b[0]) as usize;
        count[k] = idx.len() as f32;
        if let Some(v) = biomass::term_values(&table, idx, &terms, model.min_pulses) {
            let p = model.predict(&v);
            if p < 0.0 {
                clamped += 1;
            }
            bio[k] = p.max(0.0) as f32;
            predicted += 1;
        }
    }
    let mut r = Raster::new(
        width,
        height,
        b[0] as f64 * a.cell,
        (b[3] + 1) as f64 * a.cell,
        a.cell,
        code,
        NODATA,
    );
    r.push_band("biomass", "Mg/ha", bio);
    r.push_band("pulses", "1", count);
    write_cog(&a.out, &r, &CogOptions::default()).map_err(Failure::job)?;
    println!(
        "wrote {}: {width} × {height} cells of {} m (EPSG:{code}), {predicted} predicted, {} with \
         fewer than {} pulses left nodata, {clamped} negative predictions set to 0",
        a.out.display(),
        a.cell,
        cells.len() - predicted,
        model.min_pulses
    );
    Ok(())
}
