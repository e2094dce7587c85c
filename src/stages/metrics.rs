//! The `metrics` stage: forest structure metrics of every pulse ([`crate::forest::measure`],
//! written by the `pulse_metrics.csv` sink and the metrics rasters), after decompose. Its
//! configuration, [`MetricsConfig`], is the metrics' parameter set (also used by `fwlidar
//! metrics`, `fwlidar process` and the GEDI check), defined beside them; a `ground = "dem"`
//! stage takes the run's DEM when the run starts ([`StageKind::prepare`]).

use super::{BuildError, Products, RunContext, StageKind};
use crate::core::validate::{Validate, Validator, field};
use crate::forest::measure::Metrics;
use crate::pulse::waveform_metrics::{GroundFrom, MAX_PROFILE_BINS};
use crate::forest::pulse_metrics::RunDem;
pub use crate::forest::pulse_metrics::MetricsConfig;
use crate::pipeline::stage::{Emitter, Stage, StageError};
use crate::pulse::Pulse;

impl Validate for MetricsConfig {
    fn validate(&self, path: &str, v: &mut Validator) {
        let nonneg = |x: f64| x.is_finite() && x >= 0.0;
        v.require(
            nonneg(self.smoothing_sigma_ns) && self.smoothing_sigma_ns <= 1000.0,
            field(path, "smoothing_sigma_ns"),
            "must be 0 (the outgoing pulse's σ) or a σ in ns up to 1000",
        );
        v.positive(
            self.front_threshold_sigmas,
            field(path, "front_threshold_sigmas"),
        );
        v.positive(
            self.back_threshold_sigmas,
            field(path, "back_threshold_sigmas"),
        );
        v.positive(self.rho_ratio, field(path, "rho_ratio"));
        v.positive(self.leaf_projection_g, field(path, "leaf_projection_g"));
        v.require(
            self.clumping_omega.is_finite()
                && self.clumping_omega > 0.0
                && self.clumping_omega <= 1.0,
            field(path, "clumping_omega"),
            "must be in (0, 1]",
        );
        v.require(
            nonneg(self.ground_centre_buffer_ns),
            field(path, "ground_centre_buffer_ns"),
            "must be a non-negative number of ns",
        );
        v.positive(self.profile_bin_m, field(path, "profile_bin_m"));
        v.require(
            (1..=MAX_PROFILE_BINS).contains(&self.profile_bins),
            field(path, "profile_bins"),
            format!(
                "must be 1..={}",
                MAX_PROFILE_BINS
            ),
        );
        v.require(
            self.fhd_bin_m.is_finite() && self.fhd_bin_m >= 0.1,
            field(path, "fhd_bin_m"),
            "must be at least 0.1 m",
        );
        v.require(
            self.crown_energy_fraction > 0.0 && self.crown_energy_fraction <= 1.0,
            field(path, "crown_energy_fraction"),
            "must be in (0, 1]",
        );
        v.positive(self.herbaceous_height_m, field(path, "herbaceous_height_m"));
    }
}

impl StageKind for MetricsConfig {
    fn kind(&self) -> &'static str {
        "metrics"
    }

    fn changes_waveform(&self) -> bool {
        false
    }

    /// Hands the run's DEM to a stage that takes its ground from it (`ground = "dem"`).
    fn prepare(&mut self, ctx: &RunContext<'_>) {
        if self.ground == GroundFrom::Dem {
            self.dem = ctx.dem.cloned().map(RunDem);
        }
    }

    fn build(&self) -> Result<Box<dyn Stage>, BuildError> {
        Ok(Box::new(Metrics::new(self.clone())))
    }

    fn needs_dem(&self) -> Option<&'static str> {
        (self.ground == GroundFrom::Dem).then_some("ground")
    }

    fn products(&self) -> Products {
        Products {
            metrics: true,
            ..Products::default()
        }
    }
}

impl Stage for Metrics {
    fn name(&self) -> &'static str {
        "metrics"
    }

    /// Never drops a pulse: a pulse without metrics carries a status saying why (counted by
    /// the `pulse_metrics.csv` sink's report).
    fn process(&mut self, mut pulse: Box<Pulse>, out: &mut Emitter<'_>) -> Result<(), StageError> {
        let m = self.measure(&pulse);
        pulse.metrics = Some(m);
        out.emit(pulse);
        Ok(())
    }
}
