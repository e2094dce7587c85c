//! Deconvolution: recovering the cross-section σ(t) from a received segment `P = R ⊛ σ + N`,
//! method from configuration (Richardson-Lucy, Gold, Wiener, NNLS), each with a fixed worst-case
//! cost per pulse for a given configuration.
//!
//! Every method implements [`Deconvolver`] on plain slices (one segment at a time, volts above
//! baseline) so the stage, `fwlidar process` and the benchmarks share the same code.

pub mod choice;
pub(crate) mod direct;
pub mod gate;
pub mod gold;
pub mod nnls;
pub mod response;
pub mod richardson_lucy;
pub mod target;
#[cfg(test)]
mod tests;
pub mod wiener;

use serde::{Deserialize, Serialize};

use crate::signal::kernel::Kernel;

pub use choice::{NnlsOrRl, NnlsOrRlConfig};
pub use gate::{Gate, GateError, GateStats, Gated};
pub use gold::{Gold, GoldConfig};
pub use nnls::{Nnls, NnlsConfig};
pub use richardson_lucy::{RichardsonLucy, RlConfig};
pub use target::{KernelReducer, Targeted};
pub use wiener::{Wiener, WienerConfig};

/// Why a segment could not be deconvolved (the stage drops the pulse with this reason).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DeconvError {
    /// The input holds NaN or infinite samples.
    #[error("non-finite input sample")]
    NonFiniteInput,
    /// The segment is longer than the buffers were sized for.
    #[error("segment of {len} samples exceeds the maximum of {max}")]
    TooLong {
        /// Samples given.
        len: usize,
        /// Maximum.
        max: usize,
    },
    /// The kernel is longer than the buffers were sized for.
    #[error("kernel of {len} taps exceeds the maximum of {max}")]
    KernelTooLong {
        /// Taps given.
        len: usize,
        /// Maximum.
        max: usize,
    },
    /// The kernel has no taps, a non-finite tap or its centre outside the taps.
    #[error("kernel is empty, non-finite or its centre lies outside its taps")]
    BadKernel,
    /// `out` and the input differ in length.
    #[error("output length {out} differs from input length {input}")]
    LengthMismatch {
        /// Input length.
        input: usize,
        /// Output length.
        out: usize,
    },
}

impl DeconvError {
    /// The short drop reason counted in telemetry.
    pub fn reason(&self) -> &'static str {
        match self {
            DeconvError::NonFiniteInput => "non_finite_input",
            DeconvError::TooLong { .. } => "segment_too_long",
            DeconvError::KernelTooLong { .. } => "kernel_too_long",
            DeconvError::LengthMismatch { .. } => "length_mismatch",
            DeconvError::BadKernel => "bad_kernel",
        }
    }
}

/// What one deconvolution run did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MethodStats {
    /// Iterations performed (0 for direct methods).
    pub iterations: u32,
    /// True when an early-stop criterion ended the run before its budget.
    pub stopped_early: bool,
}

/// A deconvolution method with its buffers sized once.
pub trait Deconvolver: Send {
    /// Method name as in configuration (`richardson_lucy`, `gold`, `wiener`, `nnls`).
    fn name(&self) -> &'static str;

    /// Deconvolves `y` (one segment, volts above baseline, sample interval `sample_ns`) by `k`
    /// into `out` (same length). `noise_v` is the segment's noise level (used by Wiener and for
    /// early stops). Never panics; never allocates within the sizes given at construction.
    fn run(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError>;

    /// As [`Deconvolver::run`], with the samples flagged in `excluded` (as long as `y`; e.g.
    /// clipped at the digitizer's top, [`crate::signal::drift::flag_saturated`]) left out of
    /// the fit by the methods that can (NNLS); the others run on every sample.
    fn run_excluding(
        &mut self,
        y: &[f32],
        k: &Kernel,
        noise_v: f32,
        sample_ns: f64,
        excluded: &[bool],
        out: &mut [f32],
    ) -> Result<MethodStats, DeconvError> {
        let _ = excluded;
        self.run(y, k, noise_v, sample_ns, out)
    }

    /// Worst-case floating-point operations for a segment of `n` samples and a kernel of `m`
    /// taps with this configuration: the fixed cost budget the configuration states.
    fn worst_case_flops(&self, n: usize, m: usize) -> u64;

    /// Takes a target pulse of `fwhm_ns` (ns) to deliver results in itself, returning true; a
    /// method that does (the per-pulse choice, whose two methods see a target differently)
    /// is then passed through unchanged by [`Targeted`]. The default takes none (false):
    /// [`Targeted`] reduces the kernel or draws the spikes. Called at construction, not per
    /// pulse (it may allocate).
    fn take_target(&mut self, fwhm_ns: f64) -> bool {
        let _ = fwhm_ns;
        false
    }

    /// Of a per-pulse choice between two methods ([`NnlsOrRl`]): how often the second ran and
    /// was kept over the segments run so far. `None` for a single method (the default); the
    /// wrappers (gate, target pulse) pass on their method's.
    fn choice_counts(&self) -> Option<ChoiceCounts> {
        None
    }
}

/// How a per-pulse choice between two methods went over the segments run so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ChoiceCounts {
    /// Segments run.
    pub segments: u64,
    /// Segments where the second method (NNLS) ran: the first's fit misfit its echoes.
    pub second_runs: u64,
    /// Segments where the second method's result was kept.
    pub second_kept: u64,
}

