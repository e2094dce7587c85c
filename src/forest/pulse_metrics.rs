//! Forest structure metrics of one waveform: ground, canopy top, relative heights RH0–RH100,
//! energy duration, modes, crown thickness, ground and canopy energy, gap probability, cover,
//! plant area index (PAI), plant area volume density profile (PAVD), foliage height diversity
//! (FHD) and the herbaceous metrics of the ground echo.
//!
//! The definitions follow NASA GEDI's Level 2A and 2B algorithm documents (facts and formulas
//! only; `docs/forest.md` gives them with the settings matched), applied to any waveform:
//!
//! 1. The waveform is smoothed with a Gaussian of σ = `smoothing_sigma_ns` (GEDI: 6.5 ns, about
//!    its own outgoing pulse's σ).
//! 2. Signal start (canopy top) is the first crossing of `noise mean + front_threshold_sigmas ×
//!    noise σ` by the smoothed waveform, signal end the last crossing of `mean +
//!    back_threshold_sigmas × σ` (GEDI algorithm setting group 1: 3 and 6), both to a fraction
//!    of a bin.
//! 3. The ground is the lowest mode: the last local maximum of the smoothed waveform above the
//!    back threshold (parabolic peak to a fraction of a bin).
//! 4. RH n is the height above the ground at which the energy of the smoothed waveform above
//!    the noise mean, accumulated from the signal end upwards, reaches n % of the energy between
//!    start and end (heights are negative below the ground centre).
//! 5. Ground energy `Rg` is the area of an extended (skewed) Gaussian fitted to the raw waveform
//!    from 1.5 smoothing σ above the ground to the signal end, its centre held within
//!    `ground_centre_buffer_ns` of the lowest mode (GEDI L2B); canopy energy `Rv` is the rest of
//!    the energy. Cover = `Rv / (Rv + ρ Rg)` with `ρ = ρv/ρg` (`rho_ratio`, GEDI 1.5); gap
//!    probability `Pgap = 1 − cover`; `PAI = −ln(Pgap) cos θ / (G Ω)` with θ the beam's zenith
//!    angle, `G` = 0.5 (spherical leaf angles), `Ω` = 1 (no clumping).
//! 6. The canopy energy profile (waveform energy minus the fitted ground, above the ground)
//!    gives cover and PAI cumulated from the top down to each height, PAVD per height bin
//!    (`profile_bin_m`) as the PAI added in the bin per metre, and FHD = `−Σ p ln p` over the
//!    PAVD of `fhd_bin_m` bins.
//!
//! Units: times in ns on the pulse's time axis, heights in metres above the ground centre,
//! energies in signal units × bins (sum of samples above the noise mean).
//!
//! The computation reuses buffers held by [`MetricsComputer`]: no allocation per pulse once the
//! longest waveform has been seen.

// The 4 × 4 normal equations and the solver index rows and columns by number, as written.
#![allow(clippy::needless_range_loop)]

use std::cell::Cell;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::core::units::HALF_C_M_PER_NS;
use crate::geo::dem::Dem;
use crate::pulse::waveform_metrics::{
    GroundFrom, MAX_PROFILE_BINS, MetricsStatus, WaveformMetrics,
};

/// Largest supported waveform, samples (GEDI records are 1 000–1 400; airborne gates less).
pub const MAX_METRIC_SAMPLES: usize = 65_536;

/// Sub-bin steps per bin of the energy integration grid (GEDI's `rx_subbin_resolution`).
const SUBBINS: usize = 4;

/// Which waveform of the pulse the metrics are computed from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum MetricsSource {
    /// The raw received waveform (counts converted to signal units): GEDI L2A's input.
    #[default]
    Raw,
    /// The processed signal (after denoise and, where configured, deconvolution): the seed's
    /// view of what deconvolution does to the metrics.
    Signal,
}

/// Where the canopy top (`canopy_height`, the canopy height model) is put on the waveform.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum TopFrom {
    /// The signal start (GEDI's RH100): the front threshold's crossing, ahead of the first
    /// surface by the rise of the system pulse to that threshold (about 2.5 σ of the
    /// outgoing pulse and smoothing together, 2 m for a 16 ns pulse).
    #[default]
    SignalStart,
    /// The signal start moved later by that rise: `σs √(2 ln(A / T))` with σs the system
    /// pulse's σ (the waveform's pulse, `pulse_sigma_ns`, and the smoothing together), A the
    /// first mode's and T the threshold's height above the noise mean — where a surface
    /// whose echo peaks at A starts (exact for a point target, within 0.8 σs for a dense
    /// crown's erf-shaped edge); never past the first mode.
    LeadingEdge,
}

/// The run's DEM handed to the metrics stage (filled from `[georeference] dem` when the run
/// starts, by the stage's `prepare`, `stages/metrics.rs`; never read from a file).
#[derive(Clone, Debug)]
pub struct RunDem(pub Arc<Dem>);

