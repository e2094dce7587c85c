//! The deconvolve stage (`type = "deconvolve"`): every return segment of a denoised pulse is
//! deconvolved in place by the configured method and kernel.
//!
//! Configuration layout (TOML): the method is a nested table selected by its own `method` key,
//! the kernel an externally tagged value:
//!
//! ```toml
//! [[pipeline.stages]]
//! type = "deconvolve"
//! method = { method = "richardson_lucy", iterations = 20 }
//! kernel = "outgoing"                                   # the default
//! # kernel = { taps = { taps = [0.2, 0.6, 0.2], center = 1 } }   # calibrated response
//! # kernel = { flat_target = { ground_return = [...], outgoing = [...] } }  # measured one
//! max_samples = 4096
//! max_taps = 256
//! ```
//!
//! **System response in two stages** (the waveformlidar R package's order): a first
//! deconvolve stage with the calibrated response `h` (`taps`, or `flat_target`: measured from a
//! flat-target return and its outgoing pulse when the stage is built, see
//! [`response`](crate::signal::deconvolve::response)), then a second with
//! `kernel = "outgoing"`. Each stage deconvolves the return segments only; the outgoing
//! segment is left as recorded, because `h` is defined relative to the *recorded* outgoing
//! pulse (`ground return = outgoing ⊛ h`): deconvolving the outgoing pulse by `h` as well would
//! take `h` out twice. Every kernel is centred on its peak, so neither stage moves returns in
//! time (`docs/signal.md`).
//!
//! (Flattening the method's keys into the stage table is not used: serde's `flatten` cannot be
//! combined with `deny_unknown_fields`, and every table here rejects unknown keys.)
//!
//! Per pulse:
//!
//! - `signal.len() != raw.len()` (the denoise stage has not run) → dropped `not_denoised`;
//! - a segment indexing past the samples → rejected `segment_out_of_bounds`;
//! - a non-finite or non-positive sample interval → rejected `bad_digitizer_parameters`;
//! - `kernel = "outgoing"`: the kernel is rebuilt from the first outgoing segment's signal with
//!   [`Kernel::set_from_outgoing`]; no outgoing segment → dropped `no_outgoing`; an unusable one
//!   (no positive energy, non-finite, longer than `max_taps`) → dropped `bad_kernel`;
//! - each non-empty return segment is deconvolved into a scratch buffer and copied back; a
//!   [`DeconvError`](crate::signal::deconvolve::DeconvError) drops the pulse with its
//!   [`reason`](crate::signal::deconvolve::DeconvError::reason) (e.g. `non_finite_input`,
//!   `segment_too_long`), so NaN or infinite samples never travel on.
//!
//! Outgoing segments are left as they are. Buffers (method scratch, kernel, output) are sized
//! from `max_samples` and `max_taps` when the stage is built; nothing is allocated per pulse
//! (the Wiener filter plans its FFT once per padded length).

use serde::{Deserialize, Serialize};

use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::{Pulse, SegmentKind};
use crate::signal::deconvolve::response::response_from_flat_target;
use crate::signal::deconvolve::{Deconvolver, MethodConfig};
use crate::signal::kernel::Kernel;

/// Where the stage's kernel (system response) comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum KernelSource {
    /// Per shot, from the pulse's own outgoing segment (denoised volts): `kernel = "outgoing"`.
    #[default]
    Outgoing,
    /// A calibrated system impulse response: `kernel = { taps = { taps = [...], center = c } }`.
    /// Taps at the pulse's sample interval (normalised to unit sum), `center` the index of the
    /// zero-delay tap.
    Taps {
        /// The taps (any scale; the sum must be positive).
        taps: Vec<f32>,
        /// Index of the zero-delay tap.
        center: usize,
    },
    /// The system response measured on a flat target, computed once when the stage is built:
    /// `kernel = { flat_target = { ground_return = [...], outgoing = [...] } }` (see
    /// [`response_from_flat_target`]).
    FlatTarget {
        /// The flat (hard, near-nadir) target's return as recorded (counts or volts on a
        /// baseline, the median of its first 8 samples), at the pulse's sample interval.
        ground_return: Vec<f32>,
        /// The outgoing pulse recorded with that return, same units and interval.
        outgoing: Vec<f32>,
    },
}

