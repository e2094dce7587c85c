//! The `deconvolve` stage: every return segment of a denoised pulse is deconvolved in place by
//! the configured method ([`crate::signal::deconvolve`]) and kernel. The stage's configuration,
//! [`DeconvolveConfig`], is its own: the kernel source, the gate, the target pulse, the buffers
//! and the policies; the method's settings ([`MethodConfig`]) belong to the method.
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
//! long_kernel = "cut"      # an outgoing pulse longer than max_taps: "cut" or "drop"
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
//!   [`Kernel::set_from_outgoing_support`]: the pulse's support (the samples around its peak
//!   standing out of the noise by more than 3 × the pulse's `noise_v`, from the baseline the
//!   denoise stage removed), negative lobes clipped, unit sum, centred on the peak. No
//!   outgoing segment → dropped `no_outgoing` (or passed, `missing_outgoing = "pass"`); an
//!   unusable one (a non-finite sample, no pulse above its baseline or its noise) → dropped
//!   `bad_kernel`; a support longer than `max_taps` → cut to `max_taps` around the peak and
//!   noted `kernel_over_max_taps` (`long_kernel = "cut"`, the default; logged once) or dropped
//!   `kernel_over_max_taps` (`"drop"`);
//! - return samples at the digitizer's full scale (`2^bits − 1` counts: the receiver
//!   saturated) are flagged and left out of the fit by the methods that can (NNLS,
//!   [`Deconvolver::run_excluding`]); the pulse is noted `clipped_samples`;
//! - each non-empty return segment is deconvolved into a scratch buffer and copied back; a
//!   [`DeconvError`](crate::signal::deconvolve::DeconvError) drops the pulse with its
//!   [`reason`](crate::signal::deconvolve::DeconvError::reason) (e.g. `non_finite_input`,
//!   `segment_too_long`), so NaN or infinite samples never travel on.
//!
//! Outgoing segments are left as they are. Buffers (method scratch, kernel, output) are sized
//! from `max_samples` and `max_taps` when the stage is built; nothing is allocated per pulse
//! (the Wiener filter plans its FFT once per padded length).

use serde::{Deserialize, Serialize};

use super::{
    Advice, BuildError, MAX_SEGMENT_SAMPLES, MIN_SEGMENT_SAMPLES, RunContext, StageKind,
};
use crate::core::validate::{Validate, Validator, field};
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::{Pulse, SegmentKind, Verdict};
use crate::signal::deconvolve::GateError;
use crate::signal::deconvolve::response::ResponseError;
use crate::signal::deconvolve::richardson_lucy::MAX_COARSE_ITERATIONS;
use crate::signal::deconvolve::response::response_from_flat_target;
use crate::signal::deconvolve::{
    Deconvolver, Gate, Gated, MethodConfig, NnlsConfig, RlConfig, Targeted, WienerConfig,
};
use crate::signal::kernel::{Kernel, RecordLevels};
use crate::signal::learned_response::ResponseFile;

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
    /// The system response learned from the run's own input, per digitizer channel
    /// ([`crate::signal::learned_response`]): replay learns it from the input's first pulses
    /// and freezes it, as for `decompose`'s `model = "response"`: `kernel = "learned"`. For
    /// data whose outgoing pulse is not recorded (LAS waveform files) or is not the shape the
    /// receiver sees.
    Learned,
    /// A learned response file (`fwlidar response learn --out FILE`; path from the working
    /// folder), per channel: `kernel = { response = "FILE" }`.
    Response(std::path::PathBuf),
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
            KernelSource::Outgoing | KernelSource::Learned | KernelSource::Response(_) => None,
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
    /// The echo-window gate ([`gate`](crate::signal::deconvolve::gate)): `"off"` (every return
    /// segment deconvolved whole), `"on"` or `{ threshold_noise = K }` (only the windows
    /// around samples above `K × noise_v`, widened by the kernel's length on both sides; 0
    /// elsewhere). Default (key absent): on with `K = 3` for `richardson_lucy` and `gold`, off
    /// for `wiener` and `nnls` (which do not support it: naming it with them is an error).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gate: Option<Gate>,
    /// The method and its settings (a table with its own `method = "..."` key). Required.
    pub method: MethodConfig,
    /// Kernel source. Default `"outgoing"`.
    #[serde(default)]
    pub kernel: KernelSource,
    /// Deliver the result as seen by a Gaussian target pulse of this FWHM, ns (e.g. 2), instead
    /// of as the cross-section itself ([`target`](crate::signal::deconvolve::target)):
    /// Richardson-Lucy, Gold and Wiener deconvolve by the kernel that maps the target pulse to
    /// the system pulse, NNLS draws its spikes as the target pulse. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_fwhm_ns: Option<f64>,
    /// Longest segment accepted, samples; longer ones drop the pulse `segment_too_long`.
    /// Default 4096.
    #[serde(default = "default_max_samples")]
    pub max_samples: usize,
    /// Longest kernel, taps: the buffers and the worst-case cost are sized for it. With
    /// `kernel = "outgoing"` the kernel is the outgoing pulse's support (the samples around its
    /// peak standing out of its noise, [`pulse_support`](crate::signal::kernel::pulse_support)); a
    /// support longer than this is handled per `long_kernel`. Default 256.
    #[serde(default = "default_max_taps")]
    pub max_taps: usize,
    /// With `kernel = "outgoing"`, what happens when the outgoing pulse's support is longer
    /// than `max_taps`: `"cut"` (the kernel is cut to the `max_taps` samples around the peak
    /// holding the most energy, the pulse deconvolved and counted in the stage's `notes` as
    /// `kernel_over_max_taps`; the default) or `"drop"` (dropped, counted
    /// `kernel_over_max_taps`).
    #[serde(default)]
    pub long_kernel: LongKernel,
    /// With `kernel = "outgoing"`, what happens to a pulse that recorded no outgoing segment
    /// (LAS waveform files never carry one): `"drop"` (counted `no_outgoing`; the default) or
    /// `"pass"` (passed on un-deconvolved, counted in the stage's `notes` as `no_outgoing`).
    #[serde(default)]
    pub missing_outgoing: MissingOutgoing,
    /// With `kernel = "learned"` or `{ response = "FILE" }`: the response in use, resolved
    /// when the run is put together (never in a file).
    #[serde(skip)]
    pub learned: Option<std::sync::Arc<ResponseFile>>,
    /// Why the response file could not be read, reported when the stage is built.
    #[serde(skip)]
    pub learned_error: Option<String>,
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

/// What a deconvolve stage with `kernel = "outgoing"` does with an outgoing pulse whose support
/// is longer than `max_taps`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LongKernel {
    /// Cut the kernel to `max_taps` around the peak, deconvolve, count the note
    /// `kernel_over_max_taps`.
    #[default]
    Cut,
    /// Drop the pulse, counted under `kernel_over_max_taps`.
    Drop,
}

/// Note (`long_kernel = "cut"`) or drop reason (`"drop"`) of a pulse whose outgoing pulse's
/// support is longer than `max_taps`.
pub const KERNEL_OVER_MAX_TAPS: &str = "kernel_over_max_taps";