impl PartialEq for RunDem {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// Settings of the waveform metrics (`type = "metrics"`, `docs/forest.md`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetricsConfig {
    /// Waveform the metrics are computed from: `raw` (default) or `signal`.
    #[serde(default)]
    pub source: MetricsSource,
    /// σ of the Gaussian smoothing, ns. 0 (default): the σ of the pulse's own outgoing pulse
    /// (its FWHM / 2.355) when it recorded one, else [`MetricsConfig::FALLBACK_SMOOTHING_NS`];
    /// with `source = "signal"`, no smoothing.
    #[serde(default)]
    pub smoothing_sigma_ns: f64,
    /// Signal start threshold, noise σ above the noise mean. Default 3 (GEDI group 1).
    #[serde(default = "default_front")]
    pub front_threshold_sigmas: f64,
    /// Signal end and mode threshold, noise σ above the noise mean. Default 6 (GEDI group 1).
    #[serde(default = "default_back")]
    pub back_threshold_sigmas: f64,
    /// Ratio of canopy to ground reflectance `ρv/ρg` in the cover formula. Default 1.5 (GEDI
    /// L2B's 0.6 / 0.4).
    #[serde(default = "default_rho_ratio")]
    pub rho_ratio: f64,
    /// Projection of unit leaf area on the plane normal to the beam, `G`. Default 0.5
    /// (spherical leaf angle distribution).
    #[serde(default = "default_g")]
    pub leaf_projection_g: f64,
    /// Clumping index `Ω`. Default 1 (random foliage).
    #[serde(default = "default_omega")]
    pub clumping_omega: f64,
    /// How far the ground echo's fitted centre may move from the lowest mode, ns. Default 4.
    #[serde(default = "default_buffer")]
    pub ground_centre_buffer_ns: f64,
    /// Height of one PAVD profile bin, m. Default 5 (GEDI L2B `dz`).
    #[serde(default = "default_profile_bin")]
    pub profile_bin_m: f64,
    /// Number of PAVD profile bins, at most 32. Default 30 (0–150 m).
    #[serde(default = "default_profile_bins")]
    pub profile_bins: usize,
    /// Height bin of the FHD profile, m. Default 1.
    #[serde(default = "default_fhd_bin")]
    pub fhd_bin_m: f64,
    /// Fraction of the canopy energy above the crown base (crown thickness = canopy top −
    /// crown base). Default 0.95.
    #[serde(default = "default_crown_fraction")]
    pub crown_energy_fraction: f64,
    /// Height above the ground of the herbaceous layer whose energy share is reported
    /// (`energy_lowest_m`), m. Default 1.
    #[serde(default = "default_herb_height")]
    pub herbaceous_height_m: f64,
    /// Ground: `lowest_mode` (default) or `dem` (the beam's crossing of `[georeference] dem`).
    #[serde(default)]
    pub ground: GroundFrom,
    /// Canopy top: `signal_start` (default, GEDI RH100) or `leading_edge` (the signal start
    /// corrected for the rise of the system pulse: unbiased tree heights).
    #[serde(default)]
    pub top: TopFrom,
    /// σ of the pulse in the measured waveform, ns, for `top = "leading_edge"`. 0 (default):
    /// the outgoing pulse's σ for `source = "raw"`, none (a deconvolved signal) for
    /// `source = "signal"`.
    #[serde(default)]
    pub pulse_sigma_ns: f64,
    /// The run's DEM (with `ground = "dem"`): attached when the run starts, not configured.
    #[serde(skip)]
    pub dem: Option<RunDem>,
}

fn default_front() -> f64 {
    3.0
}
fn default_back() -> f64 {
    6.0
}
fn default_rho_ratio() -> f64 {
    1.5
}
fn default_g() -> f64 {
    0.5
}
fn default_omega() -> f64 {
    1.0
}
fn default_buffer() -> f64 {
    4.0
}
fn default_profile_bin() -> f64 {
    5.0
}
fn default_profile_bins() -> usize {
    30
}
fn default_fhd_bin() -> f64 {
    1.0
}
fn default_crown_fraction() -> f64 {
    0.95
}
fn default_herb_height() -> f64 {
    1.0
}

impl Default for MetricsConfig {
    fn default() -> Self {
        MetricsConfig {
            source: MetricsSource::Raw,
            smoothing_sigma_ns: 0.0,
            front_threshold_sigmas: default_front(),
            back_threshold_sigmas: default_back(),
            rho_ratio: default_rho_ratio(),
            leaf_projection_g: default_g(),
            clumping_omega: default_omega(),
            ground_centre_buffer_ns: default_buffer(),
            profile_bin_m: default_profile_bin(),
            profile_bins: default_profile_bins(),
            fhd_bin_m: default_fhd_bin(),
            crown_energy_fraction: default_crown_fraction(),
            herbaceous_height_m: default_herb_height(),
            ground: GroundFrom::LowestMode,
            top: TopFrom::SignalStart,
            pulse_sigma_ns: 0.0,
            dem: None,
        }
    }
}

impl MetricsConfig {
    /// Smoothing σ without an outgoing pulse to measure, ns (GEDI's setting group 1).
    pub const FALLBACK_SMOOTHING_NS: f64 = 6.5;
}

/// One waveform to measure.
#[derive(Clone, Copy, Debug)]
pub struct WaveformInput<'a> {
    /// Samples, signal units, in time order.
    pub samples: &'a [f32],
    /// Time of the first sample, ns after the pulse's t0.
    pub start_ns: f64,
    /// Sample interval, ns.
    pub sample_ns: f64,
    /// Noise mean and σ of the samples, signal units.
    pub noise_mean: f64,
    /// Noise standard deviation, signal units.
    pub noise_sd: f64,
    /// Smoothing σ, ns.
    pub smoothing_ns: f64,
    /// σ of the pulse in `samples` (before smoothing), ns; 0 when none (a deconvolved signal).
    /// Used by `top = "leading_edge"`.
    pub pulse_sigma_ns: f64,
    /// Position at t0 and displacement per ns (the pulse's geometry), if known.
    pub geometry: Option<crate::pulse::PulseGeometry>,
    /// Whether the geometry's x/y are degrees (geographic CRS): the zenith angle is then taken
    /// from the vertical component alone.
    pub geographic: bool,
}

