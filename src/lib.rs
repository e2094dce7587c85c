//! # fwlidar — a streaming processor for airborne small-footprint full-waveform LiDAR
//!
//! ```text
//!  digitizer frames ─┐                                                          ┌─> processed pulses
//!  (capture | later  │                                                          ├─> summary / telemetry
//!   udp, LAS, PLS)   ├─> source ─[edge]─> worker × N: denoise ─> … ─[edge]─> sink (order restored)
//!  GNSS/INS bytes ───┘        └─[nav channel]─> navigation consumer
//! ```
//!
//! The item that flows is a [`pulse::Pulse`]. Sources decode recorded or live input into pooled
//! pulses; per-pulse [`pipeline::Stage`]s run on worker threads; sinks write outputs in arrival
//! order. See `docs/architecture.md` for the threads, queues and the stage contract.
#![deny(missing_docs)]
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
