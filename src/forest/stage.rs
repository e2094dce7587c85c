//! The `metrics` stage: forest structure metrics of every pulse ([`WaveformMetrics`], written
//! by the `pulse_metrics.csv` sink), after decompose.
//!
//! Per pulse it measures the return segment with the most samples (GEDI and most digitizers
//! record one), from the raw waveform (`source = "raw"`, counts converted to signal units with
//! the pulse's gain and offset) or the processed signal (`source = "signal"`). Noise: the
//! input's own figures when it states them ([`Pulse::stated_noise`], GEDI) and the raw waveform
//! is measured; otherwise the median and the normalised median absolute deviation (× 1.4826) of
//! the measured waveform, which holds while echoes fill less than half the segment. Smoothing:
//! `smoothing_sigma_ns`, or the σ of the pulse's outgoing pulse (its FWHM / 2.355).
//!
//! Never drops a pulse: a pulse without metrics carries a status saying why.

use crate::forest::pulse_metrics::{
    MetricsComputer, MetricsConfig, MetricsSource, MetricsStatus, WaveformInput, WaveformMetrics,
};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::{Pulse, SegmentKind};

/// `2 √(2 ln 2)`: FWHM of a Gaussian in units of σ.
const FWHM_PER_SIGMA: f64 = 2.354_820_045;

/// The metrics stage.
pub struct Metrics {
    config: MetricsConfig,
    computer: MetricsComputer,
    work: Vec<f32>,
    sorted: Vec<f32>,
}

impl Metrics {
    /// A stage with `config`.
    pub fn new(config: MetricsConfig) -> Self {
        Metrics {
            config,
            computer: MetricsComputer::with_capacity(2048),
            work: Vec::with_capacity(2048),
            sorted: Vec::with_capacity(2048),
        }
    }

    /// The metrics of one pulse (what [`Stage::process`] stores in [`Pulse::metrics`]).
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
                None
            }
        };
        let (mean, sd) = match stated {
            Some(n) => (f64::from(n.mean), f64::from(n.stddev)),
            None => self.robust_noise(),
        };
        let smoothing = if self.config.smoothing_sigma_ns > 0.0 {
            self.config.smoothing_sigma_ns
        } else {
            outgoing_sigma_ns(p).unwrap_or(MetricsConfig::FALLBACK_SMOOTHING_NS)
        };
        let input = WaveformInput {
            samples: &self.work,
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

    fn robust_noise(&mut self) -> (f64, f64) {
        self.sorted.clear();
        self.sorted.extend_from_slice(&self.work);
        let n = self.sorted.len();
        if n == 0 {
            return (f64::NAN, f64::NAN);
        }
        let mid = n / 2;
        let (_, med, _) = self.sorted.select_nth_unstable_by(mid, f32::total_cmp);
        let med = *med;
        for v in &mut self.sorted {
            *v = (*v - med).abs();
        }
        let (_, mad, _) = self.sorted.select_nth_unstable_by(mid, f32::total_cmp);
        (f64::from(med), 1.4826 * f64::from(*mad))
    }
}

/// σ of the pulse's outgoing pulse, ns: its FWHM above the segment's first sample / 2.355.
fn outgoing_sigma_ns(p: &Pulse) -> Option<f64> {
    let i = p.outgoing()?;
    let raw = p.raw.get(p.segments[i].range())?;
    if raw.len() < 3 {
        return None;
    }
    let base = f64::from(raw[0].min(raw[raw.len() - 1]));
    let (k, &peak) = raw.iter().enumerate().max_by_key(|(_, v)| **v)?;
    let half = base + 0.5 * (f64::from(peak) - base);
    if f64::from(peak) <= base {
        return None;
    }
    let v = |j: usize| f64::from(raw[j]);
    let mut left = 0.0;
    let mut j = k;
    while j > 0 && v(j - 1) > half {
        j -= 1;
    }
    if j > 0 {
        left = (j - 1) as f64 + (half - v(j - 1)) / (v(j) - v(j - 1));
    }
    let mut r = k;
    while r + 1 < raw.len() && v(r + 1) > half {
        r += 1;
    }
    let right = if r + 1 < raw.len() {
        r as f64 + (v(r) - half) / (v(r) - v(r + 1))
    } else {
        r as f64
    };
    let fwhm = (right - left) * p.sample_ns;
    (fwhm > 0.0 && fwhm.is_finite()).then_some(fwhm / FWHM_PER_SIGMA)
}

impl Stage for Metrics {
    fn name(&self) -> &'static str {
        "metrics"
    }

    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        let m = self.measure(&pulse);
        pulse.metrics = Some(m);
        if m.status != MetricsStatus::Ok {
            // Counted by the sink's report by status; the pulse goes on.
        }
        out.emit(pulse);
        Ok(())
    }
}