/// Computes [`WaveformMetrics`] with reused buffers.
#[derive(Debug, Default)]
pub struct MetricsComputer {
    smooth: Vec<f64>,
    kernel: Vec<f64>,
    /// σ, bins, that `kernel` was built for.
    kernel_sigma_bins: f64,
    energy: Vec<f64>,
    heights: Vec<f64>,
    canopy: Vec<f64>,
    cum: Vec<f64>,
    padded: Vec<f64>,
    /// Work buffers of the ground echo's fit.
    fit: FitScratch,
    /// PAI of the FHD's layers, m²/m².
    layers: Vec<f64>,
}

impl MetricsComputer {
    /// A computer with buffers for waveforms of up to `samples` samples (they grow if needed).
    pub fn with_capacity(samples: usize) -> Self {
        MetricsComputer {
            smooth: Vec::with_capacity(samples),
            kernel: Vec::with_capacity(256),
            kernel_sigma_bins: 0.0,
            energy: Vec::with_capacity(samples * SUBBINS + 1),
            heights: Vec::with_capacity(samples * SUBBINS + 1),
            canopy: Vec::with_capacity(samples * SUBBINS + 1),
            cum: Vec::with_capacity(samples * SUBBINS + 2),
            padded: Vec::with_capacity(samples + 512),
            fit: FitScratch::default(),
            layers: Vec::with_capacity(256),
        }
    }

    /// The metrics of one waveform.
    pub fn compute(&mut self, config: &MetricsConfig, w: &WaveformInput<'_>) -> WaveformMetrics {
        let mut m = WaveformMetrics::default();
        m.status = match self.fill_metrics(config, w, &mut m) {
            Ok(()) => MetricsStatus::Ok,
            Err(status) => status,
        };
        m
    }

    /// Fills `m` step by step (the steps of the module's documentation); `Err` with the
    /// status of the step that found no metrics, `m` then filled up to that step.
    fn fill_metrics(
        &mut self,
        config: &MetricsConfig,
        w: &WaveformInput<'_>,
        m: &mut WaveformMetrics,
    ) -> Result<(), MetricsStatus> {
        check_input(w)?;
        let dt = w.sample_ns;
        let mean = w.noise_mean;
        let sd = w.noise_sd.max(0.0);
        m.noise_mean = mean as f32;
        m.noise_sd = sd as f32;
        m.smoothing_ns = w.smoothing_ns as f32;
        let (vz, zenith) = beam_geometry(w);
        m.vertical_m_per_ns = vz;
        m.zenith_deg = zenith.to_degrees() as f32;
        let vz_bin = vz * dt; // metres of height per bin

        // 1. Smoothing (Gaussian, edges held at the end samples).
        let sigma_bins = w.smoothing_ns / dt;
        self.smooth_into(w.samples, sigma_bins);
        let s = &self.smooth;

        // 2. Signal start and end.
        let front = mean + config.front_threshold_sigmas * sd;
        let back = mean + config.back_threshold_sigmas * sd;
        let extent = signal_extent(s, config, w, front, back)?;

        // 3. Modes and the lowest one.
        let modes = find_modes(s, extent.first, extent.last, back);
        m.modes = modes.count;
        m.mode_ns = w.start_ns + modes.centre * dt;
        let ground = match extent.dem_ground {
            Some(g) => {
                m.ground_from = GroundFrom::Dem;
                g
            }
            None => modes.centre,
        };

        // 4. Energy on a sub-bin grid from the top to the bottom, relative heights.
        let start_grid = energy_grid(
            s,
            mean,
            &extent,
            ground,
            vz_bin,
            &mut self.energy,
            &mut self.heights,
        );
        let total: f64 = self.energy.iter().sum();
        if total.is_nan() || total <= 0.0 || self.energy.len() < 2 {
            return Err(MetricsStatus::NoSignal);
        }
        let (t10, t90) =
            relative_heights(&self.energy, &self.heights, total, start_grid, &mut m.rh);
        m.energy_10_90_ns = ((t90 - t10) * dt) as f32;
        m.bottom_ns = w.start_ns + extent.bottom * dt;
        m.ground_ns = w.start_ns + ground * dt;
        let peak_at = modes.first.unwrap_or(modes.lowest);
        let top_edge = canopy_top(config.top, w, s, extent.top, peak_at, front);
        m.top_ns = w.start_ns + top_edge * dt;
        m.canopy_height = match config.top {
            TopFrom::SignalStart => m.rh[100],
            TopFrom::LeadingEdge => ((ground - top_edge) * vz_bin) as f32,
        };
        m.energy_total = total as f32;

        // 5. Ground echo, ground and canopy energy, cover, gap probability and PAI.
        let fit = fit_ground_echo(
            &mut self.fit,
            config,
            w,
            s,
            ground,
            extent.bottom,
            sigma_bins,
        );
        let (rv, gaps) = partition_energy(config, &fit, total, zenith, vz_bin, m);

        // 6. Canopy energy profile, PAVD, FHD, crown thickness and the herbaceous layer.
        self.canopy_structure(config, &fit.smoothed(sigma_bins), start_grid, gaps, rv, m);
        let herb = herbaceous_energy(&self.canopy, &self.heights, config.herbaceous_height_m);
        m.energy_lowest_m = (herb / total) as f32;

        if let Some(g) = w.geometry {
            m.ground_xyz = g.at(m.ground_ns);
            m.top_xyz = g.at(m.top_ns);
        }
        Ok(())
    }

