//! Per-pulse signal processing stages: denoise, deconvolve and decompose (peaks and a bounded
//! Gaussian fit).

pub mod decompose;
pub mod deconvolve;
pub mod denoise;
pub mod gauss_fit;
pub mod kernel;
pub mod peaks;

pub use decompose::{Decompose, DecomposeConfig};
pub use denoise::{Denoise, DenoiseConfig};
