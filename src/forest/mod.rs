//! Forest structure from the waveforms (issue 20): per-pulse metrics (relative heights, cover,
//! PAI, PAVD, FHD, crown thickness, herbaceous metrics) and their measurement per pulse, the
//! check against NASA GEDI's Level 2A/2B products, the same rasters recomputed from a voxel
//! store (`store_metrics`, `fwlidar metrics`), the metrics of waveform tables (`table_metrics`,
//! `fwlidar process --metrics`), their figure (`metrics_plot`, `fwlidar metrics-plot`), and biomass models from the metrics (`biomass`).
//! Definitions: `docs/forest.md`.

pub mod biomass;
pub mod gedi_check;
pub mod gedi_l2a;
pub mod measure;
pub mod metrics_plot;
pub mod products;
pub mod pulse_metrics;
pub mod store_metrics;
pub mod table_metrics;