    /// Step 6 into `m`: the canopy energy profile (`canopy`, its prefix sums `cum`) of the
    /// energy grid (first point `start_grid` bins) less `ground_echo` (the fitted ground echo
    /// smoothed like the waveform), scaled to the canopy energy `rv` (signal units × bins);
    /// then the PAVD profile, FHD and crown thickness, with the cover and PAI of `gaps`.
    fn canopy_structure(
        &mut self,
        config: &MetricsConfig,
        ground_echo: &ExtGauss,
        start_grid: f64,
        gaps: GapModel,
        rv: f64,
        m: &mut WaveformMetrics,
    ) {
        canopy_profile(
            &self.energy,
            &self.heights,
            ground_echo,
            start_grid,
            rv,
            &mut self.canopy,
        );
        prefix_sums(&self.canopy, &mut self.cum);
        let above = CanopyAbove::new(&self.heights, &self.cum, gaps);
        pavd_profile(&above, config, m);
        m.fhd = foliage_height_diversity(
            &above,
            self.heights[0].max(0.0),
            config.fhd_bin_m,
            &mut self.layers,
        );
        let crown_top_h = f64::from(m.canopy_height).max(0.0);
        m.crown_thickness_m = crown_thickness(
            &self.canopy,
            &self.heights,
            crown_top_h,
            config.crown_energy_fraction,
            rv,
        );
    }

    fn smooth_into(&mut self, y: &[f32], sigma_bins: f64) {
        let n = y.len();
        self.smooth.clear();
        if sigma_bins.is_nan() || sigma_bins <= 0.05 {
            self.smooth.extend(y.iter().map(|&v| f64::from(v)));
            return;
        }
        let half = ((4.0 * sigma_bins).round() as usize).clamp(1, 1024);
        // The kernel of the last σ is kept: a line's pulses share one σ (bit for bit).
        if self.kernel_sigma_bins.to_bits() != sigma_bins.to_bits() || self.kernel.is_empty() {
            self.kernel.clear();
            let mut sum = 0.0;
            for i in 0..=2 * half {
                let d = i as f64 - half as f64;
                let v = (-0.5 * d * d / (sigma_bins * sigma_bins)).exp();
                sum += v;
                self.kernel.push(v);
            }
            for v in &mut self.kernel {
                *v /= sum;
            }
            self.kernel_sigma_bins = sigma_bins;
        }
        // Edges held at the end samples: a padded copy, then one dot product per sample
        // (`pulse_metrics/smoothing.rs`).
        self.padded.clear();
        self.padded
            .extend(std::iter::repeat_n(f64::from(y[0]), half));
        self.padded.extend(y.iter().map(|&v| f64::from(v)));
        self.padded
            .extend(std::iter::repeat_n(f64::from(y[n - 1]), half));
        smooth_padded(&self.padded, &self.kernel, n, &mut self.smooth);
    }
}

/// Whether `w` can be measured: `Err(NoWaveform)` unless it has 4 to [`MAX_METRIC_SAMPLES`]
/// samples and a positive sample interval, `Err(NonFinite)` for a sample, noise figure or
/// smoothing σ that is not finite.
fn check_input(w: &WaveformInput<'_>) -> Result<(), MetricsStatus> {
    let n = w.samples.len();
    if !(4..=MAX_METRIC_SAMPLES).contains(&n) || w.sample_ns.is_nan() || w.sample_ns <= 0.0 {
        return Err(MetricsStatus::NoWaveform);
    }
    if !(w.noise_mean.is_finite() && w.noise_sd.is_finite() && w.smoothing_ns.is_finite())
        || w.samples.iter().any(|v| !v.is_finite())
    {
        return Err(MetricsStatus::NonFinite);
    }
    Ok(())
}

/// The beam's vertical metres per ns of the time axis (positive: later is lower) and zenith
/// angle, radians, from the pulse's geometry; c/2 and 0 (nadir) without a usable geometry.
/// The zenith angle is 0 for geographic coordinates (degrees are no length).
fn beam_geometry(w: &WaveformInput<'_>) -> (f64, f64) {
    match w.geometry {
        Some(g) => {
            let d = g.direction;
            let vz = -d[2];
            let zen = if w.geographic || !(d[0].is_finite() && d[1].is_finite()) {
                0.0
            } else {
                let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if norm > 0.0 {
                    (vz.abs() / norm).clamp(-1.0, 1.0).acos()
                } else {
                    0.0
                }
            };
            if vz.is_finite() && vz != 0.0 {
                (vz, zen)
            } else {
                (HALF_C_M_PER_NS, 0.0)
            }
        }
        None => (HALF_C_M_PER_NS, 0.0),
    }
}

/// Where the signal lies on the smoothed waveform (step 2), bins from its first sample.
struct SignalExtent {
    /// First sample above the front threshold.
    first: usize,
    /// Last sample above the back threshold (above the front one for a DEM ground without a
    /// return above the back threshold).
    last: usize,
    /// Signal start, bins (to a fraction of a bin).
    top: f64,
    /// Signal end, bins (to a fraction of a bin).
    bottom: f64,
    /// The beam's crossing of the DEM, bins, when the ground is the DEM's and the beam
    /// crosses it.
    dem_ground: Option<f64>,
}

