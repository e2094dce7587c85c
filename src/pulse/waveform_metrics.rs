//! The forest structure metrics a pulse carries after the `metrics` stage
//! ([`super::Pulse::metrics`]): the values, and why a pulse has none. Computed in
//! `forest::pulse_metrics`; defined here, below the pulse, so that the pulse does not depend on
//! the forest products.

use serde::{Deserialize, Serialize};

/// Most height bins of the PAVD profile.
pub const MAX_PROFILE_BINS: usize = 32;

/// Where the metrics' ground (height 0 of every RH, profile and cover) is taken from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GroundFrom {
    /// The waveform's lowest mode (GEDI L2A): needs a ground echo, which dense crowns hide.
    #[default]
    LowestMode,
    /// The beam's crossing of the run's DEM (`[georeference] dem`); the lowest mode for a
    /// pulse without geometry or outside the DEM.
    Dem,
}

impl GroundFrom {
    /// Short name for the CSV's `ground_from` column.
    pub fn as_str(&self) -> &'static str {
        match self {
            GroundFrom::LowestMode => "lowest_mode",
            GroundFrom::Dem => "dem",
        }
    }
}

/// Why a pulse has no metrics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum MetricsStatus {
    /// Metrics computed.
    #[default]
    Ok,
    /// The smoothed waveform never rises above the front threshold (no signal).
    NoSignal,
    /// The signal never rises above the back threshold, or ends before it starts.
    NoGround,
    /// No return segment, or it is longer than the metrics measure
    /// (`forest::pulse_metrics::MAX_METRIC_SAMPLES`).
    NoWaveform,
    /// A sample or the noise figures are not finite.
    NonFinite,
}

impl MetricsStatus {
    /// Short name for reports and the CSV's `status` column.
    pub fn as_str(&self) -> &'static str {
        match self {
            MetricsStatus::Ok => "ok",
            MetricsStatus::NoSignal => "no_signal",
            MetricsStatus::NoGround => "no_ground",
            MetricsStatus::NoWaveform => "no_waveform",
            MetricsStatus::NonFinite => "non_finite",
        }
    }
}

/// The metrics of one pulse (`pulse_metrics.csv`, `docs/forest.md`). Heights in metres above
/// the ground centre (the lowest mode), times in ns on the pulse's time axis; NaN where a value
/// does not exist (e.g. every field but `status` when it is not `Ok`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WaveformMetrics {
    /// Whether metrics were computed.
    pub status: MetricsStatus,
    /// Noise mean and σ used, signal units.
    pub noise_mean: f32,
    /// Noise standard deviation used, signal units.
    pub noise_sd: f32,
    /// Smoothing σ used, ns.
    pub smoothing_ns: f32,
    /// Signal start (canopy top), ns.
    pub top_ns: f64,
    /// Signal end, ns.
    pub bottom_ns: f64,
    /// Ground (centre of the lowest mode), ns.
    pub ground_ns: f64,
    /// Vertical metres per ns of the time axis (positive: later is lower).
    pub vertical_m_per_ns: f64,
    /// Zenith angle of the beam, degrees (0: nadir; 0 when the pulse has no geometry).
    pub zenith_deg: f32,
    /// Relative heights RH0…RH100, m above the ground.
    pub rh: [f32; 101],
    /// Time between 10 % and 90 % of the cumulated energy, ns.
    pub energy_10_90_ns: f32,
    /// Modes (local maxima of the smoothed waveform above the back threshold).
    pub modes: u16,
    /// Canopy top to crown base, m (crown base: `crown_energy_fraction` of the canopy energy
    /// lies above it); 0 without canopy energy.
    pub crown_thickness_m: f32,
    /// Energy between signal start and end, signal units × bins.
    pub energy_total: f32,
    /// Ground energy `Rg` (area of the fitted ground echo), signal units × bins.
    pub energy_ground: f32,
    /// Canopy energy `Rv = total − Rg`, signal units × bins.
    pub energy_canopy: f32,
    /// Canopy cover, 0..1.
    pub cover: f32,
    /// Gap probability at the beam's zenith angle, 0..1.
    pub pgap: f32,
    /// Plant area index, m²/m².
    pub pai: f32,
    /// Foliage height diversity (Shannon index of the PAVD in `fhd_bin_m` bins).
    pub fhd: f32,
    /// Plant area volume density per `profile_bin_m` bin from the ground up, m²/m³.
    pub pavd: [f32; MAX_PROFILE_BINS],
    /// Number of meaningful bins in `pavd`.
    pub pavd_bins: u8,
    /// σ of the fitted ground echo, m of height (the seed's herbaceous metric: grass widens it).
    pub ground_sigma_m: f32,
    /// Skewness parameter γ of the fitted extended Gaussian ground echo.
    pub ground_skew: f32,
    /// Share of the total energy between the ground centre and `herbaceous_height_m` above it,
    /// ground echo excluded, 0..1.
    pub energy_lowest_m: f32,
    /// Canopy top above the ground, m (`top`: the signal start, = RH100, or its leading edge).
    pub canopy_height: f32,
    /// Ground position `[x, y, z]` in the CRS of the pulse's geometry (NaN without geometry).
    pub ground_xyz: [f64; 3],
    /// Where the ground came from: the lowest mode, or the beam's crossing of the DEM.
    pub ground_from: GroundFrom,
    /// The waveform's lowest mode, ns on the pulse's time axis (the ground with
    /// `ground = "lowest_mode"`; with a DEM ground, what grass or understorey lifts).
    pub mode_ns: f64,
    /// Signal start (canopy top) position `[x, y, z]` along the beam (NaN without geometry):
    /// where an off-nadir beam met the canopy top, not above its ground point.
    pub top_xyz: [f64; 3],
}

impl Default for WaveformMetrics {
    fn default() -> Self {
        WaveformMetrics {
            status: MetricsStatus::NoWaveform,
            noise_mean: f32::NAN,
            noise_sd: f32::NAN,
            smoothing_ns: f32::NAN,
            top_ns: f64::NAN,
            bottom_ns: f64::NAN,
            ground_ns: f64::NAN,
            vertical_m_per_ns: f64::NAN,
            zenith_deg: f32::NAN,
            rh: [f32::NAN; 101],
            energy_10_90_ns: f32::NAN,
            modes: 0,
            crown_thickness_m: f32::NAN,
            energy_total: f32::NAN,
            energy_ground: f32::NAN,
            energy_canopy: f32::NAN,
            cover: f32::NAN,
            pgap: f32::NAN,
            pai: f32::NAN,
            fhd: f32::NAN,
            pavd: [f32::NAN; MAX_PROFILE_BINS],
            pavd_bins: 0,
            ground_sigma_m: f32::NAN,
            ground_skew: f32::NAN,
            energy_lowest_m: f32::NAN,
            canopy_height: f32::NAN,
            ground_xyz: [f64::NAN; 3],
            ground_from: GroundFrom::LowestMode,
            mode_ns: f64::NAN,
            top_xyz: [f64::NAN; 3],
        }
    }
}
