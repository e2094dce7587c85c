//! Combining voxel stores (`fwlidar merge`, and the merge tree of `fwlidar campaign`).
//!
//! The stores must share their grid (voxel size, tile-grid anchor, height range and mode, tile
//! size, intensity quantum), CRS and intensity units; their extents may differ and the result
//! covers them all. A tile present in several stores is the sum of their counts and intensity
//! sums (integers of the quantum, so exact) and the larger of their maxima: the data do not
//! depend on the order of the stores nor on how a merge is split into merges of merges, bit for
//! bit. A tile only one input holds is copied as its chunk files are (the encoding is
//! deterministic, so these are the bytes a decode and re-encode would give, without the cost). The metadata (`run_key`, `configuration`) name the inputs unless the caller gives them
//! ([`MergeMeta::Given`]), which a campaign does so that its mosaic is byte-identical whatever
//! its merge tree.

use std::path::{Path, PathBuf};

use crate::voxel::tile::TileData;
use crate::voxel::zarr::{StoreInfo, ZarrStore};

/// The metadata of a merged store.
#[derive(Clone, Debug, PartialEq)]
pub enum MergeMeta {
    /// `run_key` "merged from <paths>", `configuration` every input's under its path.
    FromInputs,
    /// As given.
    Given {
        /// `fwlidar.run_key`.
        run_key: String,
        /// The `configuration` attribute (TOML text).
        configuration: String,
    },
}

/// What a merge did.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MergeSummary {
    /// Input stores.
    pub stores: usize,
    /// Tiles written.
    pub tiles: usize,
    /// Tiles present in more than one input.
    pub tiles_from_several: u64,
    /// Tiles one input held, copied as its chunk files are (not decoded and encoded again).
    pub tiles_copied: u64,
    /// Tiles of the result's arrays along x and y.
    pub span_tiles: [u32; 2],
    /// Columns per tile side.
    pub tile_columns: u32,
    /// Height levels of the grid.
    pub levels: u32,
}