/// The signal start and end on the smoothed waveform `s` (step 2) for the front and back
/// thresholds (signal units), and the DEM's ground where asked for. `Err(NoSignal)` when `s`
/// never rises above the front threshold, `Err(NoGround)` when no end is found or it is not
/// after the start.
fn signal_extent(
    s: &[f64],
    config: &MetricsConfig,
    w: &WaveformInput<'_>,
    front: f64,
    back: f64,
) -> Result<SignalExtent, MetricsStatus> {
    let n = s.len();
    let dt = w.sample_ns;
    let Some(first) = s.iter().position(|&v| v > front) else {
        return Err(MetricsStatus::NoSignal);
    };
    // The DEM's ground, when asked for and the beam crosses it.
    let dem_ground = match (config.ground, &config.dem, w.geometry) {
        (GroundFrom::Dem, Some(dem), Some(g)) if !w.geographic => {
            let guess = w.start_ns + 0.5 * (n - 1) as f64 * dt;
            dem_crossing_ns(&dem.0, &g, guess).map(|t| (t - w.start_ns) / dt)
        }
        _ => None,
    };
    // Signal end: the last crossing of the back threshold (with a DEM ground, of the front
    // one when no return clears the back threshold: a canopy without ground echo).
    let Some(last) = s
        .iter()
        .rposition(|&v| v > back)
        .or_else(|| dem_ground.and_then(|_| s.iter().rposition(|&v| v > front)))
    else {
        return Err(MetricsStatus::NoGround);
    };
    let end_level = if s[last] > back { back } else { front };
    let top = if first == 0 {
        0.0
    } else {
        let (a, b) = (s[first - 1], s[first]);
        (first - 1) as f64 + ((front - a) / (b - a)).clamp(0.0, 1.0)
    };
    let bottom = if last + 1 >= n {
        (n - 1) as f64
    } else {
        let (a, b) = (s[last], s[last + 1]);
        last as f64 + ((a - end_level) / (a - b)).clamp(0.0, 1.0)
    };
    if bottom <= top {
        return Err(MetricsStatus::NoGround);
    }
    Ok(SignalExtent {
        first,
        last,
        top,
        bottom,
        dem_ground,
    })
}

/// The modes of the signal (step 3): local maxima of the smoothed waveform above the back
/// threshold.
struct Modes {
    /// How many.
    count: u16,
    /// Sample of the lowest (last) mode; without a mode, the signal's highest sample.
    lowest: usize,
    /// Sample of the first mode, if any.
    first: Option<usize>,
    /// Centre of the lowest mode, bins (parabolic peak, within half a bin of `lowest`).
    centre: f64,
}

/// The modes of the smoothed waveform `s` between its samples `first` and `last` (the
/// signal's), above `back` (signal units).
fn find_modes(s: &[f64], first: usize, last: usize, back: f64) -> Modes {
    let n = s.len();
    let mut modes = 0u16;
    let mut lowest: Option<usize> = None;
    let mut first_mode: Option<usize> = None;
    let lo = first.max(1);
    let hi = (last + 1).min(n - 1);
    for k in lo..hi {
        if s[k] > back && s[k - 1] < s[k] && s[k] >= s[k + 1] {
            modes = modes.saturating_add(1);
            lowest = Some(k);
            first_mode.get_or_insert(k);
        }
    }
    let k = lowest.unwrap_or_else(|| {
        let mut best = first;
        for i in first..=last {
            if s[i] > s[best] {
                best = i;
            }
        }
        best
    });
    let centre = if k >= 1 && k + 1 < n {
        let (a, b, c) = (s[k - 1], s[k], s[k + 1]);
        let den = a - 2.0 * b + c;
        if den < 0.0 {
            k as f64 + (0.5 * (a - c) / den).clamp(-0.5, 0.5)
        } else {
            k as f64
        }
    } else {
        k as f64
    };
    Modes {
        count: modes,
        lowest: k,
        first: first_mode,
        centre,
    }
}

/// Fills `energy` (signal units × bins) and `heights` (m above `ground`) on the sub-bin grid
/// from the signal's top to its bottom (step 4): the smoothed waveform `s` interpolated
/// linearly, above the noise `mean`, negative parts clipped; `vz_bin` is metres of height per
/// bin. Returns the grid's first point, bins.
fn energy_grid(
    s: &[f64],
    mean: f64,
    extent: &SignalExtent,
    ground: f64,
    vz_bin: f64,
    energy: &mut Vec<f64>,
    heights: &mut Vec<f64>,
) -> f64 {
    let n = s.len();
    let step = 1.0 / SUBBINS as f64;
    let start_grid = (extent.top * SUBBINS as f64).ceil() / SUBBINS as f64;
    energy.clear();
    heights.clear();
    let mut x = start_grid;
    while x <= extent.bottom + 1e-9 {
        // `x as usize` is `x.floor() as usize` for every `x` (truncation is the floor at and
        // above 0; below, both saturate to 0), without a libm `floor` call per grid point.
        let i = (x as usize).min(n - 1);
        let f = x - i as f64;
        let v = if i + 1 < n {
            s[i] * (1.0 - f) + s[i + 1] * f
        } else {
            s[i]
        };
        energy.push((v - mean).max(0.0) * step);
        heights.push((ground - x) * vz_bin);
        x += step;
    }
    start_grid
}

/// `n / 100` for RH n, n = 0…100 (the same divisions, made once).
const RH_FRACTIONS: [f64; 101] = {
    let mut f = [0.0; 101];
    let mut n = 0;
    while n <= 100 {
        f[n] = n as f64 / 100.0;
        n += 1;
    }
    f
};