/// The method and its settings (`method = "..."` in a `deconvolve` stage).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "snake_case")]
pub enum MethodConfig {
    /// Richardson-Lucy.
    RichardsonLucy(RlConfig),
    /// Gold (iterations × repetitions × boost).
    Gold(GoldConfig),
    /// Wiener filter fused with the low-pass.
    Wiener(WienerConfig),
    /// Non-negative least squares on the banded Toeplitz system.
    Nnls(NnlsConfig),
    /// NNLS or Richardson-Lucy, chosen per segment by their residuals.
    NnlsOrRl(NnlsOrRlConfig),
}

impl MethodConfig {
    /// Method name as in configuration (`richardson_lucy`, `gold`, `wiener`, `nnls`,
    /// `nnls_or_rl`).
    pub fn name(&self) -> &'static str {
        match self {
            MethodConfig::RichardsonLucy(_) => "richardson_lucy",
            MethodConfig::Gold(_) => "gold",
            MethodConfig::Wiener(_) => "wiener",
            MethodConfig::Nnls(_) => "nnls",
            MethodConfig::NnlsOrRl(_) => "nnls_or_rl",
        }
    }

    /// The fixed iteration budget per segment: RL `iterations`, Gold `iterations ×
    /// repetitions`, NNLS `max_iterations` (outer Lawson-Hanson iterations), Wiener 0 (direct),
    /// the per-pulse choice the sum of its two methods'.
    pub fn iteration_budget(&self) -> u64 {
        match self {
            MethodConfig::RichardsonLucy(c) => c.iterations as u64,
            MethodConfig::Gold(c) => c.iterations as u64 * c.repetitions.max(1) as u64,
            MethodConfig::Wiener(_) => 0,
            MethodConfig::Nnls(c) => c.max_iterations as u64,
            MethodConfig::NnlsOrRl(c) => c.nnls.max_iterations as u64 + c.rl.iterations as u64,
        }
    }

    /// Worst-case floating-point operations of one segment of `n` samples deconvolved by a
    /// kernel of `m` taps with these settings (the same figure as
    /// [`Deconvolver::worst_case_flops`], computed without building the method's buffers).
    pub fn worst_case_flops(&self, n: usize, m: usize) -> u64 {
        match self {
            MethodConfig::RichardsonLucy(c) => c.worst_case_flops(n, m),
            MethodConfig::Gold(c) => c.worst_case_flops(n, m),
            MethodConfig::Wiener(c) => c.worst_case_flops(n, m),
            MethodConfig::Nnls(c) => c.worst_case_flops(n, m),
            MethodConfig::NnlsOrRl(c) => c.worst_case_flops(n, m),
        }
    }

    /// Builds the method with buffers for segments of up to `max_samples` and kernels of up to
    /// `max_taps`.
    pub fn build(&self, max_samples: usize, max_taps: usize) -> Box<dyn Deconvolver> {
        match self {
            MethodConfig::RichardsonLucy(c) => {
                Box::new(RichardsonLucy::new(c.clone(), max_samples, max_taps))
            }
            MethodConfig::Gold(c) => Box::new(Gold::new(c.clone(), max_samples, max_taps)),
            MethodConfig::Wiener(c) => Box::new(Wiener::new(c.clone(), max_samples, max_taps)),
            MethodConfig::Nnls(c) => Box::new(Nnls::new(c.clone(), max_samples, max_taps)),
            MethodConfig::NnlsOrRl(c) => Box::new(NnlsOrRl::new(c.clone(), max_samples, max_taps)),
        }
    }
}