/// Note of a pulse with return samples at the digitizer's full scale (the receiver saturated).
pub const CLIPPED_SAMPLES: &str = "clipped_samples";

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

impl Default for DeconvolveConfig {
    /// Richardson-Lucy with its defaults (in a file the method is required).
    fn default() -> Self {
        DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(Default::default()))
    }
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

    /// The gate in force: the configured one, or [`Gate::default_for`] the method.
    pub fn effective_gate(&self) -> Gate {
        self.gate.unwrap_or_else(|| Gate::default_for(&self.method))
    }

    /// A configuration with the given method and every other field at its default.
    pub fn with_method(method: MethodConfig) -> Self {
        DeconvolveConfig {
            gate: None,
            method,
            kernel: KernelSource::default(),
            target_fwhm_ns: None,
            max_samples: default_max_samples(),
            max_taps: default_max_taps(),
            missing_outgoing: MissingOutgoing::default(),
            long_kernel: LongKernel::default(),
            learned: None,
            learned_error: None,
        }
    }
}

/// The deconvolve stage.
pub struct Deconvolve {
    config: DeconvolveConfig,
    /// The method behind the configured echo-window gate, to the target pulse if one is set.
    method: Targeted,
    kernel: Kernel,
    /// With a learned response: one kernel per digitizer channel (the first, learned from the
    /// most echoes, for a channel it does not know); empty otherwise.
    channel_kernels: Vec<(u16, Kernel)>,
    /// Output of one segment, `max_samples`.
    out: Vec<f32>,
    /// The samples of one segment at the digitizer's full scale, `max_samples`.
    clipped: Vec<bool>,
    /// Set once the first kernel was cut to `max_taps` (logged once per stage).
    warned_cut: bool,
}

impl Deconvolve {
    /// Builds the stage and sizes its buffers. Fails when a calibrated kernel (`taps`,
    /// `flat_target`) is unusable (configuration validation reports it before that, naming the
    /// field).
    pub fn new(config: DeconvolveConfig) -> Result<Self, BuildError> {
        let method = Targeted::new(
            Box::new(Gated::build(
                &config.method,
                config.effective_gate(),
                config.max_samples,
                config.max_taps,
            )),
            config.target_fwhm_ns,
            config.max_samples,
            config.max_taps,
        );
        let kernel = match config.kernel.fixed_kernel(&config.method, config.max_taps) {
            None => Kernel::with_capacity(config.max_taps),
            Some(Ok(k)) => k,
            Some(Err(e)) => {
                return Err(BuildError {
                    kind: "deconvolve",
                    message: format!("calibrated kernel: {e}"),
                });
            }
        };
        let channel_kernels = learned_kernels(&config).map_err(|message| BuildError {
            kind: "deconvolve",
            message,
        })?;
        Ok(Deconvolve {
            channel_kernels,
            out: vec![0.0; config.max_samples],
            clipped: Vec::with_capacity(config.max_samples),
            method,
            kernel,
            config,
            warned_cut: false,
        })
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
        let verdict = self.deconvolve_pulse(&mut pulse);
        out.give(pulse, verdict);
        Ok(())
    }
}

impl Deconvolve {
    /// Deconvolves every return segment of `pulse` in place (see the module documentation for
    /// what is dropped, rejected or noted).
    pub fn deconvolve_pulse(&mut self, pulse: &mut Pulse) -> Verdict {
        if pulse.signal.len() != pulse.raw.len() {
            return Verdict::Drop("not_denoised");
        }
        let len = pulse.signal.len();
        if pulse.segments.iter().any(|s| s.range().end > len) {
            return Verdict::Reject("segment_out_of_bounds");
        }
        let sample_ns = pulse.sample_ns;
        if !(sample_ns.is_finite() && sample_ns > 0.0) {
            return Verdict::Reject("bad_digitizer_parameters");
        }
        let mut cut = false;
        if self.config.kernel == KernelSource::Outgoing {
            let Some(o) = pulse.outgoing() else {
                return match self.config.missing_outgoing {
                    MissingOutgoing::Drop => Verdict::Drop("no_outgoing"),
                    MissingOutgoing::Pass => Verdict::noted("no_outgoing"),
                };
            };
            let range = pulse.segments[o].range();
            // The denoise stage removed the baseline and measured the noise level.
            let noise_v = pulse.noise.noise_v;
            let known = RecordLevels {
                baseline_removed: true,
                noise: (noise_v.is_finite() && noise_v > 0.0).then_some(noise_v),
            };
            match self.kernel.set_from_outgoing_support(
                &pulse.signal[range],
                known,
                self.config.max_taps,
            ) {
                Err(_) => return Verdict::Drop("bad_kernel"),
                Ok(fit) if fit.was_cut() => {
                    if self.config.long_kernel == LongKernel::Drop {
                        return Verdict::Drop(KERNEL_OVER_MAX_TAPS);
                    }
                    self.warn_cut_once(fit.span);
                    cut = true;
                }
                Ok(_) => {}
            }
        }
        let noise_v = pulse.noise.noise_v;
        let mut failure: Option<&'static str> = None;
        let mut any_clipped = false;
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
            let y = &pulse.signal[range.clone()];
            let kernel = channel_kernel(&self.channel_kernels, &self.kernel, seg.channel);
            let full_scale = pulse.full_scale_dn();
            let result = if flag_full_scale(&pulse.raw[range.clone()], full_scale, &mut self.clipped)
            {
                any_clipped = true;
                self.method.run_excluding(
                    y,
                    kernel,
                    noise_v,
                    sample_ns,
                    &self.clipped,
                    &mut self.out[..n],
                )
            } else {
                self.method
                    .run(y, kernel, noise_v, sample_ns, &mut self.out[..n])
            };
            match result {
                Ok(_) => pulse.signal[range].copy_from_slice(&self.out[..n]),
                Err(e) => {
                    failure = Some(e.reason());
                    break;
                }
            }
        }
        if let Some(reason) = failure {
            return Verdict::Drop(reason);
        }
        match (cut, any_clipped) {
            (true, true) => Verdict::Keep([Some(KERNEL_OVER_MAX_TAPS), Some(CLIPPED_SAMPLES), None]),
            (true, false) => Verdict::noted(KERNEL_OVER_MAX_TAPS),
            (false, true) => Verdict::noted(CLIPPED_SAMPLES),
            (false, false) => Verdict::DONE,
        }
    }
}

/// The kernel of digitizer `channel`: its learned one, else the first learned (the one learned
/// from the most echoes), else `fixed` (no learned response).
fn channel_kernel<'k>(learned: &'k [(u16, Kernel)], fixed: &'k Kernel, channel: u8) -> &'k Kernel {
    learned
        .iter()
        .find(|(c, _)| *c == u16::from(channel))
        .or_else(|| learned.first())
        .map_or(fixed, |(_, k)| k)
}

