//! `fwlidar merge STORE... --out STORE`: combines voxel stores of several flights or replays.
//!
//! The stores must share their grid (voxel size, tile-grid anchor, height range and mode, tile
//! size, intensity quantum), CRS and intensity units; their extents may differ and the result
//! covers them all. A tile present in several stores is the sum of their counts and intensity
//! sums (integers of the quantum, so exact) and the larger of their maxima: the result does not
//! depend on the order the stores are named in, bit for bit. The result's arrays span the
//! bounding box of its tiles (`ZarrStore::fit`). The output must not exist.

use std::path::PathBuf;

use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::Failure;
use crate::voxel::tile::TileData;
use crate::voxel::zarr::{StoreInfo, ZarrStore};

/// Arguments of `fwlidar merge`.
#[derive(Debug, clap::Args)]
pub struct MergeArgs {
    /// Voxel stores (`voxels.zarr` folders) to combine.
    #[arg(required = true, num_args = 1..)]
    pub stores: Vec<PathBuf>,
    /// The combined store to write (must not exist).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Do not draw a progress bar.
    #[arg(long)]
    pub no_progress: bool,
}

/// Runs `fwlidar merge`.
pub fn run(args: MergeArgs) -> Result<(), Failure> {
    if args.out.exists() {
        return Err(Failure::usage(format!(
            "{} exists; merge writes a new store and never overwrites one",
            args.out.display()
        )));
    }
    // A fixed order (by path) for everything that is not commutative: attributes, file order.
    let mut paths = args.stores.clone();
    paths.sort();
    paths.dedup();
    let mut stores = Vec::with_capacity(paths.len());
    for p in &paths {
        stores.push(ZarrStore::open(p).map_err(Failure::job)?);
    }
    let first = &stores[0];
    let mut grid = first.grid().clone();
    for (s, p) in stores.iter().zip(&paths).skip(1) {
        grid.compatible(s.grid()).map_err(|why| {
            Failure::job(format!(
                "{} and {} cannot be merged: {why}",
                paths[0].display(),
                p.display()
            ))
        })?;
        if s.info().epsg != first.info().epsg || s.info().crs_wkt != first.info().crs_wkt {
            return Err(Failure::job(format!(
                "{} and {} cannot be merged: their CRS differ (EPSG {:?} and {:?})",
                paths[0].display(),
                p.display(),
                first.info().epsg,
                s.info().epsg
            )));
        }
        if s.info().intensity_units != first.info().intensity_units {
            return Err(Failure::job(format!(
                "{} and {} cannot be merged: intensities in {:?} and {:?}",
                paths[0].display(),
                p.display(),
                first.info().intensity_units,
                s.info().intensity_units
            )));
        }
        grid = grid.union(s.grid());
    }
    let names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
    let info = StoreInfo {
        crs_wkt: first.info().crs_wkt.clone(),
        epsg: first.info().epsg,
        intensity_units: first.info().intensity_units.clone(),
        run_key: format!("merged from {}", names.join(", ")),
        configuration: stores
            .iter()
            .zip(&names)
            .map(|(s, n)| format!("# {n}\n{}", s.info().configuration))
            .collect::<Vec<_>>()
            .join("\n"),
    };
    let mut tiles: Vec<[i64; 2]> = stores.iter().flat_map(|s| s.tiles()).collect();
    tiles.sort();
    tiles.dedup();
    let mut out = ZarrStore::create_or_open(&args.out, grid.clone(), info).map_err(Failure::job)?;
    let bar = (!args.no_progress).then(|| {
        let bar = ProgressBar::new(tiles.len() as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    });
    let (mut acc, mut part) = (TileData::for_grid(&grid), TileData::for_grid(&grid));
    let mut merged_from_several = 0u64;
    for &t in &tiles {
        acc.clear();
        let mut holders = 0;
        for s in stores.iter_mut() {
            if s.read_tile(t, &mut part).map_err(Failure::job)? {
                acc.merge(&part);
                holders += 1;
            }
        }
        if holders > 1 {
            merged_from_several += 1;
        }
        // A merged store is not resumed: its tiles carry watermark 0.
        out.write_tile(t, &acc, 0).map_err(Failure::job)?;
        if let Some(b) = &bar {
            b.inc(1);
        }
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    // The arrays span the bounding box of the tiles, whatever the inputs' extents.
    out.fit().map_err(Failure::job)?;
    let span = *out.span();
    println!(
        "merged {} stores into {}: {} tiles ({} present in more than one), arrays of {} × {} \
         tiles of {} columns × {} levels",
        stores.len(),
        args.out.display(),
        tiles.len(),
        merged_from_several,
        span.tiles[0],
        span.tiles[1],
        grid.tile_columns,
        grid.levels
    );
    Ok(())
}
