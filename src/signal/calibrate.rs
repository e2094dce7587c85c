//! The calibrate stage: radiometric calibration of every bin of a pulse.
//!
//! For an extended Lambertian target filling the footprint the radar equation gives a received
//! power proportional to `E_t · ρ · cos θ · η_sys · η_atm / R²`; the calibrated backscatter of a
//! bin `t` ns after the pulse's t0 holding `P(t)` volts is therefore
//!
//! `β(t) = C · P(t) · (R(t) / R_ref)² / (E_out / E_ref)`, `R(t) = (t − t_emit) · c / (2 n)`
//!
//! (derivation, assumptions and units: `docs/calibration.md`). The stage does **not** rewrite
//! [`Pulse::signal`], which stays in volts for `waveforms.csv` and for the stages after it: it
//! attaches a per-pulse [`Calibration`] (`Pulse::calibration`) whose
//! [`Calibration::factor_at`] turns any bin's volts into backscatter, and fills
//! [`crate::pulse::FittedReturn::backscatter`] of every return (amplitude × factor at its
//! `time_ns`).
//!
//! Per pulse, in this order:
//!
//! 1. **Volts** (switch `volts`): when no stage has filled `signal` yet (it is empty), it is
//!    filled with `offset_v + gain_v_per_dn × counts` (with `volts = false`: the counts
//!    themselves). After a denoise stage the signal is already in volts above the baseline and
//!    is left as it is.
//! 2. **Outgoing pulse** (first outgoing segment with samples): baseline = median of its first
//!    [`KERNEL_BASELINE_SAMPLES`] samples; energy `E_out = Σ (v − baseline) × sample_ns`
//!    (V·ns); emission time `t_emit` = its peak sample ([`peak_index`], the same peak the
//!    deconvolution kernel is centred on) refined by the vertex of the parabola through it and
//!    its neighbours.
//! 3. **Range** (switch `range`): `t_emit` from the outgoing pulse; without one (or with one
//!    of no positive energy), `t_emit = 0` when the input times its pulses from emission
//!    (`t0_is_emission`), otherwise the range is unknown: policy `range_unknown`.
//! 4. **Energy** (switch `energy`): the factor `E_ref / E_out`; no outgoing segment
//!    (`no_outgoing`) or a non-positive / non-finite energy (`bad_outgoing_energy`): policy
//!    `energy_unknown`.
//! 5. **System constant** (switch `system_constant`): `C` from `system_constant_value`, or
//!    from the sensor profile's `calibration_constant` when that key is left out (resolved from
//!    the input when the run starts, [`CalibrateConfig::resolve_from_input`]; 1 when nothing
//!    states it).
//!
//! Policies: `"unscaled"` passes the pulse on without the factor it cannot compute, counted as
//! a note (`summary.json`, the stage's `notes`) under the reason; `"drop"` drops it, counted
//! under the reason. Pulses the stage cannot read are rejected (errors):
//! `segment_out_of_bounds`, `signal_length_mismatch` (a signal filled but not sample for
//! sample with `raw`), `bad_digitizer_parameters` (non-finite gain/offset when converting, or
//! a non-positive / non-finite sample interval). A return at or before the emission gets a NaN
//! backscatter (noted `return_before_emission`).
//!
//! Work per pulse: one pass over the raw counts when converting, one over the outgoing
//! segment, a few flops per return; nothing is allocated after warm-up (the signal buffer is
//! the pooled pulse's own).

use serde::{Deserialize, Serialize};

use crate::core::facts::SourceFacts;
use crate::pulse::{Calibration, Pulse, SegmentKind, Verdict};
use crate::signal::kernel::{KERNEL_BASELINE_SAMPLES, peak_index};

/// What the stage does with a pulse one of whose factors cannot be computed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnknownPolicy {
    /// Pass the pulse on without that factor (counted as a note under the reason).
    #[default]
    Unscaled,
    /// Drop the pulse (counted under the reason).
    Drop,
}

