//! Sinks: where processed pulses go, in arrival order (processed waveforms, fitted returns as CSV
//! and as LAS 1.4 with waveforms; voxel tiles as a later issue lands).

pub mod hyper_points;
pub mod las_wave;
pub mod metrics_rasters;
pub mod pulse_metrics_csv;
pub mod returns_csv;
pub mod voxel_tiles;
pub mod waveform_csv;
pub mod waveform_npy;
