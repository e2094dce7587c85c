//! Truth cross-sections for scoring the signal chain, until the scene simulator lands: seeded,
//! deterministic scatterer profiles along the beam, and the waveforms J. Wu (2012, §2.1.3.1)
//! compares: the **truth** (the cross-section convolved with a 2 ns FWHM outgoing pulse, the
//! seed's "near-perfect impulse response") and the **received** waveform (the cross-section
//! convolved with a wider Gaussian pulse, 4, 8 or 16 ns FWHM, plus uniform white noise, as the
//! seed added).
//!
//! Units: one bin is one sample of `sample_ns` nanoseconds (1 ns, 0.15 m of range, as in the
//! seed); the cross-section is in "signal units per bin" (a hard surface of reflectance `a` is a
//! single bin of value `a`); every pulse has unit sum, so the truth, the received waveform and a
//! deconvolved waveform all share that unit and the same area.
//!
//! Two families:
//!
//! - [`TruthFamily::Sparse`]: 2 to 4 discrete hard surfaces (ground and objects above it),
//!   3 to 40 bins apart, so some pairs are unresolved by the wider pulses (hidden peaks).
//! - [`TruthFamily::Extended`]: 1 to 3 canopy-like layers of extended scatterers, each 6 to
//!   30 bins deep and made of 2 to 5 foliage clumps (Gaussian in depth, 1 to 4 bins standard
//!   deviation), attenuated with depth (Beer-Lambert on the cumulative cross-section), over a
//!   ground return attenuated by everything above it.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::signal::kernel::{Kernel, convolve_same};

/// FWHM of the outgoing pulse whose waveform is taken as the truth, ns (the seed's 2 ns).
pub const TRUTH_FWHM_NS: f64 = 2.0;

/// Number of bins of every simulated waveform (the seed's 225 bins).
pub const DEFAULT_BINS: usize = 225;

/// Bins kept free of scatterers at either end of the window (room for a 16 ns pulse's tails).
const MARGIN_BINS: usize = 30;

/// A family of truth cross-sections.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TruthFamily {
    /// A few discrete hard surfaces.
    Sparse,
    /// Layers of canopy-like extended scatterers over the ground.
    Extended,
}

impl TruthFamily {
    /// Both families, in report order.
    pub const ALL: [TruthFamily; 2] = [TruthFamily::Sparse, TruthFamily::Extended];

    /// The family's name in reports (`sparse`, `extended`).
    pub fn name(self) -> &'static str {
        match self {
            TruthFamily::Sparse => "sparse",
            TruthFamily::Extended => "extended",
        }
    }

    fn stream(self) -> u64 {
        match self {
            TruthFamily::Sparse => 1,
            TruthFamily::Extended => 2,
        }
    }
}

/// Why a pulse shape could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TruthError {
    /// The FWHM or the sample interval is not a positive finite number.
    #[error("pulse FWHM {fwhm_ns} ns at {sample_ns} ns sampling is not usable")]
    BadPulse {
        /// FWHM, ns.
        fwhm_ns: f64,
        /// Sample interval, ns.
        sample_ns: f64,
    },
    /// The window is too short to hold any scatterer.
    #[error("{bins} bins are too few (at least {min})")]
    TooFewBins {
        /// Bins asked for.
        bins: usize,
        /// Minimum.
        min: usize,
    },
}

/// A sampled Gaussian outgoing pulse of `fwhm_ns` FWHM at `sample_ns` sampling, ±3.5 standard
/// deviations, unit sum, centred on its peak (so convolving with it does not shift anything).
pub fn gaussian_pulse(fwhm_ns: f64, sample_ns: f64) -> Result<Kernel, TruthError> {
    let mut k = Kernel::default();
    k.set_gaussian(fwhm_ns, sample_ns)
        .map_err(|_| TruthError::BadPulse { fwhm_ns, sample_ns })?;
    Ok(k)
}