/// RH0…RH100 into `rh` (m above the ground): the heights at which the `energy` of the grid
/// (first point `start_grid` bins, `heights` in m), cumulated from the bottom, reaches n % of
/// `total`. Returns the grid positions (bins) where 10 % and 90 % of the energy lie above.
fn relative_heights(
    energy: &[f64],
    heights: &[f64],
    total: f64,
    start_grid: f64,
    rh: &mut [f32; 101],
) -> (f64, f64) {
    let step = 1.0 / SUBBINS as f64;
    let mut rh_idx = 0usize;
    let mut cum = 0.0;
    let len = energy.len();
    let mut t10 = f64::NAN;
    let mut t90 = f64::NAN;
    // The fraction below the previous grid point: the previous point's `cum / total` (0 / total
    // before the first).
    let mut frac = 0.0 / total;
    for j in (0..len).rev() {
        cum += energy[j];
        let frac_prev = frac;
        frac = cum / total;
        while rh_idx <= 100 && frac + 1e-12 >= RH_FRACTIONS[rh_idx] {
            let target = RH_FRACTIONS[rh_idx];
            // Interpolate between the heights of samples j+1 (at frac_prev) and j (at frac).
            let h_here = heights[j];
            let h_prev = if j + 1 < len { heights[j + 1] } else { h_here };
            let h = if frac > frac_prev {
                h_prev + (h_here - h_prev) * ((target - frac_prev) / (frac - frac_prev))
            } else {
                h_here
            };
            rh[rh_idx] = h as f32;
            rh_idx += 1;
        }
        let tj = start_grid + j as f64 * step;
        if t90.is_nan() && frac >= 0.1 {
            t90 = tj; // 10 % from the bottom = 90 % from the top
        }
        if t10.is_nan() && frac >= 0.9 {
            t10 = tj;
        }
    }
    while rh_idx <= 100 {
        rh[rh_idx] = heights[0] as f32;
        rh_idx += 1;
    }
    (t10, t90)
}

/// The canopy top, bins: the signal start `top`, or with [`TopFrom::LeadingEdge`] the signal
/// start moved later by the rise of the system pulse to the front threshold `front` (signal
/// units), never past the first mode `peak_at` (a sample of the smoothed waveform `s`).
fn canopy_top(
    from: TopFrom,
    w: &WaveformInput<'_>,
    s: &[f64],
    top: f64,
    peak_at: usize,
    front: f64,
) -> f64 {
    match from {
        TopFrom::SignalStart => top,
        TopFrom::LeadingEdge => {
            let mean = w.noise_mean;
            let ps = if w.pulse_sigma_ns.is_finite() {
                w.pulse_sigma_ns.max(0.0)
            } else {
                0.0
            };
            let sys_bins = (ps * ps + w.smoothing_ns * w.smoothing_ns).sqrt() / w.sample_ns;
            let a = s[peak_at] - mean;
            let t = front - mean;
            if a > t && t > 0.0 && sys_bins.is_finite() {
                (top + sys_bins * (2.0 * (a / t).ln()).sqrt()).min(peak_at as f64)
            } else {
                top
            }
        }
    }
}

/// The ground echo (step 5): an extended Gaussian fitted to the raw samples above the noise
/// mean from 1.5 smoothing σ above `ground` to the signal end `bottom` (bins), its centre held
/// within `ground_centre_buffer_ns` of `ground`; `sigma_bins` is the smoothing σ, bins,
/// `scratch` the fit's work buffers. Of
/// area 0 when the ground lies more than that buffer below the signal's end (a DEM ground the
/// beam saw no echo of) or the window is too short to fit.
fn fit_ground_echo(
    scratch: &mut FitScratch,
    config: &MetricsConfig,
    w: &WaveformInput<'_>,
    s: &[f64],
    ground: f64,
    bottom: f64,
    sigma_bins: f64,
) -> ExtGauss {
    let (y, n, mean, dt) = (w.samples, w.samples.len(), w.noise_mean, w.sample_ns);
    let buffer = config.ground_centre_buffer_ns / dt;
    let fit_from = ((ground - 1.5 * sigma_bins).floor().max(0.0)) as usize;
    let fit_to = (bottom.ceil() as usize).min(n - 1);
    let kg = (ground.round().max(0.0) as usize).min(n - 1);
    let peak = (s[kg] - mean).max(0.0);
    let sigma0 = sigma_bins.max(1.0);
    let start = ExtGauss {
        area: peak * sigma0 * SQRT_2PI,
        centre: ground,
        sigma: sigma0,
        gamma: 0.0,
    };
    // A DEM ground below the signal's end: the beam saw no ground echo.
    if ground > bottom + buffer || fit_to < fit_from + 3 {
        ExtGauss {
            area: 0.0,
            centre: ground,
            sigma: sigma0,
            gamma: 0.0,
        }
    } else {
        fit_ext_gauss(
            scratch,
            y,
            mean,
            fit_from,
            fit_to,
            start,
            FitBounds {
                centre: (ground - buffer, ground + buffer),
                sigma: (0.5, (fit_to - fit_from).max(2) as f64),
            },
        )
    }
}

/// Splits the `total` energy (signal units × bins) into ground energy `Rg` (the area of the
/// fitted ground echo `fit`) and canopy energy `Rv` (the rest) into `m`, with the ground echo's
/// width (m, `vz_bin` metres of height per bin) and skew, and the cover, gap probability and
/// PAI at zenith angle `zenith` (radians). Returns `Rv` and the cover model.
fn partition_energy(
    config: &MetricsConfig,
    fit: &ExtGauss,
    total: f64,
    zenith: f64,
    vz_bin: f64,
    m: &mut WaveformMetrics,
) -> (f64, GapModel) {
    let rg = fit.area.clamp(0.0, total);
    let rv = total - rg;
    m.energy_ground = rg as f32;
    m.energy_canopy = rv as f32;
    if fit.area > 0.0 {
        m.ground_sigma_m = (fit.sigma * vz_bin).abs() as f32;
        m.ground_skew = fit.gamma as f32;
    }
    let gaps = GapModel::new(config, rv, rg, zenith);
    let cover = gaps.cover(rv);
    let pgap = (1.0 - cover).clamp(1e-6, 1.0);
    m.cover = cover as f32;
    m.pgap = pgap as f32;
    m.pai = (-pgap.ln() * gaps.k_pai) as f32;
    (rv, gaps)
}

