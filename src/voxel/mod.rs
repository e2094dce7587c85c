//! Voxel tiles: the grid (`grid`), per-tile accumulators (`tile`), depositing pulses bin by bin
//! (`voxelise`), the tile lifecycle (`tiles`) and the Zarr v3 store they are written to
//! (`zarr`; tiles grouped into shards with a journal: `shard_group`; zstd frames of sparse inner
//! chunks written from their runs of values: `fill_frame`). The sink that drives them in a run is `crate::sink::voxel_tiles`; combining stores
//! is `merge` (`fwlidar merge`, the campaign's merge tree).

pub mod fill_frame;
pub mod grid;
pub mod merge;
pub mod shard_group;
pub mod tile;
pub mod tiles;
pub mod voxelise;
pub mod zarr;
