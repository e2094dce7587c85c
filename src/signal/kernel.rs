//! The system response used for deconvolution: a short kernel of taps with a declared centre.
//!
//! Convolution convention (used by every method): `(k ⊛ x)[i] = Σ_j taps[j] · x[i + center − j]`
//! over the indices that exist (samples outside the segment are zero). A kernel whose peak is at
//! `center` therefore does not shift anything in time: deconvolving with it keeps returns where
//! they are. Correlation (convolution with the flipped kernel) is
//! `(k ⋆ x)[i] = Σ_j taps[j] · x[i − center + j]`.
//!
//! Per-shot kernels come from the outgoing pulse (baseline removed, negative samples clipped,
//! normalised to unit sum, centred on the peak sample); a calibrated system impulse response can
//! come from configuration as plain taps, or be measured on a flat target
//! ([`crate::signal::deconvolve::response`]).
//!
//! **Zero-phase alignment on the peak, not the centroid.** The zero-delay tap of a kernel built
//! from a recorded pulse is its highest sample. A point target at two-way time `t` then returns
//! `k ⊛ δ_t`, whose highest sample is at `t`, and deconvolution puts the target back at `t`: the
//! deconvolved return lies where the raw echo peaked, the convention of discrete-return ranging
//! and of the NEON geolocation (`geo.csv` references the outgoing pulse at its peak bin). The
//! centroid was rejected: for the asymmetric pulses of real digitizers (NEON: a 1-2 ns rise, a
//! long tail) it lies 1.5-2 bins after the peak, so every return would move by that much
//! relative to the raw peak; it is not a sample, so it needs rounding (±0.5 bin) or a
//! fractional shift; and it depends on where the recording truncates the tail and on the
//! baseline estimate (a 1 % baseline error over a 60-sample tail moves it by about a bin),
//! while the peak depends on neither. See `docs/signal.md`.

/// Number of leading samples whose median is taken as the baseline of a recorded pulse
/// ([`remove_baseline`]).
pub const KERNEL_BASELINE_SAMPLES: usize = 8;

/// A recorded pulse (digitizer counts or volts on a pedestal) minus its baseline, the median
/// of its first [`KERNEL_BASELINE_SAMPLES`] samples (the pre-trigger samples). Empty in, empty
/// out.
pub fn remove_baseline(row: &[f32]) -> Vec<f32> {
    if row.is_empty() {
        return Vec::new();
    }
    let mut head = row[..row.len().min(KERNEL_BASELINE_SAMPLES)].to_vec();
    head.sort_unstable_by(f32::total_cmp);
    let n = head.len();
    let base = if n % 2 == 1 {
        head[n / 2]
    } else {
        0.5 * (head[n / 2 - 1] + head[n / 2])
    };
    row.iter().map(|v| v - base).collect()
}

/// Index of the first maximum of `x` (the peak sample of a recorded pulse: the zero-delay tap
/// of a kernel, the emission reference of the `calibrate` stage); `None` when `x` is empty or
/// holds no number above `f32::MIN` (NaN samples are never a maximum).
pub fn peak_index(x: &[f32]) -> Option<usize> {
    let mut peak = None;
    let mut best = f32::MIN;
    for (i, &v) in x.iter().enumerate() {
        if v > best {
            best = v;
            peak = Some(i);
        }
    }
    peak
}

/// Why a kernel could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KernelError {
    /// No taps, or every tap zero or negative.
    #[error("kernel has no positive energy")]
    NoEnergy,
    /// A tap is NaN or infinite.
    #[error("kernel has a non-finite tap")]
    NonFinite,
    /// More taps than the buffers were sized for.
    #[error("kernel of {len} taps exceeds the maximum of {max}")]
    TooLong {
        /// Taps given.
        len: usize,
        /// Maximum.
        max: usize,
    },
}

/// A normalised system response: taps summing to 1 with the zero-delay tap at `center`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Kernel {
    /// The taps (unit sum, non-negative for kernels from outgoing pulses).
    pub taps: Vec<f32>,
    /// Index of the zero-delay tap (the peak for kernels from outgoing pulses).
    pub center: usize,
}

impl Kernel {
    /// An empty kernel whose buffer holds `max_taps` without reallocating.
    pub fn with_capacity(max_taps: usize) -> Self {
        Kernel {
            taps: Vec::with_capacity(max_taps),
            center: 0,
        }
    }

    /// Rebuilds the kernel from an outgoing pulse already in volts above its baseline:
    /// negative samples clipped to zero, normalised to unit sum, centred on the peak sample (the
    /// zero-phase alignment: the peak is the emission reference t0 of the digitizer, so a return
    /// deconvolved with it stays at its two-way time). Does not allocate within capacity.
    pub fn set_from_outgoing(
        &mut self,
        outgoing: &[f32],
        max_taps: usize,
    ) -> Result<(), KernelError> {
        if outgoing.len() > max_taps {
            return Err(KernelError::TooLong {
                len: outgoing.len(),
                max: max_taps,
            });
        }
        if outgoing.iter().any(|v| !v.is_finite()) {
            return Err(KernelError::NonFinite);
        }
        self.taps.clear();
        self.taps.extend(outgoing.iter().map(|v| v.max(0.0)));
        let sum: f64 = self.taps.iter().map(|&v| v as f64).sum();
        if sum <= 0.0 || !sum.is_finite() {
            return Err(KernelError::NoEnergy);
        }
        let inv = (1.0 / sum) as f32;
        for v in self.taps.iter_mut() {
            *v *= inv;
        }
        self.center = peak_index(&self.taps).unwrap_or(0);
        Ok(())
    }

