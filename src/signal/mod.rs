//! Per-pulse signal processing stages: denoise, deconvolve, decompose (peaks and a bounded
//! Gaussian fit) and calibrate (radiometric calibration).

pub mod calibrate;
pub mod decompose;
pub mod deconvolve;
pub mod denoise;
pub mod drift;
pub mod echo_fit;
pub mod echo_strength;
pub mod gauss_fit;
pub mod kernel;
pub mod kernel_stretch;
pub mod learned_response;
pub mod peaks;
pub mod robust_noise;

pub use calibrate::{Calibrate, CalibrateConfig};
pub use decompose::{Decompose, DecomposeBaseline, DecomposeConfig, DecomposePulses, StartValues};
pub use denoise::{Denoise, DenoiseConfig};