impl KernelSource {
    /// The fixed kernel of a calibrated source (`taps` or `flat_target`), built and checked
    /// with at most `max_taps` taps, the flat-target response measured with `method`; `None`
    /// for `outgoing` (per shot). The error names the offending field.
    pub fn fixed_kernel(
        &self,
        method: &MethodConfig,
        max_taps: usize,
    ) -> Option<Result<Kernel, String>> {
        match self {
            KernelSource::Outgoing => None,
            KernelSource::Taps { taps, center } => {
                let mut k = Kernel::with_capacity(max_taps);
                Some(
                    k.set_from_taps(taps, *center, max_taps)
                        .map(|_| k)
                        .map_err(|e| format!("kernel.taps: {e}")),
                )
            }
            KernelSource::FlatTarget {
                ground_return,
                outgoing,
            } => Some(
                response_from_flat_target(ground_return, outgoing, method, max_taps)
                    .map_err(|e| format!("kernel.flat_target.{e}")),
            ),
        }
    }
}

/// Configuration of the deconvolve stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeconvolveConfig {
    /// The method and its settings (a table with its own `method = "..."` key). Required.
    pub method: MethodConfig,
    /// Kernel source. Default `"outgoing"`.
    #[serde(default)]
    pub kernel: KernelSource,
    /// Longest segment accepted, samples; longer ones drop the pulse `segment_too_long`.
    /// Default 4096.
    #[serde(default = "default_max_samples")]
    pub max_samples: usize,
    /// Longest kernel accepted, taps; a longer outgoing segment drops the pulse `bad_kernel`.
    /// Default 256.
    #[serde(default = "default_max_taps")]
    pub max_taps: usize,
    /// With `kernel = "outgoing"`, what happens to a pulse that recorded no outgoing segment
    /// (LAS waveform files never carry one): `"drop"` (counted `no_outgoing`; the default) or
    /// `"pass"` (passed on un-deconvolved, counted in the stage's `notes` as `no_outgoing`).
    #[serde(default)]
    pub missing_outgoing: MissingOutgoing,
}

/// What a deconvolve stage with `kernel = "outgoing"` does with a pulse without an outgoing
/// segment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MissingOutgoing {
    /// Drop it, counted under `no_outgoing`.
    #[default]
    Drop,
    /// Pass it on as it is (not deconvolved), counted in the stage's notes under `no_outgoing`.
    Pass,
}

fn default_max_samples() -> usize {
    4096
}
fn default_max_taps() -> usize {
    256
}

/// The fixed worst-case cost of a deconvolve stage per return segment, as its configuration
/// states it (`fwlidar validate` prints it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WorstCase {
    /// Longest segment accepted (`max_samples`), samples.
    pub samples: usize,
    /// Longest kernel: `max_taps` for `kernel = "outgoing"`, the calibrated kernel's length
    /// otherwise, taps.
    pub taps: usize,
    /// Iteration budget ([`MethodConfig::iteration_budget`]).
    pub iterations: u64,
    /// Floating-point operations for one segment of `samples` by a kernel of `taps`.
    pub flops: u64,
}

impl DeconvolveConfig {
    /// The stage's worst case per return segment (a pulse costs the sum over its return
    /// segments). The kernel of `flat_target` is measured to know its length (`max_taps` when
    /// that fails).
    pub fn worst_case(&self) -> WorstCase {
        let taps = match self.kernel.fixed_kernel(&self.method, self.max_taps) {
            Some(Ok(k)) => k.len(),
            _ => self.max_taps,
        };
        WorstCase {
            samples: self.max_samples,
            taps,
            iterations: self.method.iteration_budget(),
            flops: self.method.worst_case_flops(self.max_samples, taps),
        }
    }