/// One simulated pulse: its cross-section and the waveforms derived from it (all `bins` long).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TruthPulse {
    /// The scatterer cross-section per bin (signal units per bin, non-negative).
    pub cross_section: Vec<f32>,
    /// The truth waveform: the cross-section convolved with the 2 ns pulse.
    pub truth: Vec<f32>,
    /// The received waveform: the cross-section convolved with the system pulse, plus noise.
    pub received: Vec<f32>,
}

/// Generator of truth pulses: the same `(seed, family, index)` always gives the same
/// cross-section, whatever the pulse width, so results at different widths are comparable.
#[derive(Clone, Debug)]
pub struct TruthGenerator {
    bins: usize,
    seed: u64,
    truth_kernel: Kernel,
}

impl TruthGenerator {
    /// A generator of `bins`-bin waveforms at `sample_ns` sampling.
    pub fn new(bins: usize, sample_ns: f64, seed: u64) -> Result<Self, TruthError> {
        let min = 2 * MARGIN_BINS + 50;
        if bins < min {
            return Err(TruthError::TooFewBins { bins, min });
        }
        Ok(TruthGenerator {
            bins,
            seed,
            truth_kernel: gaussian_pulse(TRUTH_FWHM_NS, sample_ns)?,
        })
    }

    /// Bins per waveform.
    pub fn bins(&self) -> usize {
        self.bins
    }

    /// The 2 ns truth pulse.
    pub fn truth_kernel(&self) -> &Kernel {
        &self.truth_kernel
    }

    /// Writes pulse `index` of `family` into `out`: cross-section, truth, and the received
    /// waveform for the system pulse `system` with uniform noise in `[−a, a]`,
    /// `a = noise_fraction × max(noise-free received)` (dimensionless fraction of the peak).
    pub fn pulse(
        &self,
        family: TruthFamily,
        index: u64,
        system: &Kernel,
        noise_fraction: f32,
        out: &mut TruthPulse,
    ) {
        let n = self.bins;
        out.cross_section.clear();
        out.cross_section.resize(n, 0.0);
        let mut rng = self.rng(family, index, 0);
        match family {
            TruthFamily::Sparse => sparse(&mut rng, &mut out.cross_section),
            TruthFamily::Extended => extended(&mut rng, &mut out.cross_section),
        }
        out.truth.resize(n, 0.0);
        convolve_same(&out.cross_section, &self.truth_kernel, &mut out.truth);
        out.received.resize(n, 0.0);
        convolve_same(&out.cross_section, system, &mut out.received);
        let peak = out.received.iter().fold(0.0f32, |m, &v| m.max(v));
        let a = noise_fraction.max(0.0) * peak;
        if a > 0.0 {
            // Noise depends on the system pulse too (a different acquisition), through its length.
            let mut noise = self.rng(family, index, 1 + system.taps.len() as u64);
            for v in out.received.iter_mut() {
                *v += noise.random_range(-a..=a);
            }
        }
    }

    fn rng(&self, family: TruthFamily, index: u64, sub: u64) -> ChaCha8Rng {
        let mut rng = ChaCha8Rng::seed_from_u64(
            self.seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (sub << 48),
        );
        rng.set_stream(family.stream());
        rng
    }
}

/// 2 to 4 hard surfaces: the lowest is the ground; the others 3 to 40 bins apart above it.
fn sparse(rng: &mut ChaCha8Rng, sigma: &mut [f32]) {
    let n = sigma.len();
    let count = rng.random_range(2..=4usize);
    let ground = rng.random_range(n - MARGIN_BINS - 40..n - MARGIN_BINS);
    sigma[ground] = rng.random_range(0.4f32..1.0);
    let mut at = ground;
    for _ in 1..count {
        let gap = rng.random_range(3..=40usize);
        if at < MARGIN_BINS + gap {
            break;
        }
        at -= gap;
        sigma[at] = rng.random_range(0.15f32..0.8);
    }
}

