//! Per-pulse signal processing stages: denoise (and, later, deconvolve and decompose).

pub mod decompose;
pub mod deconvolve;
pub mod denoise;
pub mod kernel;

pub use denoise::{Denoise, DenoiseConfig};