/// Cover and plant area index from canopy and ground energies (step 5): cover `Rv / (Rv + ρ
/// Rg)`, `PAI = −ln(1 − cover) cos θ / (G Ω)`.
#[derive(Clone, Copy)]
struct GapModel {
    /// `Rv + ρ Rg` of the whole waveform, signal units × bins.
    denom: f64,
    /// `cos θ / (G Ω)`: PAI per unit of `−ln Pgap`.
    k_pai: f64,
}

impl GapModel {
    /// The model of a waveform of canopy energy `rv` and ground energy `rg` (signal units ×
    /// bins) seen at zenith angle `zenith` (radians).
    fn new(config: &MetricsConfig, rv: f64, rg: f64, zenith: f64) -> Self {
        let denom = rv + config.rho_ratio * rg;
        let cos_t = zenith.cos();
        let k_pai = cos_t / (config.leaf_projection_g * config.clumping_omega);
        GapModel { denom, k_pai }
    }

    /// Cover (0..1) of canopy energy `canopy` (signal units × bins); 0 without energy.
    fn cover(&self, canopy: f64) -> f64 {
        if self.denom > 0.0 {
            canopy / self.denom
        } else {
            0.0
        }
    }

    /// PAI (m²/m²) of canopy energy `canopy` (signal units × bins), the gap probability held
    /// above 10⁻⁶.
    fn pai(&self, canopy: f64) -> f64 {
        -((1.0 - self.cover(canopy)).clamp(1e-6, 1.0)).ln() * self.k_pai
    }
}

/// The canopy energy profile into `canopy` (step 6), signal units × bins on the energy grid:
/// the `energy` minus the smoothed fitted ground echo `ground` above the ground centre (0 at
/// and below it), scaled to sum to `rv`. The grid starts at `start_grid` bins; `heights` are
/// its heights, m.
fn canopy_profile(
    energy: &[f64],
    heights: &[f64],
    ground: &ExtGauss,
    start_grid: f64,
    rv: f64,
    canopy: &mut Vec<f64>,
) {
    // The energy is of the smoothed waveform, so the ground removed is the fitted echo
    // smoothed alike: a skew-normal convolved with a Gaussian is the skew-normal of
    // σ' = √(σ² + σs²) and δ' = δ σ / σ' (δ = γ / √(1 + γ²)).
    let step = 1.0 / SUBBINS as f64;
    canopy.clear();
    let mut csum = 0.0;
    for (j, &e) in energy.iter().enumerate() {
        // At and below the ground centre the profile is 0, and where the energy is +0 it is
        // `(0 − g).max(0) = +0` whatever the ground echo's value `g` (≥ +0 or NaN: a
        // non-negative area and σ): the echo is evaluated only where it counts.
        let c = if heights[j] > 0.0 && e.to_bits() != 0 {
            let xj = start_grid + j as f64 * step;
            let g = ground.value(xj) * step;
            (e - g).max(0.0)
        } else {
            0.0
        };
        csum += c;
        canopy.push(c);
    }
    if csum > 0.0 {
        let scale = rv / csum;
        for c in canopy.iter_mut() {
            *c *= scale;
        }
    }
}

/// `cum` = 0 and the running sums of `canopy` (one more value than `canopy`).
fn prefix_sums(canopy: &[f64], cum: &mut Vec<f64>) {
    cum.clear();
    let mut acc = 0.0;
    cum.push(0.0);
    for c in canopy {
        acc += c;
        cum.push(acc);
    }
}

/// The canopy above a height: its energy and PAI from the top down. The heights fall with
/// the grid index, so the canopy energy above a height is a prefix sum up to the first grid
/// point below it.
struct CanopyAbove<'a> {
    /// Heights of the energy grid, m above the ground, falling.
    heights: &'a [f64],
    /// Prefix sums of the canopy energy profile ([`prefix_sums`]).
    cum: &'a [f64],
    /// The waveform's cover and PAI model.
    gaps: GapModel,
    /// The last canopy energy's bits and its PAI: the PAVD and FHD ask for the PAI at each
    /// boundary twice, and above the canopy for an energy of 0 again and again.
    last: Cell<Option<(u64, f64)>>,
    /// When `heights` never rises: its first height and the grid points per metre (the grid
    /// is even, so `(first − h) × per_m` lands within a point or two of the answer).
    even: Option<(f64, f64)>,
}

impl<'a> CanopyAbove<'a> {
    /// The canopy above the heights `heights` (m, falling) of the profile whose prefix sums
    /// are `cum`, with the cover and PAI model `gaps`.
    fn new(heights: &'a [f64], cum: &'a [f64], gaps: GapModel) -> Self {
        let falling = heights.windows(2).all(|w| w[0] >= w[1]);
        let even = match (falling, heights.first(), heights.last()) {
            (true, Some(&first), Some(&last)) if heights.len() > 1 && first > last => {
                Some((first, (heights.len() - 1) as f64 / (first - last)))
            }
            _ => None,
        };
        CanopyAbove {
            heights,
            cum,
            gaps,
            last: Cell::new(None),
            even,
        }
    }

    /// Canopy energy above height `h` (m above the ground), signal units × bins.
    fn energy(&self, h: f64) -> f64 {
        self.cum[self.points_at_or_above(h)]
    }