/// Errors of the calibrate configuration (each names its key).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CalibrateError {
    /// A key that must be a positive finite number is not.
    #[error("{key} must be a positive finite number, got {value}")]
    NotPositive {
        /// The key.
        key: &'static str,
        /// Its value.
        value: f64,
    },
    /// The refractive index is outside 1..=1.001.
    #[error("refractive_index must be in 1..=1.001 (1 = vacuum), got {value}")]
    RefractiveIndex {
        /// Its value.
        value: f64,
    },
}

/// Configuration of the calibrate stage (`type = "calibrate"` in `[[pipeline.stages]]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrateConfig {
    /// Convert digitizer counts to volts (`offset + gain × counts`) when no stage has filled
    /// the signal yet; false: calibrate the counts themselves. No effect after a denoise stage
    /// (the signal is already in volts). Default true.
    #[serde(default = "yes")]
    pub volts: bool,
    /// Apply the range factor `(R / R_ref)²`. Default true.
    #[serde(default = "yes")]
    pub range: bool,
    /// Apply the energy factor `E_ref / E_out` (the shot's outgoing pulse). Default true.
    #[serde(default = "yes")]
    pub energy: bool,
    /// Apply the system constant C. Default true.
    #[serde(default = "yes")]
    pub system_constant: bool,
    /// The system constant C, calibrated units per volt. Left out: the sensor profile's
    /// `calibration_constant` (from the input's header or scanner record, resolved when the
    /// run starts), 1 when the input states none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub system_constant_value: Option<f64>,
    /// Reference range R_ref at which the range factor is 1, metres. Default 1000.
    #[serde(default = "default_reference_range_m")]
    pub reference_range_m: f64,
    /// Group refractive index n of the air (range per ns is `c / (2 n)`); 1 to 1.001. Default
    /// 1.00027, as `[georeference] refractive_index`.
    #[serde(default = "default_refractive_index")]
    pub refractive_index: f64,
    /// Reference outgoing energy E_ref at which the energy factor is 1, V·ns (the integral of
    /// the outgoing segment above its baseline). Default 1.
    #[serde(default = "one")]
    pub reference_energy_v_ns: f64,
    /// Whether a pulse's t0 is its emission, for pulses without an outgoing segment. Left out:
    /// as the input states it (true for fwlidar captures that were recorded or simulated,
    /// false for LAS, PulseWaves and imported captures), false when it does not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub t0_is_emission: Option<bool>,
    /// A pulse whose emission time is unknown (no outgoing segment and t0 not the emission):
    /// "unscaled" (passed on without the range factor, noted `range_unknown`) or "drop"
    /// (dropped `range_unknown`). Default "unscaled".
    #[serde(default)]
    pub range_unknown: UnknownPolicy,
    /// A pulse without an outgoing segment (`no_outgoing`) or whose outgoing energy is not a
    /// positive finite number (`bad_outgoing_energy`): "unscaled" (passed on without the energy
    /// factor, noted) or "drop". Default "unscaled".
    #[serde(default)]
    pub energy_unknown: UnknownPolicy,
}

fn yes() -> bool {
    true
}
fn one() -> f64 {
    1.0
}
fn default_reference_range_m() -> f64 {
    1000.0
}
fn default_refractive_index() -> f64 {
    1.00027
}

impl Default for CalibrateConfig {
    fn default() -> Self {
        CalibrateConfig {
            volts: true,
            range: true,
            energy: true,
            system_constant: true,
            system_constant_value: None,
            reference_range_m: default_reference_range_m(),
            refractive_index: default_refractive_index(),
            reference_energy_v_ns: one(),
            t0_is_emission: None,
            range_unknown: UnknownPolicy::Unscaled,
            energy_unknown: UnknownPolicy::Unscaled,
        }
    }
}

