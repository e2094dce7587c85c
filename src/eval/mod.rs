//! Scoring the signal chain against a known truth, and what the score costs in time.
//!
//! - [`accuracy`]: the seed's accuracy metrics (RMSE eq. 14, true/false peak detections eq. 15,
//!   spectral angle);
//! - [`tradeoff`]: the sweep of methods and settings over simulated pulses, timed per pulse;
//! - [`chain`]: a run configuration's stages as one more setting of the sweep (`--chain`);
//! - [`report`]: its CSV and markdown;
//! - [`plot`]: its SVG figure (error against time per pulse, Pareto front);
//! - [`scene_steps`]: the seed's stepwise evaluation on a described scene (raw, denoise,
//!   deconvolution, voxelised), scored against the scene's truth.

pub mod accuracy;
pub mod chain;
pub mod plot;
pub mod point_match;
pub mod report;
pub mod scene_steps;
pub mod tradeoff;