/// 1 to 3 canopy layers of foliage clumps, attenuated with depth, over an attenuated ground.
fn extended(rng: &mut ChaCha8Rng, sigma: &mut [f32]) {
    let n = sigma.len();
    let ground = rng.random_range(n - MARGIN_BINS - 20..n - MARGIN_BINS);
    let layers = rng.random_range(1..=3usize);
    // Layers stack upwards from a few bins above the ground.
    let mut bottom = ground - rng.random_range(3..=15usize);
    for _ in 0..layers {
        let depth = rng.random_range(6..=30usize);
        if bottom < MARGIN_BINS + depth {
            break;
        }
        let top = bottom - depth;
        let clumps = rng.random_range(2..=5usize);
        for _ in 0..clumps {
            let centre = rng.random_range(top as f32..bottom as f32);
            let sd = rng.random_range(1.0f32..4.0);
            let density = rng.random_range(0.02f32..0.12);
            let lo = (centre - 4.0 * sd).max(top as f32) as usize;
            let hi = ((centre + 4.0 * sd) as usize).min(bottom);
            for (i, s) in sigma.iter_mut().enumerate().take(hi + 1).skip(lo) {
                let x = (i as f32 - centre) / sd;
                *s += density * (-0.5 * x * x).exp();
            }
        }
        bottom = top - rng.random_range(2..=12usize).min(top - MARGIN_BINS);
    }
    // Beer-Lambert: each bin is lit by what the bins above it let through.
    let extinction = 1.5f32;
    let mut above = 0.0f32;
    for s in sigma.iter_mut().take(ground) {
        let v = *s;
        *s = v * (-extinction * above).exp();
        above += v;
    }
    sigma[ground] = rng.random_range(0.3f32..0.9) * (-extinction * above).exp();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pulse_has_unit_sum_and_the_asked_fwhm() {
        let k = gaussian_pulse(8.0, 1.0).unwrap();
        let s: f32 = k.taps.iter().sum();
        assert!((s - 1.0).abs() < 1e-5);
        let peak = k.taps[k.center];
        // Half maximum lies 4 bins either side of the centre.
        let half = k.taps[k.center + 4] / peak;
        assert!((half - 0.5).abs() < 0.01, "{half}");
        assert!(gaussian_pulse(0.0, 1.0).is_err());
        assert!(gaussian_pulse(f64::NAN, 1.0).is_err());
    }

    #[test]
    fn pulses_are_deterministic_and_share_the_cross_section_across_widths() {
        let g = TruthGenerator::new(DEFAULT_BINS, 1.0, 7).unwrap();
        let k4 = gaussian_pulse(4.0, 1.0).unwrap();
        let k16 = gaussian_pulse(16.0, 1.0).unwrap();
        for family in TruthFamily::ALL {
            let (mut a, mut b, mut c) = Default::default();
            g.pulse(family, 3, &k4, 0.03, &mut a);
            g.pulse(family, 3, &k4, 0.03, &mut b);
            g.pulse(family, 3, &k16, 0.03, &mut c);
            let a: TruthPulse = a;
            assert_eq!(a, b);
            assert_eq!(a.cross_section, c.cross_section);
            assert_eq!(a.truth, c.truth);
            assert!(a.cross_section.iter().all(|&v| v >= 0.0));
            assert!(a.cross_section.iter().sum::<f32>() > 0.0);
            // Unit-sum pulses keep the area (away from the edges, where nothing lies).
            let area = |v: &[f32]| v.iter().sum::<f32>();
            assert!((area(&a.truth) - area(&a.cross_section)).abs() < 1e-4);
        }
    }

    #[test]
    fn noise_is_uniform_within_the_stated_amplitude() {
        let g = TruthGenerator::new(DEFAULT_BINS, 1.0, 1).unwrap();
        let k = gaussian_pulse(8.0, 1.0).unwrap();
        let (mut clean, mut noisy) = (TruthPulse::default(), TruthPulse::default());
        g.pulse(TruthFamily::Sparse, 0, &k, 0.0, &mut clean);
        g.pulse(TruthFamily::Sparse, 0, &k, 0.05, &mut noisy);
        let peak = clean.received.iter().fold(0.0f32, |m, &v| m.max(v));
        let max_dev = clean
            .received
            .iter()
            .zip(&noisy.received)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(max_dev <= 0.05 * peak * 1.0001 && max_dev > 0.03 * peak);
    }
}