/// `method`'s run, with the samples flagged in `excluded` left out when given
/// ([`Deconvolver::run_excluding`]): what the wrappers (gate, target pulse) pass on.
pub(crate) fn run_flagged(
    method: &mut dyn Deconvolver,
    y: &[f32],
    k: &Kernel,
    noise_v: f32,
    sample_ns: f64,
    excluded: Option<&[bool]>,
    out: &mut [f32],
) -> Result<MethodStats, DeconvError> {
    match excluded {
        Some(e) => method.run_excluding(y, k, noise_v, sample_ns, e, out),
        None => method.run(y, k, noise_v, sample_ns, out),
    }
}

/// The checks every method makes before touching a segment: lengths, capacities, a usable
/// kernel and finite input. Returns the largest absolute input value (volts) on success.
pub(crate) fn check_inputs(
    y: &[f32],
    k: &Kernel,
    out: &[f32],
    max_samples: usize,
    max_taps: usize,
) -> Result<f32, DeconvError> {
    if out.len() != y.len() {
        return Err(DeconvError::LengthMismatch {
            input: y.len(),
            out: out.len(),
        });
    }
    if y.len() > max_samples {
        return Err(DeconvError::TooLong {
            len: y.len(),
            max: max_samples,
        });
    }
    if k.taps.len() > max_taps {
        return Err(DeconvError::KernelTooLong {
            len: k.taps.len(),
            max: max_taps,
        });
    }
    if k.taps.is_empty() || k.center >= k.taps.len() || k.taps.iter().any(|t| !t.is_finite()) {
        return Err(DeconvError::BadKernel);
    }
    let (finite, max_abs) = finite_max_abs(y);
    if !finite {
        return Err(DeconvError::NonFiniteInput);
    }
    Ok(max_abs)
}

/// Whether every sample of `y` is finite, and the largest magnitude (0 for no sample; not
/// meaningful when a sample is not finite). The magnitudes are compared as integers: the bits
/// of a non-negative float order as the float does, and NaN and infinity lie above every
/// finite value, so one integer maximum (16 lanes, which the compiler turns into vector
/// compares) answers both. `f32::max`'s NaN rule kept the float scan scalar, ~1 ns a sample.
#[inline]
fn finite_max_abs(y: &[f32]) -> (bool, f32) {
    const LANES: usize = 16;
    const ABS: u32 = 0x7fff_ffff;
    const INFINITY_BITS: i32 = 0x7f80_0000;
    // As i32 (the sign bit cleared, so the order is the unsigned one): baseline x86-64 compares
    // signed 32-bit lanes in one instruction.
    let bits = |v: f32| (v.to_bits() & ABS) as i32;
    let mut mx = [0i32; LANES];
    let chunks = y.chunks_exact(LANES);
    let rest = chunks.remainder();
    for c in chunks {
        for (m, &v) in mx.iter_mut().zip(c) {
            *m = (*m).max(bits(v));
        }
    }
    for (m, &v) in mx.iter_mut().zip(rest) {
        *m = (*m).max(bits(v));
    }
    let top = mx.iter().fold(0i32, |a, &b| a.max(b));
    (top < INFINITY_BITS, f32::from_bits(top as u32))
}

/// Writes `out[i] = x[i] · scale` clamped to the finite f32 range (the methods work on data
/// normalised to a unit maximum and scale back with this). In f32 when `scale` is a normal f32,
/// otherwise in f64 (denormal or out-of-range scales).
pub(crate) fn scale_out(x: &[f32], scale: f64, out: &mut [f32]) {
    let s32 = scale as f32;
    if s32.is_normal() {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = (v * s32).clamp(-f32::MAX, f32::MAX);
        }
    } else {
        let lim = f32::MAX as f64;
        for (o, &v) in out.iter_mut().zip(x) {
            *o = (v as f64 * scale).clamp(-lim, lim) as f32;
        }
    }
}

/// Writes `out[i] = x[i] / max` (the normalisation of [`scale_out`]); `max` positive and finite.
/// In f32 when `1/max` is a normal f32, otherwise in f64.
pub(crate) fn normalise(x: &[f32], max: f32, out: &mut [f32]) {
    let inv = 1.0 / max as f64;
    let inv32 = inv as f32;
    if inv32.is_normal() {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = v * inv32;
        }
    } else {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = (v as f64 * inv) as f32;
        }
    }
}
