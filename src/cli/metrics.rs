//! `fwlidar metrics STORE --out DIR`: forest structure rasters recomputed from a voxel store
//! after the flight (`crate::forest::store_metrics`): `DIR/chm.vrt` and `DIR/metrics.vrt` over
//! Cloud-Optimized GeoTIFF tiles, as a replay's `rasters/`, and `DIR/metrics.json` (what was
//! done). A non-empty `DIR` is refused unless `--force`, which replaces only these products.

use std::path::PathBuf;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::forest::store_metrics::{
    DEFAULT_NOISE_FLOOR, DEFAULT_SMOOTHING_NS, StoreMetricsError, StoreMetricsOptions,
    compute_store_metrics, product_paths,
};

/// Arguments of `fwlidar metrics`.
#[derive(Debug, clap::Args)]
pub struct MetricsArgs {
    /// Voxel store (the `voxels.zarr` folder a replay or the daemon wrote, or a merged one).
    pub store: PathBuf,
    /// Output folder (created if missing; must be empty unless --force).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Cell of the canopy height model, m (default: the store's voxel column).
    #[arg(long)]
    pub cell: Option<f64>,
    /// Cell of metrics.vrt (RH, cover, PAI, FHD, ground, pulse density), m (default: --cell).
    #[arg(long)]
    pub profile_cell: Option<f64>,
    /// σ of the Gaussian smoothing of each cell's profile, ns of two-way time (0.15 m per ns).
    #[arg(long, default_value_t = DEFAULT_SMOOTHING_NS)]
    pub smoothing_ns: f64,
    /// Least noise σ of a cell's profile, fraction of its peak (signal start at 3 σ, modes
    /// from 6 σ).
    #[arg(long, default_value_t = DEFAULT_NOISE_FLOOR)]
    pub noise_floor: f64,
    /// Leave cells crossed by fewer pulses as nodata.
    #[arg(long, default_value_t = 1)]
    pub min_pulses: u64,
    /// Replace the products of an earlier `fwlidar metrics` in a non-empty output folder.
    #[arg(long)]
    pub force: bool,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
}

/// Runs `fwlidar metrics`.
pub fn run(args: MetricsArgs) -> Result<(), Failure> {
    let out = &args.out;
    if out.exists() && !out.is_dir() {
        return Err(Failure::usage(format!(
            "output folder {} exists and is not a folder",
            out.display()
        )));
    }
    let non_empty = out.is_dir()
        && std::fs::read_dir(out)
            .map_err(|e| Failure::job(format!("{}: {e}", out.display())))?
            .next()
            .is_some();
    if non_empty && !args.force {
        return Err(Failure::usage(format!(
            "output folder {} is not empty; choose another or add --force to replace its rasters",
            out.display()
        )));
    }
    let opts = StoreMetricsOptions {
        cell_m: args.cell,
        profile_cell_m: args.profile_cell,
        smoothing_ns: args.smoothing_ns,
        min_pulses: args.min_pulses,
        noise_floor: args.noise_floor,
    };
    // Fail on the options and the store before touching the output folder.
    crate::forest::store_metrics::check_options(&opts).map_err(Failure::usage)?;
    if !args.store.join("zarr.json").is_file() {
        return Err(Failure::job(StoreMetricsError::Unusable {
            path: args.store.display().to_string(),
            what: if args.store.exists() {
                "no zarr.json: not a voxel store (give the voxels.zarr folder a replay wrote)"
                    .into()
            } else {
                "does not exist".into()
            },
        }));
    }
    if non_empty {
        for p in product_paths(out) {
            let r = if p.is_dir() {
                std::fs::remove_dir_all(&p)
            } else if p.exists() {
                std::fs::remove_file(&p)
            } else {
                Ok(())
            };
            r.map_err(|e| Failure::job(format!("cannot replace {}: {e}", p.display())))?;
        }
    }
    std::fs::create_dir_all(out).map_err(|e| {
        Failure::job(format!(
            "cannot create output folder {}: {e}",
            out.display()
        ))
    })?;
    let bar = (!args.no_progress).then(|| {
        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles ({eta})",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    });
    let start = Instant::now();
    let mut progress = |done: u64, total: u64| {
        if let Some(b) = &bar {
            b.set_length(total);
            b.set_position(done);
        }
    };
    let result = compute_store_metrics(&args.store, out, &opts, &mut progress);
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    let report = result.map_err(|e| match e {
        StoreMetricsError::Option { .. } => Failure::usage(e),
        _ => Failure::job(e),
    })?;
    let secs = start.elapsed().as_secs_f64();
    let json = crate::forest::store_metrics::metrics_json(&report, &args.store, secs);
    let jpath = out.join("metrics.json");
    let text = serde_json::to_string_pretty(&json).unwrap_or_default();
    std::fs::write(&jpath, text + "\n")
        .map_err(|e| Failure::job(format!("{}: {e}", jpath.display())))?;
    println!(
        "fwlidar metrics  {}  ->  {}",
        args.store.display(),
        out.display()
    );
    println!(
        "  {} tiles, {} voxel columns read; EPSG:{}; settings from the {}",
        report.tiles_read, report.columns, report.epsg, report.settings_from
    );
    println!(
        "  chm.vrt: {} of {} cells of {} m with a canopy height ({} tiles)",
        report.cells_ok[0], report.cells[0], report.cell_m, report.raster_tiles[0]
    );
    println!(
        "  metrics.vrt: {} of {} cells of {} m with metrics ({} tiles)",
        report.cells_ok[1], report.cells[1], report.profile_cell_m, report.raster_tiles[1]
    );
    if !report.cells_without.is_empty() || report.cells_few_pulses > 0 {
        let why: Vec<String> = report
            .cells_without
            .iter()
            .map(|(k, v)| format!("{v} {k}"))
            .collect();
        println!(
            "  without metrics: {}{} below --min-pulses",
            if why.is_empty() {
                String::new()
            } else {
                format!("{}, ", why.join(", "))
            },
            report.cells_few_pulses
        );
    }
    println!("  {secs:.2} s; report in {}", jpath.display());
    Ok(())
}