/// The kernels of a learned response (`kernel = "learned"` or `{ response = "FILE" }`), one
/// per channel, the one learned from the most echoes first; empty for other kernel sources.
/// An error names what is missing or too long.
fn learned_kernels(config: &DeconvolveConfig) -> Result<Vec<(u16, Kernel)>, String> {
    if !matches!(
        config.kernel,
        KernelSource::Learned | KernelSource::Response(_)
    ) {
        return Ok(Vec::new());
    }
    let file = match (&config.learned, &config.learned_error) {
        (Some(f), _) => f,
        (None, Some(e)) => return Err(format!("kernel.response: {e}")),
        (None, None) => {
            return Err("kernel = \"learned\" needs the response learned from the input \
                 (replay learns it from the input's first pulses; this input held too few \
                 clean single echoes, or the run does not learn): name a file instead, kernel \
                 = { response = \"FILE\" } from `fwlidar response learn`"
                .into());
        }
    };
    let mut responses: Vec<_> = file.responses.iter().collect();
    responses.sort_by_key(|r| std::cmp::Reverse(r.echoes));
    responses
        .into_iter()
        .map(|r| {
            let (taps, center) = r.kernel_taps();
            let mut k = Kernel::with_capacity(config.max_taps);
            k.set_from_taps(&taps, center, config.max_taps)
                .map_err(|e| format!("kernel: the learned response of channel {}: {e}", r.channel))?;
            Ok((r.channel, k))
        })
        .collect()
}

/// Flags in `clipped` (resized to `raw.len()`, no allocation within its capacity) the samples
/// of `raw` at the digitizer's full scale ([`Pulse::full_scale_dn`]); true when any is. No
/// full scale (an unknown bit depth) flags nothing. Only those samples: flagging their
/// neighbours as well (which the low-pass of the denoise stage mixes with the clipped top) was
/// measured and is not better (docs/accuracy.md, "Saturated returns on board").
fn flag_full_scale(raw: &[u16], full_scale: Option<u16>, clipped: &mut Vec<bool>) -> bool {
    clipped.clear();
    let Some(top) = full_scale else {
        return false;
    };
    let mut any = false;
    clipped.extend(raw.iter().map(|&c| {
        any |= c >= top;
        c >= top
    }));
    any
}

impl Deconvolve {
    /// Logs the first kernel cut to `max_taps` (the run's summary counts every one).
    fn warn_cut_once(&mut self, support: usize) {
        if !self.warned_cut {
            self.warned_cut = true;
            tracing::warn!(
                support,
                max_taps = self.config.max_taps,
                "deconvolve: an outgoing pulse stands out of its noise over {support} samples, more \
                 than max_taps = {}; its kernel is cut to max_taps around the peak (counted as \
                 the note deconvolve.kernel_over_max_taps; raise max_taps to keep the whole pulse)",
                self.config.max_taps
            );
        }
    }
}

/// Largest iteration budget a deconvolution method may be configured for (per repetition).
pub(crate) const MAX_DECONV_ITERATIONS: u32 = 10_000;
/// Largest kernel a deconvolve stage may be configured for, taps.
pub(crate) const MAX_KERNEL_TAPS: usize = 65_536;

/// Checks a cut-off frequency (GHz) at `path`: positive and below the sensor's Nyquist frequency
/// when the sample interval is known.
/// The checks of a Wiener filter's settings at `path` (the method, or RL's `wiener_start`).
fn check_wiener(c: &WienerConfig, path: &str, v: &mut Validator) {
    check_cutoff(c.cutoff_ghz, field(path, "cutoff_ghz"), v);
    v.require(
        c.noise_scale.is_finite() && c.noise_scale >= 0.0,
        field(path, "noise_scale"),
        format!("must be a finite number ≥ 0, got {}", c.noise_scale),
    );
    v.positive(c.regularisation as f64, field(path, "regularisation"));
    if let Some(fwhm) = c.target_fwhm_ns {
        v.positive(fwhm, field(path, "target_fwhm_ns"));
    }
}

fn check_cutoff(cutoff_ghz: f64, path: String, v: &mut Validator) {
    v.positive(cutoff_ghz, path.clone());
    let positive = cutoff_ghz.is_finite() && cutoff_ghz > 0.0;
    let dt_ns = v
        .sample_interval_ns()
        .filter(|dt| dt.is_finite() && *dt > 0.0);
    if let Some(dt_ns) = dt_ns.filter(|_| positive) {
        let nyquist_ghz = 1.0 / (2.0 * dt_ns);
        v.require(
            cutoff_ghz < nyquist_ghz,
            path,
            format!(
                "must be below the Nyquist frequency {nyquist_ghz} GHz of the sensor's \
                 {dt_ns} ns sample interval, got {cutoff_ghz}"
            ),
        );
    }
}

fn check_iterations(n: u32, path: String, v: &mut Validator) {
    v.require(
        (1..=MAX_DECONV_ITERATIONS).contains(&n),
        path,
        format!("must be in 1..={MAX_DECONV_ITERATIONS}, got {n}"),
    );
}

/// Checks a Richardson-Lucy configuration at `method` (its path).
fn check_rl(c: &RlConfig, method: &str, v: &mut Validator) {
        check_iterations(c.iterations, field(method, "iterations"), v);
        if let Some(tol) = c.early_stop {
            v.positive(tol as f64, field(method, "early_stop"));
        }
        if let Some(tau) = c.stop_at_noise {
            v.positive(tau as f64, field(method, "stop_at_noise"));
        }
        v.require(
            c.coarse_iterations <= MAX_COARSE_ITERATIONS,
            field(method, "coarse_iterations"),
            format!(
                "must be in 0..={MAX_COARSE_ITERATIONS}, got {}",
                c.coarse_iterations
            ),
        );
        v.require(
            c.coarse_fwhm_samples.is_finite() && c.coarse_fwhm_samples >= 1.0,
            field(method, "coarse_fwhm_samples"),
            format!(
                "must be a finite number of coarse samples ≥ 1, got {}",
                c.coarse_fwhm_samples
            ),
        );
        if let Some(w) = &c.wiener_start {
            let start = field(method, "wiener_start");
            check_wiener(w, &start, v);
            v.require(
                c.coarse_iterations == 0,
                start,
                "excludes coarse_iterations (both choose the start): keep one".to_string(),
            );
        }
        if let Some(kappa) = c.floor_noise {
            v.positive(kappa as f64, field(method, "floor_noise"));
        }
}

/// Checks an NNLS configuration at `method` (its path).
fn check_nnls(c: &NnlsConfig, method: &str, v: &mut Validator) {
        check_iterations(c.max_iterations, field(method, "max_iterations"), v);
        v.require(
            c.tolerance.is_finite() && c.tolerance >= 0.0 && c.tolerance < 1.0,
            field(method, "tolerance"),
            format!("must be a relative tolerance in 0..1, got {}", c.tolerance),
        );
        if let Some(tau) = c.support_at_noise {
            v.positive(tau as f64, field(method, "support_at_noise"));
        }
}

