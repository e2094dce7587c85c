//! The system impulse response measured on a flat target: the first of the waveformlidar R
//! package's two deconvolution steps.
//!
//! Signal model (`docs/signal.md`): a return is `P = o ⊛ h ⊛ σ + N`, `o` the outgoing pulse as
//! the digitizer records it for that shot and `h` the rest of the system response (receiver,
//! detector, electronics) relative to it. A hard, flat target near nadir (`σ` one spike)
//! returns `g = o_g ⊛ h`, `o_g` its own recorded outgoing pulse, so `h` is `g` deconvolved by
//! `o_g`. With `h` known once per campaign, every return is deconvolved by `h` (one deconvolve
//! stage with a calibrated kernel) and then by its own outgoing pulse (a second stage with
//! `kernel = "outgoing"`), in that order, as the R package's `deconvolution(re, out, imp,
//! imp_out)` does.
//!
//! [`response_from_flat_target`] computes `h` when a stage is built (not per pulse): both
//! records lose their baseline ([`remove_baseline`]); the outgoing pulse becomes a kernel
//! centred on its peak ([`Kernel::set_from_outgoing`]); the ground return is deconvolved by it
//! with the stage's own method (noise level 0: a calibration record is taken at high SNR);
//! the result is cut to the taps around its peak above [`RESPONSE_TAIL`] of the peak and becomes
//! a kernel centred on its peak, so deconvolving by `h` does not move returns either.

use crate::signal::deconvolve::{DeconvError, MethodConfig};
use crate::signal::kernel::{Kernel, KernelError, remove_baseline};

/// Taps of the measured response below this fraction of its peak, outside the contiguous run
/// around the peak, are cut (they are deconvolution residue, and every tap costs per pulse).
pub const RESPONSE_TAIL: f32 = 1e-3;

/// Why a response could not be measured from a flat-target record.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ResponseError {
    /// The flat target's outgoing pulse gives no usable kernel.
    #[error("outgoing: {0}")]
    Outgoing(KernelError),
    /// The flat target's return is empty or holds a NaN or infinite sample.
    #[error("ground_return: {0}")]
    GroundReturn(DeconvError),
    /// The deconvolved response is unusable (no positive energy, longer than `max_taps`).
    #[error("measured response: {0}")]
    Response(KernelError),
}