impl CalibrateConfig {
    /// Checks the numbers (the first error found, naming its key).
    pub fn validate(&self) -> Result<(), CalibrateError> {
        let positive = |key, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(CalibrateError::NotPositive { key, value })
            }
        };
        if let Some(c) = self.system_constant_value {
            positive("system_constant_value", c)?;
        }
        positive("reference_range_m", self.reference_range_m)?;
        positive("reference_energy_v_ns", self.reference_energy_v_ns)?;
        if !(1.0..=1.001).contains(&self.refractive_index) {
            return Err(CalibrateError::RefractiveIndex {
                value: self.refractive_index,
            });
        }
        Ok(())
    }

    /// Fills what was left to the input: the system constant from its sensor profile's
    /// `calibration_constant` and whether its t0 is the emission. Keys set in the configuration
    /// are kept. Called by `fwlidar replay` once the input is open, before the stages are
    /// built.
    pub fn resolve_from_input(&mut self, facts: &SourceFacts) {
        if self.system_constant_value.is_none() {
            self.system_constant_value = facts.sensor.as_ref().map(|s| s.calibration_constant);
        }
        if self.t0_is_emission.is_none() {
            self.t0_is_emission = facts.t0_is_emission;
        }
    }

    /// Metres of range per nanosecond of two-way time, `c / (2 n)`.
    pub fn metres_per_ns(&self) -> f64 {
        crate::core::units::half_c_in_m_per_ns(self.refractive_index)
    }
}

/// What the stage learnt from a pulse's outgoing segment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OutgoingFacts {
    /// Energy above the baseline, V·ns (or counts·ns with `volts = false`).
    pub energy_v_ns: f64,
    /// Peak time, ns after t0 (parabolic sub-sample refinement).
    pub peak_ns: f64,
}

/// Energy and peak time of an outgoing segment `x` (signal units) whose first sample lies
/// `start_ns` after t0, `sample_ns` apart. `None` for an empty segment. The energy is NaN when
/// a sample is not finite.
pub fn outgoing_facts(x: &[f32], start_ns: f64, sample_ns: f64) -> Option<OutgoingFacts> {
    if x.is_empty() {
        return None;
    }
    // Median of the pre-trigger samples, on a fixed array.
    let mut head = [0.0f32; KERNEL_BASELINE_SAMPLES];
    let n = x.len().min(KERNEL_BASELINE_SAMPLES);
    head[..n].copy_from_slice(&x[..n]);
    let head = &mut head[..n];
    head.sort_unstable_by(f32::total_cmp);
    let base = if n % 2 == 1 {
        head[n / 2] as f64
    } else {
        0.5 * (head[n / 2 - 1] as f64 + head[n / 2] as f64)
    };
    let sum: f64 = x.iter().map(|&v| v as f64 - base).sum();
    let energy_v_ns = sum * sample_ns;
    let k = peak_index(x)?;
    let mut pos = k as f64;
    if k > 0 && k + 1 < x.len() {
        let (l, c, r) = (x[k - 1] as f64, x[k] as f64, x[k + 1] as f64);
        let den = l - 2.0 * c + r;
        if den < 0.0 {
            pos += (0.5 * (l - r) / den).clamp(-0.5, 0.5);
        }
    }
    Some(OutgoingFacts {
        energy_v_ns,
        peak_ns: start_ns + pos * sample_ns,
    })
}

/// The radiometric calibration of whole pulses (what the `calibrate` stage runs).
pub struct Calibrate {
    config: CalibrateConfig,
    metres_per_ns: f64,
}

impl Calibrate {
    /// Builds the calibration for a configuration the caller has checked
    /// ([`Calibrate::try_new`] checks it).
    pub fn new(config: CalibrateConfig) -> Self {
        Calibrate {
            metres_per_ns: config.metres_per_ns(),
            config,
        }
    }

    /// Builds the stage after [`CalibrateConfig::validate`].
    pub fn try_new(config: CalibrateConfig) -> Result<Self, CalibrateError> {
        config.validate()?;
        Ok(Calibrate::new(config))
    }

