//! Forest structure metrics of one pulse (what the `metrics` stage, `stages/metrics.rs`,
//! measures on every pulse): [`WaveformMetrics`] from its return waveform.
//!
//! Per pulse it measures the return segment with the most samples (GEDI and most digitizers
//! record one), from the raw waveform (`source = "raw"`, counts converted to signal units with
//! the pulse's gain and offset) or the processed signal (`source = "signal"`). Noise: the
//! input's own figures when it states them ([`Pulse::stated_noise`], GEDI) and the raw waveform
//! is measured; otherwise the upper-clipped median and normalised median absolute deviation
//! (× 1.4826) of the measured waveform (the denoise stage's robust baseline: samples more than
//! 3 σ above the median are dropped and both taken again), which holds when echoes fill half
//! the segment or more (grass under a 64-sample window). Smoothing:
//! `smoothing_sigma_ns`, or the σ of the pulse's outgoing pulse (its FWHM / 2.355).
//!
//! A pulse without metrics gets them with a status saying why.

use crate::forest::pulse_metrics::{MetricsComputer, MetricsConfig, MetricsSource, WaveformInput};
use crate::pulse::waveform_metrics::WaveformMetrics;
use crate::pulse::{Pulse, SegmentKind, StatedNoise};
use crate::signal::robust_noise::RobustNoise;

/// `2 √(2 ln 2)`: FWHM of a Gaussian in units of σ.
const FWHM_PER_SIGMA: f64 = 2.354_820_045;

/// Measures the metrics of whole pulses, buffers sized once.
pub struct Metrics {
    config: MetricsConfig,
    computer: MetricsComputer,
    work: Vec<f32>,
    /// Buffers of the noise estimate.
    noise: RobustNoise,
}

impl Metrics {
    /// A measurer with `config`.
    pub fn new(config: MetricsConfig) -> Self {
        Metrics {
            config,
            computer: MetricsComputer::with_capacity(2048),
            work: Vec::with_capacity(2048),
            noise: RobustNoise::with_capacity(2048),
        }
    }

    /// The metrics of one pulse (what the `metrics` stage stores in [`Pulse::metrics`]).
    pub fn measure(&mut self, p: &Pulse) -> WaveformMetrics {
        let Some(seg_i) = p
            .segments
            .iter()
            .enumerate()
            .filter(|(_, s)| s.kind == SegmentKind::Return)
            .max_by_key(|(i, s)| (s.len, std::cmp::Reverse(*i)))
            .map(|(i, _)| i)
        else {
            return WaveformMetrics::default();
        };
        let seg = p.segments[seg_i];
        let range = seg.range();
        self.work.clear();
        let stated = match self.config.source {
            MetricsSource::Raw => {
                let Some(raw) = p.raw.get(range.clone()) else {
                    return WaveformMetrics::default();
                };
                self.work.extend(raw.iter().map(|&c| p.counts_to_volts(c)));
                p.stated_noise
            }
            MetricsSource::Signal => {
                let Some(sig) = p.signal.get(range.clone()) else {
                    return WaveformMetrics::default();
                };
                self.work.extend_from_slice(sig);
                // The denoise stage removed the baseline and measured the noise (a mean
                // absolute deviation: × √(π/2) for σ); without it, the robust estimate.
                let nv = p.noise.noise_v;
                (nv.is_finite() && nv > 0.0).then(|| StatedNoise {
                    mean: 0.0,
                    stddev: nv * std::f32::consts::FRAC_PI_2.sqrt(),
                })
            }
        };
        let (mean, sd) = match (stated, self.config.source) {
            (Some(n), _) => (f64::from(n.mean), f64::from(n.stddev)),
            // The raw samples are the counts in signal units: sorted by counting.
            (None, MetricsSource::Raw) => {
                let (level, sigma) = self
                    .noise
                    .level_and_sigma_of_counts(&p.raw[range], |c| p.counts_to_volts(c));
                (f64::from(level), f64::from(sigma))
            }
            (None, MetricsSource::Signal) => self.robust_noise(),
        };
        // The outgoing pulse's σ, measured once when the smoothing or the pulse's σ is taken
        // from it (raw waveforms only).
        let raw = self.config.source == MetricsSource::Raw;
        let outgoing =
            if raw && !(self.config.smoothing_sigma_ns > 0.0 && self.config.pulse_sigma_ns > 0.0) {
                outgoing_sigma_ns(p)
            } else {
                None
            };
        let smoothing = if self.config.smoothing_sigma_ns > 0.0 {
            self.config.smoothing_sigma_ns
        } else if !raw {
            // Already low-passed (and deconvolved): smoothing by the outgoing pulse would undo
            // the deconvolution.
            0.0
        } else {
            outgoing.unwrap_or(MetricsConfig::FALLBACK_SMOOTHING_NS)
        };
        let pulse_sigma = if self.config.pulse_sigma_ns > 0.0 {
            self.config.pulse_sigma_ns
        } else if raw {
            outgoing.unwrap_or(0.0)
        } else {
            0.0
        };
        let input = WaveformInput {
            samples: &self.work,
            pulse_sigma_ns: pulse_sigma,
            start_ns: seg.start_ns,
            sample_ns: p.sample_ns,
            noise_mean: mean,
            noise_sd: sd,
            smoothing_ns: smoothing,
            geometry: p.geometry,
            geographic: false,
        };
        self.computer.compute(&self.config, &input)
    }

    /// Noise level and σ of the waveform in `work`: the upper-clipped median and MAD (the
    /// denoise stage's robust baseline), so a return filling half the window does not raise them.
    fn robust_noise(&mut self) -> (f64, f64) {
        let (level, sigma) = self.noise.level_and_sigma(&self.work);
        (f64::from(level), f64::from(sigma))
    }
}

/// σ of the pulse's outgoing pulse, ns: its FWHM above the segment's first sample / 2.355.
fn outgoing_sigma_ns(p: &Pulse) -> Option<f64> {
    let i = p.outgoing()?;
    let raw = p.raw.get(p.segments[i].range())?;
    pulse_sigma_ns(raw, p.sample_ns)
}

/// σ of a recorded pulse, ns: its full width at half maximum above its base (the lower of its
/// first and last samples), to a fraction of a sample, / 2.355. `None` for fewer than three
/// samples, no peak above the base, or a width that is not a positive number.
pub fn pulse_sigma_ns<T: Copy + Into<f64>>(samples: &[T], sample_ns: f64) -> Option<f64> {
    if samples.len() < 3 {
        return None;
    }
    let v = |j: usize| -> f64 { samples[j].into() };
    let n = samples.len();
    let base = v(0).min(v(n - 1));
    let mut k = 0;
    for j in 1..n {
        // The last of equal maxima, as before.
        if v(j) >= v(k) {
            k = j;
        }
    }
    let peak = v(k);
    if peak.is_nan() || peak <= base {
        return None;
    }
    let half = base + 0.5 * (peak - base);
    let mut left = 0.0;
    let mut j = k;
    while j > 0 && v(j - 1) > half {
        j -= 1;
    }
    if j > 0 {
        left = (j - 1) as f64 + (half - v(j - 1)) / (v(j) - v(j - 1));
    }
    let mut r = k;
    while r + 1 < n && v(r + 1) > half {
        r += 1;
    }
    let right = if r + 1 < n {
        r as f64 + (v(r) - half) / (v(r) - v(r + 1))
    } else {
        r as f64
    };
    let fwhm = (right - left) * sample_ns;
    (fwhm > 0.0 && fwhm.is_finite()).then_some(fwhm / FWHM_PER_SIGMA)
}