    /// A configuration with the given method and every other field at its default.
    pub fn with_method(method: MethodConfig) -> Self {
        DeconvolveConfig {
            method,
            kernel: KernelSource::default(),
            max_samples: default_max_samples(),
            max_taps: default_max_taps(),
            missing_outgoing: MissingOutgoing::default(),
        }
    }
}

/// The deconvolve stage.
pub struct Deconvolve {
    config: DeconvolveConfig,
    method: Box<dyn Deconvolver>,
    kernel: Kernel,
    /// Set when a configured calibrated kernel is unusable (reported as a fatal error).
    kernel_error: Option<String>,
    /// Output of one segment, `max_samples`.
    out: Vec<f32>,
}

impl Deconvolve {
    /// Builds the stage and sizes its buffers. Never fails: an unusable calibrated kernel makes
    /// the first `process` call return a fatal error (configuration validation reports it
    /// before that).
    pub fn new(config: DeconvolveConfig) -> Self {
        let method = config.method.build(config.max_samples, config.max_taps);
        let mut kernel = Kernel::with_capacity(config.max_taps);
        let mut kernel_error = None;
        match config.kernel.fixed_kernel(&config.method, config.max_taps) {
            None => {}
            Some(Ok(k)) => kernel = k,
            Some(Err(e)) => kernel_error = Some(format!("calibrated kernel: {e}")),
        }
        Deconvolve {
            out: vec![0.0; config.max_samples],
            method,
            kernel,
            kernel_error,
            config,
        }
    }

    /// The configuration in force.
    pub fn config(&self) -> &DeconvolveConfig {
        &self.config
    }

    /// Buffer capacities (for the no-allocation test).
    #[cfg(test)]
    fn buffer_capacities(&self) -> [usize; 2] {
        [self.out.capacity(), self.kernel.taps.capacity()]
    }
}