impl Validate for DeconvolveConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        v.require(
            (MIN_SEGMENT_SAMPLES..=MAX_SEGMENT_SAMPLES).contains(&self.max_samples),
            field(path, "max_samples"),
            format!(
                "must be in {MIN_SEGMENT_SAMPLES}..={MAX_SEGMENT_SAMPLES} samples, got {}",
                self.max_samples
            ),
        );
        v.require(
            (1..=MAX_KERNEL_TAPS).contains(&self.max_taps),
            field(path, "max_taps"),
            format!(
                "must be in 1..={MAX_KERNEL_TAPS} taps, got {}",
                self.max_taps
            ),
        );
        let method = field(path, "method");
        match &self.method {
            MethodConfig::RichardsonLucy(c) => {
                check_rl(c, &method, v);
            }
            MethodConfig::Gold(c) => {
                check_iterations(c.iterations, field(&method, "iterations"), v);
                check_iterations(c.repetitions, field(&method, "repetitions"), v);
                v.positive(c.boost as f64, field(&method, "boost"));
                if let Some(tau) = c.stop_at_noise {
                    v.positive(tau as f64, field(&method, "stop_at_noise"));
                }
            }
            MethodConfig::Wiener(c) => check_wiener(c, &method, v),
            MethodConfig::Nnls(c) => {
                check_nnls(c, &method, v);
            }
            MethodConfig::NnlsOrRl(c) => {
                check_nnls(&c.nnls, &field(&method, "nnls"), v);
                check_rl(&c.rl, &field(&method, "rl"), v);
                let share = [
                    (c.threshold, "threshold", "share of NNLS's squared residual"),
                    (
                        c.nnls_above_noise,
                        "nnls_above_noise",
                        "multiple of the empty range's mean squared data",
                    ),
                ];
                for (value, name, what) in share {
                    v.require(
                        value.is_finite() && value >= 0.0,
                        field(&method, name),
                        format!("must be a finite {what}, ≥ 0, got {value}"),
                    );
                }
            }
        }
        if let Some(f) = self.target_fwhm_ns {
            v.positive(f, field(path, "target_fwhm_ns"));
        }
        if let Some(gate) = &self.gate {
            match gate.validate(&self.method) {
                Ok(()) => {}
                Err(e @ GateError::BadThreshold(_)) => v.report(
                    field(&field(path, "gate"), "threshold_noise"),
                    e.to_string(),
                ),
                Err(e) => v.report(field(path, "gate"), e.to_string()),
            }
        }
        if let KernelSource::Taps { taps, center } = &self.kernel {
            let kernel = field(path, "kernel");
            let finite = taps.iter().all(|t| t.is_finite());
            let sum: f64 = taps.iter().map(|&t| t as f64).sum();
            v.require(
                !taps.is_empty() && taps.len() <= self.max_taps,
                field(&kernel, "taps"),
                format!(
                    "must hold 1..={} taps (max_taps), got {}",
                    self.max_taps,
                    taps.len()
                ),
            );
            v.require(
                finite && sum > 0.0,
                field(&kernel, "taps"),
                "must be finite numbers with a positive sum",
            );
            v.require(
                *center < taps.len(),
                field(&kernel, "center"),
                format!("must index one of the {} taps, got {center}", taps.len()),
            );
        }
        if let KernelSource::FlatTarget {
            ground_return,
            outgoing,
        } = &self.kernel
        {
            let at = field(&field(path, "kernel"), "flat_target");
            // Measured here as the stage will measure it, so an unusable record is reported
            // before the run.
            if let Err(e) =
                response_from_flat_target(ground_return, outgoing, &self.method, self.max_taps)
            {
                let (name, reason) = match &e {
                    ResponseError::Outgoing(k) => ("outgoing", k.to_string()),
                    ResponseError::GroundReturn(d) => ("ground_return", d.to_string()),
                    ResponseError::Response(k) => (
                        "ground_return",
                        format!("the response measured from it is unusable: {k}"),
                    ),
                };
                v.report(field(&at, name), reason);
            }
        }
    }
}

impl StageKind for DeconvolveConfig {
    fn kind(&self) -> &'static str {
        "deconvolve"
    }

    fn prepare(&mut self, ctx: &RunContext<'_>) {
        if self.learned.is_some() {
            return;
        }
        match &self.kernel {
            KernelSource::Learned => self.learned = ctx.learned_response.cloned(),
            KernelSource::Response(path) => match ResponseFile::read(path) {
                Ok(r) => self.learned = Some(std::sync::Arc::new(r)),
                Err(e) => self.learned_error = Some(e),
            },
            _ => return,
        }
        if let Some(r) = &self.learned {
            let widths: Vec<String> = r
                .responses
                .iter()
                .map(|x| {
                    format!(
                        "channel {}: FWHM {:.1} ns",
                        x.channel,
                        f64::from(x.fwhm_samples) * x.sample_ns
                    )
                })
                .collect();
            tracing::info!(
                "deconvolve: by the learned system response ({}; {})",
                widths.join(", "),
                r.learned_from
            );
        }
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        Ok(Box::new(Deconvolve::new(self.clone())?))
    }

    fn note_meaning(&self, note: &str) -> &'static str {
        match note {
            KERNEL_OVER_MAX_TAPS => "deconvolved with the kernel cut to max_taps",
            CLIPPED_SAMPLES => {
                "deconvolved with return samples at the digitizer's full scale (left out of the \
                 fit by nnls, fitted as recorded by the other methods)"
            }
            _ => "passed on un-deconvolved",
        }
    }

    fn always_warns(&self, reason: &str) -> bool {
        reason == KERNEL_OVER_MAX_TAPS
    }

    fn drop_advice(&self, reason: &str, at: &str) -> Option<Advice> {
        let text = match reason {
            "no_outgoing" => {
                return Some(Advice::key(
                    at,
                    "missing_outgoing",
                    "the pulses recorded no outgoing segment to take the kernel from; set \
                     missing_outgoing = \"pass\" to pass them on un-deconvolved, or give a \
                     calibrated kernel = { taps = { ... } }",
                ));
            }
            "bad_kernel" if self.kernel == KernelSource::Outgoing => {
                "the outgoing segment holds no pulse above its noise (or a non-finite sample), so \
                 no kernel could be taken from it; give a calibrated kernel = { taps = { ... } } \
                 for this instrument"
            }
            "bad_kernel" => "the calibrated kernel is unusable; check its taps",
            KERNEL_OVER_MAX_TAPS => {
                return Some(Advice::key(
                    at,
                    "max_taps",
                    "the outgoing pulse stands out of its noise over more samples than max_taps \
                     and long_kernel = \"drop\"; raise max_taps (the cost grows with it) or set \
                     long_kernel = \"cut\"",
                ));
            }
            "kernel_too_long" => {
                return Some(Advice::key(
                    at,
                    "max_taps",
                    "the kernel is longer than the method was sized for; raise max_taps",
                ));
            }
            _ => return None,
        };
        Some(Advice::key(at, "kernel", text))
    }

    fn note_advice(&self, note: &str, at: &str) -> Option<Advice> {
        match note {
            KERNEL_OVER_MAX_TAPS => Some(Advice::key(
                at,
                "max_taps",
                "the outgoing pulse stands out of its noise over more samples than max_taps: \
                 the kernel was cut to max_taps around its peak (returns stay in place, the far \
                 tail is not deconvolved); raise max_taps to keep the whole pulse (the cost \
                 grows with it)",
            )),
            CLIPPED_SAMPLES if matches!(self.method, MethodConfig::Nnls(_)) => Some(Advice::key(
                at,
                "method",
                "returns reached the digitizer's full scale (the receiver saturated): nnls left \
                 those samples out of its fit and recovered the echo from its flanks (most of \
                 its energy where the clip is short, less where it is long); lower the \
                 receiver gain to record the whole echo",
            )),
            CLIPPED_SAMPLES => Some(Advice::key(
                at,
                "method",
                "returns reached the digitizer's full scale (the receiver saturated): this \
                 method fits the flattened top and underestimates the echo (by half on a \
                 strongly clipped one); method = { method = \"nnls\" } leaves those samples \
                 out of its fit, or lower the receiver gain",
            )),
            "no_outgoing" => Some(Advice::key(
                at,
                "kernel",
                "these pulses recorded no outgoing segment and were passed on un-deconvolved; \
                 give a calibrated kernel = { taps = { ... } } to deconvolve them",
            )),
            _ => None,
        }
    }

    fn cost_lines(&self) -> Vec<String> {
        let w = self.worst_case();
        let kernel = match self.kernel {
            KernelSource::Outgoing => format!("outgoing pulse of <= {} taps", w.taps),
            KernelSource::Taps { .. } => format!("calibrated, {} taps", w.taps),
            KernelSource::FlatTarget { .. } => {
                format!("response measured on a flat target, {} taps", w.taps)
            }
            KernelSource::Learned => format!("the response learned from the input, <= {} taps", w.taps),
            KernelSource::Response(ref p) => {
                format!("the learned response {}, <= {} taps", p.display(), w.taps)
            }
        };
        let iterations = if w.iterations == 0 {
            "direct".to_string()
        } else {
            format!("{} iterations", w.iterations)
        };
        let start = match &self.method {
            MethodConfig::RichardsonLucy(c) if c.wiener_start.is_some() => " from a Wiener start",
            _ => "",
        };
        let mut lines = vec![format!(
            "deconvolve ({}{start}, {iterations}, kernel: {kernel}): worst case {} flop per \
             return segment of <= {} samples",
            self.method.name(),
            grouped(w.flops),
            w.samples
        )];
        lines.extend(self.measured_rate().map(String::from));
        lines
    }
}