    /// The configuration in force.
    pub fn config(&self) -> &CalibrateConfig {
        &self.config
    }
}

impl Calibrate {
    /// Calibrates `p` (what the `calibrate` stage does to each pulse): [`Pulse::calibration`]
    /// set and every return's backscatter computed; notes for the factors left out.
    pub fn calibrate(&self, p: &mut Pulse) -> Verdict {
        let c = &self.config;
        let n = p.raw.len();
        if p.segments.iter().any(|s| s.range().end > n) {
            return Verdict::Reject("segment_out_of_bounds");
        }
        if p.signal.len() != n {
            if !p.signal.is_empty() {
                return Verdict::Reject("signal_length_mismatch");
            }
            let Pulse {
                raw,
                signal,
                gain_v_per_dn,
                offset_v,
                ..
            } = p;
            if c.volts {
                if !(gain_v_per_dn.is_finite() && offset_v.is_finite()) {
                    return Verdict::Reject("bad_digitizer_parameters");
                }
                let (g, o) = (*gain_v_per_dn, *offset_v);
                signal.extend(raw.iter().map(|&v| o + g * v as f32));
            } else {
                signal.extend(raw.iter().map(|&v| v as f32));
            }
        }
        if !(p.sample_ns.is_finite() && p.sample_ns > 0.0) {
            return Verdict::Reject("bad_digitizer_parameters");
        }
        let outgoing = p
            .segments
            .iter()
            .find(|s| s.kind == SegmentKind::Outgoing && s.len > 0)
            .and_then(|s| outgoing_facts(&p.signal[s.range()], s.start_ns, p.sample_ns));
        let energy_ok = outgoing
            .map(|o| o.energy_v_ns.is_finite() && o.energy_v_ns > 0.0)
            .unwrap_or(false);
        let mut notes = [None; 3];

        let mut emission_ns = 0.0;
        let mut range_normalised = c.range;
        if c.range {
            match outgoing.filter(|o| energy_ok && o.peak_ns.is_finite()) {
                Some(o) => emission_ns = o.peak_ns,
                None if c.t0_is_emission == Some(true) => emission_ns = 0.0,
                None => match c.range_unknown {
                    UnknownPolicy::Drop => return Verdict::Drop("range_unknown"),
                    UnknownPolicy::Unscaled => {
                        range_normalised = false;
                        notes[0] = Some("range_unknown");
                    }
                },
            }
        }

        let mut scale = 1.0f64;
        if c.system_constant {
            scale *= c.system_constant_value.unwrap_or(1.0);
        }
        if c.energy {
            let problem = match outgoing {
                None => Some("no_outgoing"),
                Some(o) if energy_ok && (c.reference_energy_v_ns / o.energy_v_ns).is_finite() => {
                    scale *= c.reference_energy_v_ns / o.energy_v_ns;
                    None
                }
                Some(_) => Some("bad_outgoing_energy"),
            };
            if let Some(reason) = problem {
                match c.energy_unknown {
                    UnknownPolicy::Drop => return Verdict::Drop(reason),
                    UnknownPolicy::Unscaled => notes[1] = Some(reason),
                }
            }
        }

        let cal = Calibration {
            scale: scale as f32,
            emission_ns,
            metres_per_ns: self.metres_per_ns,
            reference_range_m: c.reference_range_m,
            range_normalised,
        };
        p.calibration = Some(cal);
        let mut before_emission = false;
        for r in p.returns.iter_mut() {
            r.backscatter = cal.calibrated(r.amplitude, r.time_ns);
            before_emission |= range_normalised && cal.range_m(r.time_ns) <= 0.0;
        }
        if before_emission {
            notes[2] = Some("return_before_emission");
        }
        Verdict::Keep(notes)
    }
}

#[cfg(test)]
mod tests;