/// Merges `stores` into the new store `out` (which must not exist; it appears when complete,
/// written as `<out>.partial` first); `tick` is called once per tile written. Errors name the
/// stores at fault.
pub fn merge_stores(
    stores: &[PathBuf],
    out: &Path,
    meta: &MergeMeta,
    mut tick: impl FnMut(usize, usize),
) -> Result<MergeSummary, String> {
    if out.exists() {
        return Err(format!(
            "{} exists; merge writes a new store and never overwrites one",
            out.display()
        ));
    }
    if stores.is_empty() {
        return Err("no store to merge".into());
    }
    // A fixed order (by path) for everything that is not commutative: attributes, file order.
    let mut paths = stores.to_vec();
    paths.sort();
    paths.dedup();
    let mut opened = Vec::with_capacity(paths.len());
    for p in &paths {
        opened.push(ZarrStore::open(p).map_err(|e| e.to_string())?);
    }
    let first = &opened[0];
    let mut grid = first.grid().clone();
    for (s, p) in opened.iter().zip(&paths).skip(1) {
        grid.compatible(s.grid()).map_err(|why| {
            format!(
                "{} and {} cannot be merged: {why}",
                paths[0].display(),
                p.display()
            )
        })?;
        if s.info().epsg != first.info().epsg || s.info().crs_wkt != first.info().crs_wkt {
            return Err(format!(
                "{} and {} cannot be merged: their CRS differ (EPSG {:?} and {:?})",
                paths[0].display(),
                p.display(),
                first.info().epsg,
                s.info().epsg
            ));
        }
        if s.info().intensity_units != first.info().intensity_units {
            return Err(format!(
                "{} and {} cannot be merged: intensities in {:?} and {:?}",
                paths[0].display(),
                p.display(),
                first.info().intensity_units,
                s.info().intensity_units
            ));
        }
        grid = grid.union(s.grid());
    }
    let names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
    let (run_key, configuration) = match meta {
        MergeMeta::FromInputs => (
            format!("merged from {}", names.join(", ")),
            opened
                .iter()
                .zip(&names)
                .map(|(s, n)| format!("# {n}\n{}", s.info().configuration))
                .collect::<Vec<_>>()
                .join("\n"),
        ),
        MergeMeta::Given {
            run_key,
            configuration,
        } => (run_key.clone(), configuration.clone()),
    };
    let info = StoreInfo {
        crs_wkt: first.info().crs_wkt.clone(),
        epsg: first.info().epsg,
        intensity_units: first.info().intensity_units.clone(),
        run_key,
        configuration,
    };
    // Every tile of the result with its height chunks: the arrays are created on their
    // bounding box, so that nothing moves when the result is fitted.
    let mut chunks: std::collections::BTreeMap<[i64; 2], Vec<u32>> = Default::default();
    for s in &opened {
        for t in s.tiles() {
            let c = chunks.entry(t).or_default();
            c.extend_from_slice(s.tile_chunks(t).unwrap_or_default());
        }
    }
    let tiles: Vec<[i64; 2]> = chunks.keys().copied().collect();
    // Written whole into `<out>.partial` (a killed merge's is cleared), without a sync per
    // tile, then synced once and renamed: `out` is complete or absent.
    let mut tmp = out.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = PathBuf::from(tmp);
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp)
            .map_err(|e| format!("cannot clear {}: {e}", tmp.display()))?;
    }
    // Laid out as the first input is (tiles grouped into shards or not), so that tiles copy.
    let layout = opened[0].layout_choice();
    let on_tiles = chunks.iter().map(|(t, c)| (*t, c.as_slice()));
    let mut result = ZarrStore::create_on_tiles(&tmp, grid.clone(), info, layout, on_tiles)
        .map_err(|e| e.to_string())?
        .unsynced();
    let (mut acc, mut part) = (TileData::for_grid(&grid), TileData::for_grid(&grid));
    let (mut from_several, mut copied) = (0u64, 0u64);
    for (k, &t) in tiles.iter().enumerate() {
        // A merged store is not resumed: its tiles carry watermark 0.
        let holders: Vec<usize> = (0..opened.len())
            .filter(|&i| opened[i].tile_chunks(t).is_some())
            .collect();
        if let [only] = holders[..]
            && result
                .copy_tile(&opened[only], t, 0)
                .map_err(|e| e.to_string())?
        {
            // One input holds the tile: its chunk files are the merged tile's bytes.
            copied += 1;
        } else {
            acc.clear();
            for &i in &holders {
                if opened[i]
                    .read_tile(t, &mut part)
                    .map_err(|e| e.to_string())?
                {
                    acc.merge(&part);
                }
            }
            result.write_tile(t, &acc, 0).map_err(|e| e.to_string())?;
        }
        if holders.len() > 1 {
            from_several += 1;
        }
        tick(k + 1, tiles.len());
    }
    // The arrays span the bounding box of the tiles, whatever the inputs' extents.
    result.fit().map_err(|e| e.to_string())?;
    result.sync();
    let span = *result.span();
    drop(result);
    std::fs::rename(&tmp, out)
        .map_err(|e| format!("cannot rename {} to {}: {e}", tmp.display(), out.display()))?;
    Ok(MergeSummary {
        stores: opened.len(),
        tiles: tiles.len(),
        tiles_from_several: from_several,
        tiles_copied: copied,
        span_tiles: span.tiles,
        tile_columns: grid.tile_columns,
        levels: grid.levels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::voxel::grid::{Grid, VoxelConfig};
    use crate::voxel::shard_group::ShardGroup;

    fn grid() -> Grid {
        Grid::new(
            &VoxelConfig {
                extent_m: Some([-32.0, -32.0, 32.0, 32.0]),
                z_range_m: [0.0, 0.6],
                tile_columns: 8,
                ..VoxelConfig::default()
            },
            [0.0, 0.0],
        )
    }

    fn tile(seed: usize) -> TileData {
        let g = grid();
        let mut t = TileData::for_grid(&g);
        for i in (seed..g.tile_voxels()).step_by(7) {
            t.deposit(i, i as i64 * 3 + 1, i as f32);
            t.pass(i);
        }
        t
    }

    #[test]
    fn stores_of_grouped_tiles_merge_into_a_grouped_store_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let group = ShardGroup {
            tiles: 4,
            height_chunks: 1,
        };
        let info = |k: &str| StoreInfo {
            crs_wkt: None,
            epsg: Some(32736),
            intensity_units: "V".into(),
            run_key: k.into(),
            configuration: String::new(),
        };
        // Two lines: [0, 0] in both, [1, 0] and [-3, 2] in one each.
        let mut paths = Vec::new();
        for (n, tiles) in [
            vec![([0, 0], 1), ([1, 0], 2)],
            vec![([0, 0], 3), ([-3, 2], 4)],
        ]
        .into_iter()
        .enumerate()
        {
            let p = dir.path().join(format!("line{n}.zarr"));
            let mut s =
                ZarrStore::create_or_open_grouped(&p, grid(), info("l"), Some(group)).unwrap();
            for (t, seed) in tiles {
                s.write_tile(t, &tile(seed), 5).unwrap();
            }
            s.fit().unwrap();
            paths.push(p);
        }
        let out = dir.path().join("mosaic.zarr");
        let sum = merge_stores(&paths, &out, &MergeMeta::FromInputs, |_, _| {}).unwrap();
        assert_eq!(
            (sum.tiles, sum.tiles_from_several, sum.tiles_copied),
            (3, 1, 2)
        );
        let mut m = ZarrStore::open(&out).unwrap();
        assert_eq!(m.layout_choice().group, Some(group));
        let mut got = TileData::for_grid(&grid());
        let mut both = tile(1);
        both.merge(&tile(3));
        for (t, want) in [([0, 0], both), ([1, 0], tile(2)), ([-3, 2], tile(4))] {
            assert!(m.read_tile(t, &mut got).unwrap());
            let (a, b) = (got.dense(), want.dense());
            assert_eq!(
                (a.sum_q, a.samples, a.pulses),
                (b.sum_q, b.samples, b.pulses),
                "{t:?}"
            );
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a.max), bits(&b.max), "{t:?}");
        }
    }
}