impl Stage for Deconvolve {
    fn name(&self) -> &'static str {
        "deconvolve"
    }

    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        if let Some(message) = &self.kernel_error {
            let message = message.clone();
            out.drop_pulse(pulse, "bad_kernel");
            return Err(StageError::Fatal {
                stage: "deconvolve",
                message,
            });
        }
        if pulse.signal.len() != pulse.raw.len() {
            out.drop_pulse(pulse, "not_denoised");
            return Ok(());
        }
        let len = pulse.signal.len();
        if pulse.segments.iter().any(|s| s.range().end > len) {
            out.reject(pulse, "segment_out_of_bounds");
            return Ok(());
        }
        let sample_ns = pulse.sample_ns;
        if !(sample_ns.is_finite() && sample_ns > 0.0) {
            out.reject(pulse, "bad_digitizer_parameters");
            return Ok(());
        }
        if self.config.kernel == KernelSource::Outgoing {
            let Some(o) = pulse.outgoing() else {
                match self.config.missing_outgoing {
                    MissingOutgoing::Drop => out.drop_pulse(pulse, "no_outgoing"),
                    MissingOutgoing::Pass => out.emit_noted(pulse, "no_outgoing"),
                }
                return Ok(());
            };
            let range = pulse.segments[o].range();
            if self
                .kernel
                .set_from_outgoing(&pulse.signal[range], self.config.max_taps)
                .is_err()
            {
                out.drop_pulse(pulse, "bad_kernel");
                return Ok(());
            }
        }
        let noise_v = pulse.noise.noise_v;
        let mut failure: Option<&'static str> = None;
        for si in 0..pulse.segments.len() {
            let seg = pulse.segments[si];
            if seg.kind != SegmentKind::Return || seg.len == 0 {
                continue;
            }
            let range = seg.range();
            let n = range.len();
            if n > self.out.len() {
                failure = Some("segment_too_long");
                break;
            }
            let result = self.method.run(
                &pulse.signal[range.clone()],
                &self.kernel,
                noise_v,
                sample_ns,
                &mut self.out[..n],
            );
            match result {
                Ok(_) => pulse.signal[range].copy_from_slice(&self.out[..n]),
                Err(e) => {
                    failure = Some(e.reason());
                    break;
                }
            }
        }
        if let Some(reason) = failure {
            out.drop_pulse(pulse, reason);
            return Ok(());
        }
        out.emit(pulse);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::testing::run_stage;
    use crate::signal::deconvolve::{GoldConfig, RlConfig, WienerConfig};

    fn gauss(n: usize, centre: f32, sigma: f32, amp: f32) -> Vec<f32> {
        (0..n)
            .map(|i| {
                let d = (i as f32 - centre) / sigma;
                amp * (-0.5 * d * d).exp()
            })
            .collect()
    }

    /// A denoised pulse: a 41-sample outgoing Gaussian and one return of two echoes.
    fn denoised_pulse() -> Pulse {
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Outgoing, 0, -20.0, [0u16; 41]);
        p.push_segment(SegmentKind::Return, 0, 900.0, [0u16; 128]);
        p.signal = gauss(41, 20.0, 3.4, 1.0);
        let r1 = gauss(128, 40.0, 3.4, 0.5);
        let r2 = gauss(128, 80.0, 3.4, 0.3);
        p.signal.extend(r1.iter().zip(&r2).map(|(a, b)| a + b));
        p.noise.noise_v = 0.001;
        p
    }

    fn methods() -> [MethodConfig; 3] {
        [
            MethodConfig::RichardsonLucy(RlConfig::default()),
            MethodConfig::Gold(GoldConfig::default()),
            MethodConfig::Wiener(WienerConfig::default()),
        ]
    }

    #[test]
    fn deconvolve_stage_sharpens_returns_and_keeps_the_outgoing() {
        for m in methods() {
            let mut stage = Deconvolve::new(DeconvolveConfig::with_method(m.clone()));
            let before = denoised_pulse();
            let run = run_stage(&mut stage, [denoised_pulse()]).unwrap();
            assert_eq!(run.emitted.len(), 1, "{m:?}");
            let p = &run.emitted[0];
            assert_eq!(p.signal_of(0), before.signal_of(0));
            let ret = p.signal_of(1);
            assert!(ret.iter().all(|v| v.is_finite()));
            let peak = ret
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .unwrap();
            assert!((peak.0 as i32 - 40).abs() <= 1, "{m:?}: peak at {}", peak.0);
            assert!(*peak.1 > 0.6, "{m:?}: sharpened peak {}", peak.1);
        }
    }

    #[test]
    fn a_pulse_without_outgoing_is_passed_unchanged_and_noted_when_configured() {
        use crate::pipeline::{DropCounts, Emitter};
        use crate::pulse::PulsePool;
        let mut stage = Deconvolve::new(DeconvolveConfig {
            missing_outgoing: MissingOutgoing::Pass,
            ..DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig::default()))
        });
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Return, 0, 0.0, [0u16; 10]);
        p.signal = (0..10).map(|i| i as f32).collect();
        let before = p.signal.clone();
        let pool = PulsePool::new(2);
        let (mut out, mut dropped, mut errors, mut notes) = (
            Vec::new(),
            DropCounts::default(),
            0u64,
            DropCounts::default(),
        );
        let mut em =
            Emitter::new(&mut out, &pool, &mut dropped, &mut errors).with_notes(&mut notes);
        stage.process(Box::new(p), &mut em).unwrap();
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].signal, before, "not deconvolved");
        assert_eq!(dropped.total(), 0);
        assert_eq!(notes.get("no_outgoing"), 1);
    }

    #[test]
    fn deconvolve_stage_drop_reasons() {
        let mut stage = Deconvolve::new(DeconvolveConfig {
            max_samples: 150,
            ..DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig::default()))
        });
        let mut not_denoised = denoised_pulse();
        not_denoised.signal.clear();
        let mut no_outgoing = Pulse::default();
        no_outgoing.push_segment(SegmentKind::Return, 0, 0.0, [0u16; 10]);
        no_outgoing.signal = vec![1.0; 10];
        let mut bad_kernel = denoised_pulse();
        bad_kernel.signal[..41].fill(-1.0);
        let mut nan = denoised_pulse();
        nan.signal[50] = f32::NAN;
        let mut inf = denoised_pulse();
        inf.signal[60] = f32::INFINITY;
        let mut too_long = denoised_pulse();
        too_long.push_segment(SegmentKind::Return, 0, 0.0, [0u16; 160]); // > 150
        too_long.signal.extend([0.1f32; 160]);
        let mut oob = denoised_pulse();
        oob.segments[1].len = 500;
        let mut short = denoised_pulse();
        short.segments[1].len = 60;
        let run = run_stage(
            &mut stage,
            [
                not_denoised,
                no_outgoing,
                bad_kernel,
                nan,
                inf,
                too_long,
                oob,
                short,
            ],
        )
        .unwrap();
        assert_eq!(run.emitted.len(), 1);
        assert_eq!(run.dropped.get("not_denoised"), 1);
        assert_eq!(run.dropped.get("no_outgoing"), 1);
        assert_eq!(run.dropped.get("bad_kernel"), 1);
        assert_eq!(run.dropped.get("non_finite_input"), 2);
        assert_eq!(run.dropped.get("segment_too_long"), 1);
        assert_eq!(run.dropped.get("segment_out_of_bounds"), 1);
        assert_eq!(run.errors, 1);
        assert!(run.emitted[0].signal.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn deconvolve_stage_calibrated_kernel_and_fatal_bad_taps() {
        let cfg = DeconvolveConfig {
            kernel: KernelSource::Taps {
                taps: gauss(41, 20.0, 3.4, 1.0),
                center: 20,
            },
            ..DeconvolveConfig::with_method(MethodConfig::Gold(GoldConfig::default()))
        };
        let mut stage = Deconvolve::new(cfg);
        let mut p = denoised_pulse();
        p.segments.remove(0); // no outgoing needed with calibrated taps
        let run = run_stage(&mut stage, [p]).unwrap();
        assert_eq!(run.emitted.len(), 1);
        let bad = DeconvolveConfig {
            kernel: KernelSource::Taps {
                taps: vec![0.0; 3],
                center: 1,
            },
            ..DeconvolveConfig::with_method(MethodConfig::Gold(GoldConfig::default()))
        };
        let mut stage = Deconvolve::new(bad);
        assert!(matches!(
            run_stage(&mut stage, [denoised_pulse()]),
            Err(StageError::Fatal { .. })
        ));
    }

    /// A NEON-like asymmetric outgoing pulse (volts above baseline): 2.5-bin Gaussian rise,
    /// 6-bin exponential tail, peak at bin 12 of 48. Its centroid lies ~2.5 bins after the peak.
    fn asymmetric_outgoing() -> Vec<f32> {
        (0..48)
            .map(|i| {
                let t = i as f32 - 12.0;
                if t < 0.0 {
                    (-0.5 * (t / 2.5).powi(2)).exp()
                } else {
                    (-t / 6.0).exp()
                }
            })
            .collect()
    }

    #[test]
    fn deconvolve_stage_zero_phase_returns_stay_at_their_time() {
        // Point targets at bins 60 and 130 of a 200-sample return segment echo the outgoing
        // pulse: sample i of the echo of a target at t is a · outgoing[i − t + peak], the
        // outgoing pulse's peak (bin 12) being the emission reference. Through the stage (kernel
        // from the pulse's own outgoing segment) each target must come back at its own bin; an
        // alignment on the centroid would put them ~2 bins later.
        let out = asymmetric_outgoing();
        let total: f32 = out.iter().sum();
        let centroid = out
            .iter()
            .enumerate()
            .map(|(i, v)| i as f32 * v)
            .sum::<f32>()
            / total;
        assert!(
            centroid - 12.0 > 1.5,
            "centroid {centroid}: the test would not tell"
        );
        let targets = [(60usize, 0.8f32), (130, 0.5)];
        let mut ret = vec![0.0f32; 200];
        for (t, a) in targets {
            for (i, r) in ret.iter_mut().enumerate() {
                let j = i as i64 - t as i64 + 12;
                if (0..out.len() as i64).contains(&j) {
                    *r += a * out[j as usize];
                }
            }
        }
        let mut methods = methods().to_vec();
        methods.push(MethodConfig::Nnls(Default::default()));
        for m in methods {
            let mut p = Pulse::default();
            p.push_segment(SegmentKind::Outgoing, 0, -12.0, [0u16; 48]);
            p.push_segment(SegmentKind::Return, 0, 900.0, [0u16; 200]);
            p.signal = out.clone();
            p.signal.extend(&ret);
            p.noise.noise_v = 0.001;
            let mut stage = Deconvolve::new(DeconvolveConfig::with_method(m.clone()));
            let run = run_stage(&mut stage, [p]).unwrap();
            assert_eq!(run.emitted.len(), 1, "{m:?}");
            let y = run.emitted[0].signal_of(1);
            for (t, _) in targets {
                let window = &y[t - 8..t + 9];
                let peak = window
                    .iter()
                    .enumerate()
                    .max_by(|a, b| a.1.total_cmp(b.1))
                    .unwrap()
                    .0 as i64
                    - 8;
                assert_eq!(
                    peak,
                    0,
                    "{m:?}: target at {t} came back at {}",
                    t as i64 + peak
                );
            }
        }
    }

    #[test]
    fn deconvolve_stage_two_stage_system_response_keeps_returns_in_place() {
        // The full response is outgoing ⊛ h, h a 5-tap asymmetric receiver response measured
        // on a flat target: stage 1 (flat_target) then stage 2 (outgoing) put a point target
        // back at its bin, while the outgoing segment stays as recorded.
        let out = asymmetric_outgoing();
        let mut h = Kernel::default();
        h.set_from_taps(&[0.1, 0.5, 0.25, 0.1, 0.05], 1, 8).unwrap();
        let mut full = vec![0.0f32; out.len()];
        crate::signal::kernel::convolve_same(&out, &h, &mut full);
        // Flat target: its outgoing pulse on a pedestal (the same shape) and its return,
        // `full` 20 bins later, padded to 100 samples.
        let pedestal = 200.0f32;
        let target_out: Vec<f32> = out.iter().map(|v| pedestal + 500.0 * v).collect();
        let ground: Vec<f32> = (0..100)
            .map(|i| {
                let j = i as i64 - 20;
                pedestal
                    + if (0..full.len() as i64).contains(&j) {
                        500.0 * full[j as usize]
                    } else {
                        0.0
                    }
            })
            .collect();
        let gold = MethodConfig::Gold(GoldConfig {
            iterations: 200,
            repetitions: 1,
            boost: 1.0,
        });
        let t = 90usize;
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Outgoing, 0, -12.0, [0u16; 48]);
        p.push_segment(SegmentKind::Return, 0, 900.0, [0u16; 200]);
        p.signal = out.clone();
        let mut ret = vec![0.0f32; 200];
        for (i, r) in ret.iter_mut().enumerate() {
            let j = i as i64 - t as i64 + 12;
            if (0..full.len() as i64).contains(&j) {
                *r = 0.7 * full[j as usize];
            }
        }
        p.signal.extend(&ret);
        p.noise.noise_v = 0.001;
        let mut first = Deconvolve::new(DeconvolveConfig {
            kernel: KernelSource::FlatTarget {
                ground_return: ground,
                outgoing: target_out,
            },
            ..DeconvolveConfig::with_method(gold.clone())
        });
        let mut second = Deconvolve::new(DeconvolveConfig::with_method(gold));
        let run = run_stage(&mut first, [p]).unwrap();
        assert_eq!(run.emitted.len(), 1);
        let run = run_stage(&mut second, run.emitted.into_iter().map(|p| *p)).unwrap();
        assert_eq!(run.emitted.len(), 1);
        let p = &run.emitted[0];
        assert_eq!(
            p.signal_of(0),
            &out[..],
            "the outgoing segment is left as recorded"
        );
        let y = p.signal_of(1);
        assert!(y.iter().all(|v| v.is_finite() && *v >= 0.0));
        let peak = y
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap()
            .0;
        assert_eq!(peak, t, "two-stage result peaks at {peak}, target at {t}");
        // Sharper than the outgoing-only deconvolution of the same return: h is removed too.
        let mut only = Deconvolve::new(DeconvolveConfig::with_method(MethodConfig::Gold(
            GoldConfig {
                iterations: 200,
                repetitions: 1,
                boost: 1.0,
            },
        )));
        let mut q = Pulse::default();
        q.push_segment(SegmentKind::Outgoing, 0, -12.0, [0u16; 48]);
        q.push_segment(SegmentKind::Return, 0, 900.0, [0u16; 200]);
        q.signal = out.clone();
        q.signal.extend(&ret);
        let single = run_stage(&mut only, [q]).unwrap();
        let z = single.emitted[0].signal_of(1);
        assert!(
            y[t] > z[t],
            "two-stage peak {} vs outgoing only {}",
            y[t],
            z[t]
        );
    }

    #[test]
    fn deconvolve_stage_does_not_grow_buffers() {
        for m in methods() {
            let mut stage = Deconvolve::new(DeconvolveConfig::with_method(m));
            run_stage(&mut stage, [denoised_pulse()]).unwrap();
            let caps = stage.buffer_capacities();
            let run = run_stage(&mut stage, (0..200).map(|_| denoised_pulse())).unwrap();
            assert_eq!(run.emitted.len(), 200);
            assert_eq!(stage.buffer_capacities(), caps);
        }
    }

    fn parse(text: &str) -> Result<DeconvolveConfig, toml::de::Error> {
        toml::from_str(text)
    }

    #[test]
    fn deconvolve_config_toml_round_trip_and_unknown_fields() {
        let c = parse("method = { method = \"richardson_lucy\" }").unwrap();
        assert_eq!(
            c,
            DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig::default()))
        );
        let text = "max_taps = 64\n[method]\nmethod = \"gold\"\niterations = 10\nrepetitions = 3\nboost = 1.5\n[kernel.taps]\ntaps = [0.25, 0.5, 0.25]\ncenter = 1\n";
        let c = parse(text).unwrap();
        assert_eq!(c.max_taps, 64);
        assert_eq!(
            c.method,
            MethodConfig::Gold(GoldConfig {
                iterations: 10,
                repetitions: 3,
                boost: 1.5
            })
        );
        assert_eq!(
            c.kernel,
            KernelSource::Taps {
                taps: vec![0.25, 0.5, 0.25],
                center: 1
            }
        );
        let mut all = vec![c];
        for m in methods() {
            all.push(DeconvolveConfig::with_method(m));
        }
        all.push(DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(
            RlConfig {
                iterations: 7,
                early_stop: Some(1e-3),
            },
        )));
        for c in all {
            let text = toml::to_string(&c).unwrap();
            assert_eq!(parse(&text).unwrap(), c, "{text}");
        }
        for bad in [
            "method = { method = \"richardson_lucy\" }\nbogus = 1",
            "method = { method = \"richardson_lucy\", bogus = 1 }",
            "method = { method = \"wiener\", iterations = 3 }",
            "method = { method = \"gold\" }\nkernel = { taps = { taps = [1.0], center = 0, x = 1 } }",
            "method = { method = \"gold\" }\nkernel = \"incoming\"",
            "kernel = \"outgoing\"",
        ] {
            assert!(parse(bad).is_err(), "{bad}");
        }
    }
}
