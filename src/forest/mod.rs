//! Forest structure from the waveforms (issue 20): per-pulse metrics (relative heights, cover,
//! PAI, PAVD, FHD, crown thickness, herbaceous metrics), the stage that computes them, and the
//! check against NASA GEDI's Level 2A/2B products, and the same rasters recomputed from a voxel
//! store (`store_metrics`, `fwlidar metrics`). Definitions: `docs/forest.md`.

pub mod gedi_check;
pub mod pulse_metrics;
pub mod stage;
pub mod store_metrics;