impl DeconvolveConfig {
    /// What was measured for the two on-board settings by the outgoing pulse (behind the gate)
    /// (docs/performance.md, "Every pulse on board"); none for other settings.
    fn measured_rate(&self) -> Option<&'static str> {
        let MethodConfig::RichardsonLucy(c) = &self.method else {
            return None;
        };
        let on_board = self.kernel == KernelSource::Outgoing;
        if on_board && *c == RlConfig::onboard() {
            Some(
                "measured 2026-11-27 (2-core VM, survey line, every pulse): 2.5-2.8 µs mean \
                 per pulse; with the FIR denoise, calibrate and the QC-only decomposition \
                 ~210 000 pulses/s with 1 worker, ~249 000 with 2 (docs/performance.md)",
            )
        } else if on_board && *c == (RlConfig { iterations: 20, ..RlConfig::default() }) {
            Some(
                "measured 2026-11-27 (2-core VM, survey line, every pulse): 3.0 µs mean per \
                 pulse; ~2-3 % fewer pulses/s than the on-board setting (docs/performance.md)",
            )
        } else {
            None
        }
    }
}

/// Groups the digits of `n` by thousands with spaces (`1 860 770`).
fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::testing::run_stage;
    use crate::signal::deconvolve::{GoldConfig, NnlsOrRlConfig, RlConfig, WienerConfig};

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

    /// An 8-bit pulse whose strong return saturates the digitizer: counts clipped at 255 on
    /// the top 9 samples, the signal the counts in volts (1 mV per count). Also returns the
    /// unclipped return's area, volt-samples.
    fn saturated_pulse(bits: u8) -> (Pulse, f32) {
        let mut p = Pulse {
            bits,
            ..Default::default()
        };
        let outgoing = gauss(41, 20.0, 3.4, 200.0);
        let echo: Vec<f32> = gauss(128, 60.0, 3.4, 600.0)
            .iter()
            .zip(gauss(128, 90.0, 3.4, 80.0))
            .map(|(a, b)| a + b)
            .collect();
        let counts = |v: &[f32]| -> Vec<u16> { v.iter().map(|x| x.round().min(255.0) as u16).collect() };
        let (co, cr) = (counts(&outgoing), counts(&echo));
        assert_eq!(cr.iter().filter(|&&c| c == 255).count(), 9);
        p.push_segment(SegmentKind::Outgoing, 0, -20.0, co.clone());
        p.push_segment(SegmentKind::Return, 0, 900.0, cr.clone());
        p.signal = co.iter().chain(&cr).map(|&c| c as f32 * 1e-3).collect();
        p.noise.noise_v = 1e-3;
        let area = echo.iter().map(|v| v.round() * 1e-3).sum();
        (p, area)
    }

    #[test]
    fn nnls_leaves_samples_at_the_digitizer_full_scale_out_and_recovers_the_echo() {
        let mut stage = Deconvolve::new(DeconvolveConfig::with_method(MethodConfig::Nnls(
            Default::default(),
        )))
        .unwrap();
        let area_of = |p: &Pulse| p.signal_of(1).iter().sum::<f32>();
        // Recorded by an 8-bit digitizer: 255 counts is its full scale.
        let (clipped, truth) = saturated_pulse(8);
        let recorded: f32 = clipped.signal_of(1).iter().sum();
        let run = run_stage(&mut stage, [clipped]).unwrap();
        let p = &run.emitted[0];
        let kept = area_of(p);
        // The same counts from a 16-bit digitizer are not at its full scale: fitted as recorded.
        let (as_recorded, _) = saturated_pulse(16);
        let plain = area_of(&run_stage(&mut stage, [as_recorded]).unwrap().emitted[0]);
        println!("area: truth {truth}, recorded {recorded}, clipped left out {kept}, fitted {plain}");
        assert!(recorded < 0.8 * truth, "the top is clipped: {recorded} of {truth}");
        assert!(
            (kept - truth).abs() < 0.05 * truth,
            "full-scale samples left out: area {kept} vs {truth}"
        );
        assert!(plain < 0.85 * truth, "fitted as recorded: {plain} of {truth}");
        assert!(p.signal_of(1).iter().all(|v| v.is_finite() && *v >= 0.0));
        assert_eq!(run.notes.get(CLIPPED_SAMPLES), 1);
        // Nothing at the full scale: no note.
        let run = run_stage(&mut stage, [denoised_pulse()]).unwrap();
        assert_eq!(run.notes.get(CLIPPED_SAMPLES), 0);
    }

    #[test]
    fn deconvolve_stage_sharpens_returns_and_keeps_the_outgoing() {
        for m in methods() {
            let mut stage = Deconvolve::new(DeconvolveConfig::with_method(m.clone())).unwrap();
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

    /// A learned response file of one channel: a Gaussian of σ `sigma` samples on the quarter
    /// grid, as `fwlidar response learn` writes it.
    fn learned_file(channel: u16, sigma: f32) -> crate::signal::learned_response::ResponseFile {
        use crate::signal::learned_response::{LearnedResponse, ResponseFile};
        let start = -16.0f32;
        let shape: Vec<f32> = (0..129)
            .map(|g| {
                let x = (start + g as f32 * 0.25) / sigma;
                (-0.5 * x * x).exp()
            })
            .collect();
        ResponseFile {
            learned_from: "a test".into(),
            responses: vec![LearnedResponse {
                channel,
                sample_ns: 1.0,
                step_samples: 0.25,
                start_samples: start,
                spread: vec![0.0; shape.len()],
                shape,
                echoes: 100,
                candidates: 100,
                fwhm_samples: 2.3548 * sigma,
                amplitude_counts: [50.0, 200.0],
                amplitude_dependence: None,
                gaussian_misfit: 0.0,
                shape_noise: 0.0,
            }],
        }
    }

    #[test]
    fn a_learned_response_deconvolves_pulses_without_their_outgoing_pulse() {
        let config = DeconvolveConfig {
            kernel: KernelSource::Learned,
            learned: Some(std::sync::Arc::new(learned_file(3, 3.4))),
            ..DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig::default()))
        };
        let mut stage = Deconvolve::new(config).unwrap();
        // No outgoing segment, channel 0 (the file knows channel 3 only: its one response).
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Return, 0, 900.0, [0u16; 128]);
        let r1 = gauss(128, 40.0, 3.4, 0.5);
        let r2 = gauss(128, 80.0, 3.4, 0.3);
        p.signal = r1.iter().zip(&r2).map(|(a, b)| a + b).collect();
        p.noise.noise_v = 0.001;
        let run = run_stage(&mut stage, [p]).unwrap();
        assert_eq!(run.emitted.len(), 1);
        let ret = run.emitted[0].signal_of(0);
        let peak = ret
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap();
        assert!((peak.0 as i32 - 40).abs() <= 1, "peak at {}", peak.0);
        assert!(*peak.1 > 0.6, "sharpened peak {}", peak.1);
        // Without a learned response the stage is not built, and says what to do.
        let e = Deconvolve::new(DeconvolveConfig {
            kernel: KernelSource::Learned,
            ..DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig::default()))
        })
        .err()
        .unwrap();
        assert!(
            e.message.contains("kernel = \"learned\"") && e.message.contains("response learn"),
            "{}",
            e.message
        );
        // The file form parses from TOML.
        let c: DeconvolveConfig = toml::from_str(
            "method = { method = \"richardson_lucy\" }\nkernel = { response = \"r.toml\" }",
        )
        .unwrap();
        assert_eq!(c.kernel, KernelSource::Response("r.toml".into()));
    }

    #[test]
    fn a_pulse_without_outgoing_is_passed_unchanged_and_noted_when_configured() {
        use crate::pipeline::{DropCounts, Emitter};
        use crate::pulse::PulsePool;
        let mut stage = Deconvolve::new(DeconvolveConfig {
            missing_outgoing: MissingOutgoing::Pass,
            ..DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig::default()))
        }).unwrap();
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
        }).unwrap();
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
    fn deconvolve_stage_calibrated_kernel_and_bad_taps_refused_when_built() {
        let cfg = DeconvolveConfig {
            kernel: KernelSource::Taps {
                taps: gauss(41, 20.0, 3.4, 1.0),
                center: 20,
            },
            ..DeconvolveConfig::with_method(MethodConfig::Gold(GoldConfig::default()))
        };
        let mut stage = Deconvolve::new(cfg).unwrap();
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
        // An unusable calibrated kernel stops the run before it starts (the configuration's
        // validation names the field; building refuses it).
        let e = Deconvolve::new(bad).err().expect("refused");
        assert!(e.to_string().contains("calibrated kernel: kernel.taps"), "{e}");
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
            let mut stage = Deconvolve::new(DeconvolveConfig::with_method(m.clone())).unwrap();
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

    /// The issue's outgoing pulse, denoised (volts above the baseline): 98 samples, peak 0.8 V
    /// at sample 15, a fast fall and a long low tail (15 % decaying over 25 samples), with
    /// ±4 mV of residual noise. Returns the noisy record and the clean pulse.
    fn long_outgoing() -> (Vec<f32>, Vec<f32>) {
        let clean: Vec<f32> = (0..98)
            .map(|i| {
                let t = i as f32 - 15.0;
                0.8 * if t < 0.0 {
                    (-0.5 * (t / 2.0).powi(2)).exp()
                } else {
                    0.85 * (-t / 3.0).exp() + 0.15 * (-t / 25.0).exp()
                }
            })
            .collect();
        let mut x = 12345u32;
        let noisy = clean
            .iter()
            .map(|v| {
                x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                v + 0.004 * ((x >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0)
            })
            .collect();
        (noisy, clean)
    }

    /// A pulse with [`long_outgoing`] and a 240-sample return of point targets at bins 60 and
    /// 150 echoing the clean pulse (emission reference at its peak, sample 15).
    fn long_outgoing_pulse() -> Pulse {
        let (noisy, clean) = long_outgoing();
        let mut ret = vec![0.0f32; 240];
        for (t, a) in [(60usize, 0.6f32), (150, 0.4)] {
            for (i, r) in ret.iter_mut().enumerate() {
                let j = i as i64 - t as i64 + 15;
                if (0..clean.len() as i64).contains(&j) {
                    *r += a * clean[j as usize];
                }
            }
        }
        let mut p = Pulse::default();
        p.push_segment(SegmentKind::Outgoing, 0, -15.0, [0u16; 98]);
        p.push_segment(SegmentKind::Return, 0, 900.0, [0u16; 240]);
        p.signal = noisy;
        p.signal.extend(&ret);
        p.noise.noise_v = 0.004;
        p
    }

    #[test]
    fn a_long_outgoing_segment_deconvolves_by_its_support_and_returns_stay_in_place() {
        // 98 samples with max_taps = 96 (the replay configuration): every such pulse used to be
        // dropped `bad_kernel`; its support (~70 samples above the noise) fits.
        let mut methods = methods().to_vec();
        methods.push(MethodConfig::Nnls(Default::default()));
        for m in methods {
            let mut stage = Deconvolve::new(DeconvolveConfig {
                max_taps: 96,
                ..DeconvolveConfig::with_method(m.clone())
            }).unwrap();
            let run = run_stage(&mut stage, [long_outgoing_pulse()]).unwrap();
            assert_eq!(run.emitted.len(), 1, "{m:?}: {:?}", run.dropped);
            assert_eq!(run.notes.total(), 0, "{m:?}: the support fits, nothing cut");
            let y = run.emitted[0].signal_of(1);
            for t in [60usize, 150] {
                let window = &y[t - 10..t + 11];
                let peak = crate::signal::kernel::peak_index(window).unwrap() as i64 - 10;
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
    fn a_support_longer_than_max_taps_is_cut_and_noted_or_dropped() {
        let rl = MethodConfig::RichardsonLucy(RlConfig::default());
        let mut cut = Deconvolve::new(DeconvolveConfig {
            max_taps: 16,
            ..DeconvolveConfig::with_method(rl.clone())
        }).unwrap();
        let run = run_stage(&mut cut, (0..3).map(|_| long_outgoing_pulse())).unwrap();
        assert_eq!(run.emitted.len(), 3);
        assert_eq!(run.notes.get(KERNEL_OVER_MAX_TAPS), 3);
        assert_eq!(run.dropped.total(), 0);
        assert_eq!(cut.kernel.len(), 16);
        let y = run.emitted[0].signal_of(1);
        assert_eq!(crate::signal::kernel::peak_index(&y[50..71]), Some(10));
        let mut drop = Deconvolve::new(DeconvolveConfig {
            max_taps: 16,
            long_kernel: LongKernel::Drop,
            ..DeconvolveConfig::with_method(rl)
        }).unwrap();
        let run = run_stage(&mut drop, (0..3).map(|_| long_outgoing_pulse())).unwrap();
        assert_eq!(run.emitted.len(), 0);
        assert_eq!(run.dropped.get(KERNEL_OVER_MAX_TAPS), 3);
        assert_eq!(run.notes.total(), 0);
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
            stop_at_noise: None,
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
        }).unwrap();
        let mut second = Deconvolve::new(DeconvolveConfig::with_method(gold)).unwrap();
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
                stop_at_noise: None,
            },
        ))).unwrap();
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
            for max_taps in [256, 16] {
                // 16: every long outgoing pulse is cut to max_taps.
                let mut stage = Deconvolve::new(DeconvolveConfig {
                    max_taps,
                    ..DeconvolveConfig::with_method(m.clone())
                }).unwrap();
                run_stage(&mut stage, [denoised_pulse()]).unwrap();
                let caps = stage.buffer_capacities();
                let pulses = (0..200).map(|i| {
                    if i % 2 == 0 {
                        denoised_pulse()
                    } else {
                        long_outgoing_pulse()
                    }
                });
                let run = run_stage(&mut stage, pulses).unwrap();
                assert_eq!(run.emitted.len(), 200);
                assert_eq!(stage.buffer_capacities(), caps);
            }
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
        let c = parse("method = { method = \"gold\" }\nlong_kernel = \"drop\"").unwrap();
        assert_eq!(c.long_kernel, LongKernel::Drop);
        assert_eq!(
            parse("method = { method = \"gold\" }").unwrap().long_kernel,
            LongKernel::Cut
        );
        assert!(parse("method = { method = \"gold\" }\nlong_kernel = \"trim\"").is_err());
        let text = "max_taps = 64\n[method]\nmethod = \"gold\"\niterations = 10\nrepetitions = 3\nboost = 1.5\n[kernel.taps]\ntaps = [0.25, 0.5, 0.25]\ncenter = 1\n";
        let c = parse(text).unwrap();
        assert_eq!(c.max_taps, 64);
        assert_eq!(
            c.method,
            MethodConfig::Gold(GoldConfig {
                iterations: 10,
                repetitions: 3,
                boost: 1.5,
                stop_at_noise: None,
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
                accelerate: false,
                stop_at_noise: Some(1.0),
                ..RlConfig::default()
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

    #[test]
    fn grouped_digits() {
        assert_eq!(grouped(0), "0");
        assert_eq!(grouped(999), "999");
        assert_eq!(grouped(1_860_770), "1 860 770");
    }

    fn stage(text: &str) -> Result<crate::stages::StageConfig, toml::de::Error> {
        toml::from_str(text)
    }

    #[test]
    fn stage_config_deconvolve_round_trips_and_checks() {
        use crate::signal::deconvolve::{GoldConfig, NnlsConfig, RlConfig, WienerConfig};
        let s = stage("type = \"deconvolve\"\nmethod = { method = \"gold\" }").unwrap();
        assert_eq!(
            s,
            crate::stages::StageConfig::Deconvolve(DeconvolveConfig::with_method(MethodConfig::Gold(
                GoldConfig::default()
            )))
        );
        assert_eq!(s.kind(), "deconvolve");
        let text = toml::to_string(&s).unwrap();
        assert_eq!(stage(&text).unwrap(), s, "{text}");
        assert!(stage("type = \"deconvolve\"\nmethod = { method = \"gold\" }\nbogus = 1").is_err());
        let mut v = Validator::new(None);
        v.set_sample_interval_ns(Some(4.0));
        let bad = DeconvolveConfig {
            kernel: KernelSource::Taps {
                taps: vec![0.0, f32::NAN],
                center: 5,
            },
            max_samples: 8,
            max_taps: 0,
            ..DeconvolveConfig::with_method(MethodConfig::Wiener(WienerConfig {
                cutoff_ghz: 0.2,
                noise_scale: -1.0,
                regularisation: 0.0,
                target_fwhm_ns: None,
            }))
        };
        Validate::validate(&bad, "s", &mut v);
        let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            [
                "s.max_samples",
                "s.max_taps",
                "s.method.cutoff_ghz",
                "s.method.noise_scale",
                "s.method.regularisation",
                "s.kernel.taps",
                "s.kernel.taps",
                "s.kernel.center"
            ]
        );
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
            iterations: 0,
            early_stop: Some(-1.0),
            accelerate: false,
            stop_at_noise: Some(f32::NAN),
            ..RlConfig::default()
        }));
        Validate::validate(&bad, "s", &mut v);
        assert_eq!(v.issues().len(), 3);
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
            coarse_iterations: MAX_COARSE_ITERATIONS + 1,
            coarse_fwhm_samples: 0.5,
            ..RlConfig::default()
        }));
        Validate::validate(&bad, "s", &mut v);
        let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            ["s.method.coarse_iterations", "s.method.coarse_fwhm_samples"]
        );
        for fwhm in [f32::NAN, f32::INFINITY] {
            let mut v = Validator::new(None);
            let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
                coarse_iterations: 10,
                coarse_fwhm_samples: fwhm,
                ..RlConfig::default()
            }));
            Validate::validate(&bad, "s", &mut v);
            assert_eq!(v.issues().len(), 1, "{fwhm}");
        }
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::RichardsonLucy(RlConfig {
            coarse_iterations: 5,
            floor_noise: Some(-1.0),
            wiener_start: Some(WienerConfig {
                target_fwhm_ns: Some(f64::NAN),
                noise_scale: f32::INFINITY,
                ..WienerConfig::default()
            }),
            ..RlConfig::default()
        }));
        Validate::validate(&bad, "s", &mut v);
        let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            paths,
            [
                "s.method.wiener_start.noise_scale",
                "s.method.wiener_start.target_fwhm_ns",
                "s.method.wiener_start",
                "s.method.floor_noise"
            ]
        );
        let mut v = Validator::new(None);
        let bad = DeconvolveConfig::with_method(MethodConfig::Gold(GoldConfig {
            iterations: 1,
            repetitions: 0,
            boost: f32::INFINITY,
            stop_at_noise: Some(0.0),
        }));
        Validate::validate(&bad, "s", &mut v);
        assert_eq!(v.issues().len(), 3);
        for tau in [0.0, -1.0, f32::NAN] {
            let mut v = Validator::new(None);
            let bad = DeconvolveConfig::with_method(MethodConfig::Nnls(NnlsConfig {
                support_at_noise: Some(tau),
                ..NnlsConfig::default()
            }));
            Validate::validate(&bad, "s", &mut v);
            let fields: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
            assert_eq!(fields, ["s.method.support_at_noise"], "{tau}");
        }
        let mut v = Validator::new(None);
        Validate::validate(
            &DeconvolveConfig::with_method(MethodConfig::Wiener(WienerConfig::default())),
            "s",
            &mut v,
        );
        assert!(v.issues().is_empty());
    }

    /// The per-pulse choice parses from TOML with its two methods as nested tables, and each
    /// bad value is named by its path (the two methods checked as on their own).
    #[test]
    fn nnls_or_rl_parses_and_each_field_is_checked() {
        let crate::stages::StageConfig::Deconvolve(c) = stage(
            "type = \"deconvolve\"\ntarget_fwhm_ns = 2.0\n[method]\nmethod = \"nnls_or_rl\"\n\
             threshold = 0.4\nnnls = { max_iterations = 30 }\nrl = { iterations = 10 }",
        )
        .unwrap() else {
            panic!("not a deconvolve stage")
        };
        let MethodConfig::NnlsOrRl(m) = &c.method else {
            panic!("{:?}", c.method)
        };
        assert_eq!((m.threshold, m.nnls.max_iterations, m.rl.iterations), (0.4, 30, 10));
        assert_eq!(m.rl.coarse_iterations, 0, "a table given replaces the defaults");
        let mut v = Validator::new(None);
        Validate::validate(&c, "s", &mut v);
        assert!(v.issues().is_empty(), "{:?}", v.issues());
        let bad = DeconvolveConfig::with_method(MethodConfig::NnlsOrRl(NnlsOrRlConfig {
            threshold: -0.1,
            nnls_above_noise: f32::NAN,
            nnls: NnlsConfig {
                support_at_noise: Some(0.0),
                ..NnlsConfig::default()
            },
            rl: RlConfig {
                iterations: 0,
                ..RlConfig::default()
            },
        }));
        let mut v = Validator::new(None);
        Validate::validate(&bad, "s", &mut v);
        let fields: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
        assert_eq!(
            fields,
            [
                "s.method.nnls.support_at_noise",
                "s.method.rl.iterations",
                "s.method.threshold",
                "s.method.nnls_above_noise"
            ]
        );
        let mut gated = c.clone();
        gated.gate = Some(crate::signal::deconvolve::Gate::default());
        let mut v = Validator::new(None);
        Validate::validate(&gated, "s", &mut v);
        assert_eq!(v.issues()[0].0, "s.gate", "the gate is RL's, inside the choice");
    }

    #[test]
    fn stage_config_deconvolve_gate_is_parsed_and_checked() {
        use crate::signal::deconvolve::Gate;
        let crate::stages::StageConfig::Deconvolve(c) = stage(
            "type = \"deconvolve\"\nmethod = { method = \"richardson_lucy\" }\ngate = \"off\"",
        )
        .unwrap() else {
            panic!("not a deconvolve stage")
        };
        assert_eq!(c.gate, Some(Gate::Off));
        assert_eq!(c.effective_gate(), Gate::Off);
        let e = stage("type = \"deconvolve\"\nmethod = { method = \"gold\" }\ngate = { k = 1 }")
            .unwrap_err()
            .to_string();
        assert!(e.contains("threshold_noise"), "{e}");
        let issues = |text: &str| {
            let crate::stages::StageConfig::Deconvolve(c) = stage(text).unwrap() else {
                panic!("not a deconvolve stage")
            };
            let mut v = Validator::new(None);
            Validate::validate(&c, "s", &mut v);
            v.issues()
                .iter()
                .map(|(p, _)| p.clone())
                .collect::<Vec<_>>()
        };
        assert!(issues("type = \"deconvolve\"\nmethod = { method = \"gold\" }\ngate = { threshold_noise = 2.0 }").is_empty());
        assert!(issues("type = \"deconvolve\"\nmethod = { method = \"wiener\" }").is_empty());
        assert_eq!(
            issues(
                "type = \"deconvolve\"\nmethod = { method = \"richardson_lucy\" }\ngate = { threshold_noise = 0.0 }"
            ),
            ["s.gate.threshold_noise"]
        );
        assert_eq!(
            issues("type = \"deconvolve\"\nmethod = { method = \"nnls\" }\ngate = \"on\""),
            ["s.gate"]
        );
    }

    #[test]
    fn stage_config_flat_target_kernel_is_parsed_and_checked() {
        let text = "type = \"deconvolve\"\nmethod = { method = \"gold\" }\n\
                    kernel = { flat_target = { ground_return = [200.0, 200.0, 900.0, 400.0, 200.0], \
                    outgoing = [200.0, 200.0, 700.0, 300.0, 200.0] } }";
        let s = stage(text).unwrap();
        let crate::stages::StageConfig::Deconvolve(c) = &s else {
            panic!("{s:?}")
        };
        assert!(matches!(c.kernel, KernelSource::FlatTarget { .. }));
        assert_eq!(stage(&toml::to_string(&s).unwrap()).unwrap(), s);
        let mut v = Validator::new(None);
        Validate::validate(c, "s", &mut v);
        assert!(v.issues().is_empty(), "{:?}", v.issues());
        // A flat outgoing pulse (no energy above its baseline) and a NaN in the return.
        for (ground, out, path) in [
            (
                vec![200.0, 900.0, 200.0],
                vec![5.0; 4],
                "s.kernel.flat_target.outgoing",
            ),
            (
                vec![200.0, f32::NAN],
                vec![0.0, 3.0, 0.0],
                "s.kernel.flat_target.ground_return",
            ),
        ] {
            let bad = DeconvolveConfig {
                kernel: KernelSource::FlatTarget {
                    ground_return: ground,
                    outgoing: out,
                },
                ..c.clone()
            };
            let mut v = Validator::new(None);
            Validate::validate(&bad, "s", &mut v);
            let paths: Vec<&str> = v.issues().iter().map(|(p, _)| p.as_str()).collect();
            assert_eq!(paths, [path], "{:?}", v.issues());
        }
    }
}