/// The system response `h` (unit sum, centred on its peak) from a flat-target return
/// `ground_return` and its recorded outgoing pulse `outgoing` (both raw records on a baseline:
/// counts or volts), deconvolved with `method`. At most `max_taps` taps.
pub fn response_from_flat_target(
    ground_return: &[f32],
    outgoing: &[f32],
    method: &MethodConfig,
    max_taps: usize,
) -> Result<Kernel, ResponseError> {
    if outgoing.iter().any(|v| !v.is_finite()) {
        return Err(ResponseError::Outgoing(KernelError::NonFinite));
    }
    if ground_return.iter().any(|v| !v.is_finite()) {
        return Err(ResponseError::GroundReturn(DeconvError::NonFiniteInput));
    }
    if ground_return.is_empty() {
        return Err(ResponseError::Response(KernelError::NoEnergy));
    }
    let mut k_out = Kernel::with_capacity(outgoing.len());
    k_out
        .set_from_outgoing(&remove_baseline(outgoing), outgoing.len())
        .map_err(ResponseError::Outgoing)?;
    let g = remove_baseline(ground_return);
    let mut h = vec![0.0f32; g.len()];
    let mut dec = method.build(g.len(), k_out.len());
    dec.run(&g, &k_out, 0.0, 1.0, &mut h)
        .map_err(ResponseError::GroundReturn)?;
    // The contiguous run around the peak above RESPONSE_TAIL × peak.
    let peak = h
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(&a.0)))
        .map_or(0, |(i, _)| i);
    let floor = h[peak] * RESPONSE_TAIL;
    let mut lo = peak;
    while lo > 0 && h[lo - 1] > floor {
        lo -= 1;
    }
    let mut hi = peak + 1;
    while hi < h.len() && h[hi] > floor {
        hi += 1;
    }
    let mut kernel = Kernel::with_capacity(max_taps);
    kernel
        .set_from_outgoing(&h[lo..hi], max_taps)
        .map_err(ResponseError::Response)?;
    Ok(kernel)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::deconvolve::GoldConfig;
    use crate::signal::kernel::convolve_same;

    /// An asymmetric digitizer-like pulse on a 200-count pedestal: fast rise, long tail.
    fn pulse(n: usize, peak: usize, amp: f32) -> Vec<f32> {
        (0..n)
            .map(|i| {
                let t = i as f32 - peak as f32;
                let v = if t < 0.0 {
                    (-0.5 * (t / 2.5).powi(2)).exp()
                } else {
                    (-t / 6.0).exp()
                };
                200.0 + amp * v
            })
            .collect()
    }

    /// A flat target's record: the outgoing pulse `out` (on its 200-count pedestal) convolved
    /// with `h`, 9 bins later (its range), 80 samples on the pedestal.
    fn flat_target(out: &[f32], h: &Kernel) -> Vec<f32> {
        let mut padded: Vec<f32> = out.iter().map(|v| v - 200.0).collect();
        padded.resize(80, 0.0);
        let mut g = vec![0.0f32; 80];
        convolve_same(&padded, h, &mut g);
        (0..80)
            .map(|i| 200.0 + if i >= 9 { g[i - 9] } else { 0.0 })
            .collect()
    }

    fn three_taps() -> Kernel {
        let mut h = Kernel::default();
        h.set_from_taps(&[0.25, 0.5, 0.25], 1, 8).unwrap();
        h
    }

    #[test]
    fn a_known_response_is_recovered_from_a_flat_target() {
        let out = pulse(60, 20, 700.0);
        let g = flat_target(&out, &three_taps());
        let method = MethodConfig::Gold(GoldConfig {
            iterations: 200,
            repetitions: 1,
            boost: 1.0,
            stop_at_noise: None,
        });
        let k = response_from_flat_target(&g, &out, &method, 64).unwrap();
        // Narrow and centred: most of the energy in the centre tap and its two neighbours.
        let c = k.center;
        let core: f32 = k.taps[c.saturating_sub(1)..(c + 2).min(k.len())]
            .iter()
            .sum();
        assert!(core > 0.85, "{k:?}");
        assert!((k.taps.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        // The recovered spread is that of h: variance 0.5 bin² (measured 1.0 after 200 Gold
        // iterations: the multiplicative updates sharpen slowly); an unrecovered response, the
        // flat target's whole echo, would have ~30 bin².
        let var: f32 = k
            .taps
            .iter()
            .enumerate()
            .map(|(i, t)| t * (i as f32 - c as f32).powi(2))
            .sum();
        assert!(var > 0.2 && var < 1.25, "variance {var} bin², {k:?}");
    }

    #[test]
    fn bad_flat_target_records_are_errors() {
        let m = MethodConfig::Gold(GoldConfig::default());
        let out = pulse(40, 10, 500.0);
        assert!(matches!(
            response_from_flat_target(&[200.0; 30], &[200.0; 20], &m, 64),
            Err(ResponseError::Outgoing(KernelError::NoEnergy))
        ));
        assert!(matches!(
            response_from_flat_target(&[1.0, f32::NAN], &out, &m, 64),
            Err(ResponseError::GroundReturn(_))
        ));
        assert!(matches!(
            response_from_flat_target(&[], &out, &m, 64),
            Err(ResponseError::Response(_))
        ));
        // The 3-tap response does not fit in 2 taps.
        let g = flat_target(&out, &three_taps());
        assert!(matches!(
            response_from_flat_target(&g, &out, &m, 2),
            Err(ResponseError::Response(KernelError::TooLong { .. }))
        ));
    }
}