    /// How many grid points lie at or above `h` m: `heights.partition_point(|hh| hh ≥ h)`.
    /// On a grid that never rises the boundary is unique, so it is found by stepping from a
    /// guess on the even grid (one or two steps instead of a binary search); otherwise by
    /// the binary search itself.
    fn points_at_or_above(&self, h: f64) -> usize {
        let Some((first, per_m)) = self.even else {
            return self.heights.partition_point(|&hh| hh >= h);
        };
        let len = self.heights.len();
        // A float-to-int cast saturates (NaN to 0): any guess in 0..=len is a start.
        let mut i = (((first - h) * per_m) as usize).min(len);
        // `!(heights[i − 1] ≥ h)`, NaN included.
        while i > 0
            && !matches!(
                self.heights[i - 1].partial_cmp(&h),
                Some(std::cmp::Ordering::Greater | std::cmp::Ordering::Equal)
            )
        {
            i -= 1;
        }
        while i < len && self.heights[i] >= h {
            i += 1;
        }
        i
    }

    /// PAI of the canopy above height `h` (m above the ground), m²/m² (that of the last
    /// energy asked for when the energy is the same, bit for bit).
    fn pai(&self, h: f64) -> f64 {
        let e = self.energy(h);
        match self.last.get() {
            Some((bits, pai)) if bits == e.to_bits() => pai,
            _ => {
                let pai = self.gaps.pai(e);
                self.last.set(Some((e.to_bits(), pai)));
                pai
            }
        }
    }
}

/// PAVD per `profile_bin_m` bin from the ground up into `m.pavd` (m²/m³, the PAI added in the
/// bin per metre) and the number of bins into `m.pavd_bins`.
fn pavd_profile(above: &CanopyAbove<'_>, config: &MetricsConfig, m: &mut WaveformMetrics) {
    let bins = config.profile_bins.min(MAX_PROFILE_BINS);
    m.pavd_bins = bins as u8;
    let bin_m = config.profile_bin_m;
    for b in 0..bins {
        let lo_h = b as f64 * bin_m;
        m.pavd[b] = ((above.pai(lo_h) - above.pai(lo_h + bin_m)) / bin_m) as f32;
    }
}

/// Foliage height diversity: the Shannon index `−Σ p ln p` of the PAI of `fbin` m layers
/// from the ground to `top_h` m (two passes: the sum, then the entropy; the layers' PAI
/// (m²/m²) kept in `layers` between them).
fn foliage_height_diversity(
    above: &CanopyAbove<'_>,
    top_h: f64,
    fbin: f64,
    layers: &mut Vec<f64>,
) -> f32 {
    let nf = ((top_h / fbin).ceil() as usize).clamp(1, 4096);
    let layer = |b: usize| -> f64 {
        (above.pai(b as f64 * fbin) - above.pai((b + 1) as f64 * fbin)).max(0.0)
    };
    layers.clear();
    layers.extend((0..nf).map(layer));
    let pavd_sum: f64 = layers.iter().sum();
    let mut ent = 0.0;
    if pavd_sum > 0.0 {
        for &v in layers.iter() {
            if v > 0.0 {
                let p = v / pavd_sum;
                ent -= p * p.ln();
            }
        }
    }
    ent as f32
}

/// Crown thickness, m: the canopy top `crown_top_h` (m above the ground) down to the crown
/// base, where `fraction` of the canopy energy `rv` lies above; 0 without canopy energy.
fn crown_thickness(
    canopy: &[f64],
    heights: &[f64],
    crown_top_h: f64,
    fraction: f64,
    rv: f64,
) -> f32 {
    if rv > 0.0 {
        let mut acc = 0.0;
        let mut base_h = crown_top_h;
        for (c, h) in canopy.iter().zip(heights) {
            acc += c;
            base_h = *h;
            if acc >= fraction * rv {
                break;
            }
        }
        (crown_top_h - base_h).max(0.0) as f32
    } else {
        0.0
    }
}

/// Canopy energy between the ground centre and `herb_height_m` above it, signal units × bins.
fn herbaceous_energy(canopy: &[f64], heights: &[f64], herb_height_m: f64) -> f64 {
    canopy
        .iter()
        .zip(heights)
        .filter(|(_, h)| **h > 0.0 && **h <= herb_height_m)
        .map(|(c, _)| *c)
        .sum()
}

/// Time on the pulse's axis (ns) at which its beam crosses the DEM: the fixed point of
/// `t = (DEM(x(t), y(t)) − z0) / dz`, from `guess`. Converges when the terrain's slope times
/// the beam's tangent of zenith is below 1 (any slope under 75° at 15° off nadir); `None`
/// outside the DEM, for a horizontal beam, or without convergence in 12 steps.
pub fn dem_crossing_ns(dem: &Dem, g: &crate::pulse::PulseGeometry, guess: f64) -> Option<f64> {
    let dz = g.direction[2];
    if !(dz.is_finite() && dz.abs() > 1e-12 && guess.is_finite()) {
        return None;
    }
    let mut t = guess;
    for _ in 0..12 {
        let [x, y, _] = g.at(t);
        let z = dem.height_at(x, y)?;
        let next = (z - g.anchor[2]) / dz;
        if !next.is_finite() {
            return None;
        }
        if (next - t).abs() < 1e-4 {
            return Some(next);
        }
        t = next;
    }
    None
}

mod ground_fit;
mod smoothing;

pub use ground_fit::ExtGauss;
#[cfg(test)]
use ground_fit::erf;
use ground_fit::{FitBounds, FitScratch, SQRT_2PI, fit_ext_gauss};
use smoothing::smooth_padded;

#[cfg(test)]
mod tests;