    /// Sets the kernel from calibrated taps with an explicit centre, normalised to unit sum
    /// (taps may be negative, e.g. a ringing receiver response, but the sum must be positive).
    pub fn set_from_taps(
        &mut self,
        taps: &[f32],
        center: usize,
        max_taps: usize,
    ) -> Result<(), KernelError> {
        if taps.len() > max_taps {
            return Err(KernelError::TooLong {
                len: taps.len(),
                max: max_taps,
            });
        }
        if taps.iter().any(|v| !v.is_finite()) {
            return Err(KernelError::NonFinite);
        }
        let sum: f64 = taps.iter().map(|&v| v as f64).sum();
        if taps.is_empty() || sum <= 0.0 || center >= taps.len() {
            return Err(KernelError::NoEnergy);
        }
        self.taps.clear();
        self.taps
            .extend(taps.iter().map(|&v| (v as f64 / sum) as f32));
        self.center = center;
        Ok(())
    }

    /// Number of taps.
    pub fn len(&self) -> usize {
        self.taps.len()
    }

    /// True when the kernel has no taps.
    pub fn is_empty(&self) -> bool {
        self.taps.is_empty()
    }
}

/// `out = k ⊛ x` (same length as `x`; see the module's convention). `out.len()` must equal
/// `x.len()`.
pub fn convolve_same(x: &[f32], k: &Kernel, out: &mut [f32]) {
    let n = x.len() as isize;
    let c = k.center as isize;
    for (i, o) in out.iter_mut().enumerate() {
        let mut acc = 0.0f32;
        for (j, &t) in k.taps.iter().enumerate() {
            let src = i as isize + c - j as isize;
            if src >= 0 && src < n {
                acc += t * x[src as usize];
            }
        }
        *o = acc;
    }
}

/// `out = k ⋆ x`, the adjoint of [`convolve_same`] (convolution with the flipped kernel).
pub fn correlate_same(x: &[f32], k: &Kernel, out: &mut [f32]) {
    let n = x.len() as isize;
    let c = k.center as isize;
    for (i, o) in out.iter_mut().enumerate() {
        let mut acc = 0.0f32;
        for (j, &t) in k.taps.iter().enumerate() {
            let src = i as isize - c + j as isize;
            if src >= 0 && src < n {
                acc += t * x[src as usize];
            }
        }
        *o = acc;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outgoing_kernel_is_normalised_and_centred_on_its_peak() {
        let mut k = Kernel::with_capacity(16);
        k.set_from_outgoing(&[0.0, -0.1, 1.0, 3.0, 1.0, 0.0], 16)
            .unwrap();
        assert_eq!(k.center, 3);
        assert!((k.taps.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert_eq!(k.taps[1], 0.0);
    }

    #[test]
    fn a_centred_kernel_does_not_shift_a_spike() {
        let mut k = Kernel::with_capacity(16);
        k.set_from_outgoing(&[1.0, 2.0, 4.0, 2.0, 1.0], 16).unwrap();
        let mut x = vec![0.0f32; 20];
        x[9] = 1.0;
        let mut y = vec![0.0f32; 20];
        convolve_same(&x, &k, &mut y);
        let peak = y
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap()
            .0;
        assert_eq!(peak, 9);
        assert!((y.iter().sum::<f32>() - 1.0).abs() < 1e-6);
    }

    #[test]
    fn correlation_is_the_adjoint_of_convolution() {
        // <k ⊛ x, y> == <x, k ⋆ y> for an asymmetric, off-centre kernel.
        let mut k = Kernel::default();
        k.set_from_taps(&[0.5, 2.0, -0.3, 0.8], 1, 8).unwrap();
        let x: Vec<f32> = (0..13).map(|i| ((i * 7) % 5) as f32 - 1.0).collect();
        let y: Vec<f32> = (0..13).map(|i| ((i * 3) % 4) as f32 + 0.5).collect();
        let mut kx = vec![0.0; 13];
        let mut ky = vec![0.0; 13];
        convolve_same(&x, &k, &mut kx);
        correlate_same(&y, &k, &mut ky);
        let a: f32 = kx.iter().zip(&y).map(|(a, b)| a * b).sum();
        let b: f32 = x.iter().zip(&ky).map(|(a, b)| a * b).sum();
        assert!((a - b).abs() < 1e-4, "{a} vs {b}");
    }

    #[test]
    fn bad_kernels_are_errors() {
        let mut k = Kernel::with_capacity(4);
        assert_eq!(
            k.set_from_outgoing(&[0.0, -1.0], 4),
            Err(KernelError::NoEnergy)
        );
        assert_eq!(
            k.set_from_outgoing(&[f32::NAN], 4),
            Err(KernelError::NonFinite)
        );
        assert!(matches!(
            k.set_from_outgoing(&[1.0; 5], 4),
            Err(KernelError::TooLong { .. })
        ));
    }
}
