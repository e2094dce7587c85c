//! # fwlidar — a streaming processor for airborne small-footprint full-waveform LiDAR
//!
//! ```text
//!  digitizer frames ─┐                                                          ┌─> waveforms, returns.las
//!  (capture, UDP/TCP,│                                                          ├─> voxels.zarr, rasters
//!   LAS, PLS, GEDI)  ├─> source ─[edge]─> worker × N: denoise ─> … ─[edge]─> sink (order restored)
//!  GNSS/INS bytes ───┘        └─[nav channel]─> navigation consumer             └─> summary / QC
//! ```
//!
//! The item that flows is a [`pulse::Pulse`]. Sources decode recorded or live input into pooled
//! pulses; per-pulse stages ([`stages`], one file each, on the runtime's [`pipeline::Stage`]
//! contract) run on worker threads; sinks write outputs in arrival order; [`run`] puts a run
//! together for replay and the daemon. The modules form layers (`tests/layering.rs`), from
//! [`core`] (units, validation, loading) and [`pulse`] up to [`cli`]; `docs/architecture.md`
//! draws them and describes the threads, queues and the stage contract.
#![deny(missing_docs)]
#![deny(clippy::too_many_lines)]
// Pulses travel as `Box<Pulse>` on purpose: a pooled pulse moves between threads by pointer,
// its buffers never copied, so `Vec<Box<Pulse>>` is the right shape for emit buffers.
#![allow(clippy::vec_box)]

pub mod campaign;
pub mod cli;
pub mod config;
pub mod core;
pub mod daemon;
pub mod eval;
pub mod fixtures;
pub mod forest;
pub mod format;
pub mod geo;
pub mod nav;
pub mod pipeline;
pub mod pulse;
pub mod qc;
pub mod raster;
pub mod run;
pub mod signal;
pub mod sim;
pub mod sink;
pub mod source;
pub mod stages;
pub mod trees;
pub mod voxel;
