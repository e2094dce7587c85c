//! `fwlidar merge STORE... --out STORE`: combines voxel stores of several flights or replays
//! (`crate::voxel::merge`).
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
use crate::voxel::merge::{MergeMeta, merge_stores};

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
    let bar = (!args.no_progress).then(|| {
        let bar = ProgressBar::new(0);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    });
    let s = merge_stores(&args.stores, &args.out, &MergeMeta::FromInputs, |k, n| {
        if let Some(b) = &bar {
            b.set_length(n as u64);
            b.set_position(k as u64);
        }
    })
    .map_err(|e| {
        if args.out.exists() && e.ends_with("never overwrites one") {
            Failure::usage(e)
        } else {
            Failure::job(e)
        }
    })?;
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    println!(
        "merged {} stores into {}: {} tiles ({} present in more than one, {} copied as they \
         were), arrays of {} × {} tiles of {} columns × {} levels",
        s.stores,
        args.out.display(),
        s.tiles,
        s.tiles_from_several,
        s.tiles_copied,
        s.span_tiles[0],
        s.span_tiles[1],
        s.tile_columns,
        s.levels
    );
    Ok(())
}
