//! The described scene (`config/scenes/*.toml` without a `[scene]` table): terrain, objects
//! with materials, a flight plan with a scan pattern, the sensor, and the effects to simulate.
//!
//! Every table denies unknown keys; every key is documented here with its unit and default.
//! Positions are in the **scene frame**: metres east, north and up of `[origin]`, the local
//! tangent plane at that point (the scene is flat-earth by definition; the aircraft's navigation
//! is converted exactly to WGS84, so georeferencing the simulated capture lands in this frame).
//!
//! ```toml
//! seed = 7
//! effects = ["noise", "quantisation", "footprint"]
//! [origin]
//! lat_deg = -24.99
//! lon_deg = 31.59
//! [terrain]
//! kind = "flat"
//! [[tree]]
//! position_m = [0.0, 0.0]
//! height_m = 12.0
//! crown = { shape = "ellipsoid", base_m = 5.0, radius_m = 3.0 }
//! leaf_area_density = 0.8
//! [flight]
//! altitude_m = 1000.0
//! lines = [{ start_m = [-100.0, 0.0], end_m = [100.0, 0.0] }]
//! scan = { pattern = "oscillating", half_angle_deg = 15.0, rate_hz = 40.0 }
//! [sensor]
//! profile = "../sensors/optech_altm3100ea_cao.toml"
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::core::sensor::SensorProfile;
use crate::sim::analytic_scene::SceneError;
use crate::sim::navstream::NavigationConfig;

/// A whole described scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldScene {
    /// Seed of every random draw (noise, jitter, leaf and branch layout), ChaCha8. Default 0.
    #[serde(default)]
    pub seed: u64,
    /// GPS time of the first pulse, seconds of the GPS week. Default 345600 (Thursday 00:00).
    #[serde(default = "default_gps_start")]
    pub gps_time_start_s: f64,
    /// The effects to simulate, by name ([`Effect`]); nothing else is. Default none: the
    /// analytic answer (echo = outgoing ⊗ receiver response at 2R/c, amplitude ∝ ρ cos i / R²).
    #[serde(default)]
    pub effects: Vec<Effect>,
    /// The scene frame's origin.
    #[serde(default)]
    pub origin: Origin,
    /// The ground.
    #[serde(default)]
    pub terrain: Terrain,
    /// Reflectances at the sensor's wavelength by material name (0..1). Defaults: `ground`
    /// 0.3, `bark` 0.35, `leaf` 0.45, `grass` 0.4, `roof` 0.2, `wall` 0.25.
    #[serde(default)]
    pub materials: BTreeMap<String, f64>,
    /// Trees: a stem and branch cylinders, a crown envelope filled with leaves.
    #[serde(default)]
    pub tree: Vec<Tree>,
    /// Forests: trees generated from the seed over a rectangle (expanded into `tree`s).
    #[serde(default)]
    pub forest: Vec<Forest>,
    /// Grass patches: a turbid layer of leaves from the terrain up to a height.
    #[serde(default)]
    pub grass: Vec<Grass>,
    /// Boxes (flat-roofed buildings, crates) standing on the terrain.
    #[serde(default, rename = "box")]
    pub boxes: Vec<BoxObject>,
    /// Gable-roofed buildings standing on the terrain.
    #[serde(default)]
    pub roof: Vec<Roof>,
    /// Flight plan and scan pattern.
    pub flight: Flight,
    /// The sensor.
    pub sensor: SceneSensor,
    /// Noise model (used when `effects` has `noise`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<Noise>,
    /// Receiver ringing (used with the `ringing` effect).
    #[serde(default)]
    pub ringing: Ringing,
    /// Timing jitter of the pulse reference time (used with `timing_jitter`): 1-sigma, ns.
    /// Default 0.2.
    #[serde(default = "default_jitter")]
    pub timing_jitter_ns: f64,
    /// Fraction of digitizer frames lost (used with `packet_loss`), 0..1. Default 0.001.
    #[serde(default = "default_loss")]
    pub packet_loss: f64,
    /// Sub-rays across the footprint (used with `footprint`): rings of equal energy around the
    /// axis (1 ring = the axis ray only; 3 rings = 1 + 6 + 12 rays). Default 3.
    #[serde(default = "default_rings")]
    pub footprint_rings: u32,
    /// The navigation stream ([`NavigationConfig`]: rate, NMEA and/or NovAtel binary, noise and
    /// dropouts, which apply only with the `navigation_noise` / `navigation_dropouts` effects).
    /// Default: NMEA (GGA, PASHR, ZDA) at 10 Hz.
    #[serde(default)]
    pub navigation: NavigationConfig,
}

/// The simulated effects. A scene lists those it wants; the cost of a run grows only with them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Effect {
    /// Digitizer noise per sample, as `[noise]` says (uniform, Gaussian or Poisson shot noise).
    Noise,
    /// Rounding to whole counts of the sensor's digitizer (without it: 1/256 count steps).
    Quantisation,
    /// Clipping at the digitizer's range `0 ..= 2^bits − 1` (without it: no upper limit).
    Saturation,
    /// A damped oscillation of the receiver after every echo (`[ringing]`).
    Ringing,
    /// The beam's divergence: sub-rays across the footprint instead of the axis ray alone.
    Footprint,
    /// The scan pattern's angles (without it every pulse looks along the scanner's zero angle).
    OffNadir,
    /// Gaussian jitter of each pulse's reference time (`timing_jitter_ns`).
    TimingJitter,
    /// Gaussian noise on the navigation solution (`[navigation] noise`).
    NavigationNoise,
    /// Navigation outages (`[navigation] dropouts`, `random_dropout_probability`).
    NavigationDropouts,
    /// Digitizer frames lost (`packet_loss`): absent from the capture, listed in the truth.
    PacketLoss,
    /// Multiple scattering: not simulated (named so that asking for it is a clear error).
    MultipleScattering,
}

impl Effect {
    /// The name used in scene files.
    pub fn name(self) -> &'static str {
        match self {
            Effect::Noise => "noise",
            Effect::Quantisation => "quantisation",
            Effect::Saturation => "saturation",
            Effect::Ringing => "ringing",
            Effect::Footprint => "footprint",
            Effect::OffNadir => "off_nadir",
            Effect::TimingJitter => "timing_jitter",
            Effect::NavigationNoise => "navigation_noise",
            Effect::NavigationDropouts => "navigation_dropouts",
            Effect::PacketLoss => "packet_loss",
            Effect::MultipleScattering => "multiple_scattering",
        }
    }
}

/// The scene frame's origin on WGS84.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Origin {
    /// Latitude, degrees. Default -24.99 (Kruger National Park, the seed's CAO flights).
    #[serde(default = "default_lat")]
    pub lat_deg: f64,
    /// Longitude, degrees. Default 31.59.
    #[serde(default = "default_lon")]
    pub lon_deg: f64,
    /// Ellipsoidal height of the frame's origin (the terrain's zero), metres. Default 0 (so that
    /// the default voxel height range of a replay covers a scene's ground).
    #[serde(default = "default_origin_height")]
    pub height_m: f64,
}

impl Default for Origin {
    fn default() -> Self {
        Origin {
            lat_deg: default_lat(),
            lon_deg: default_lon(),
            height_m: default_origin_height(),
        }
    }
}

/// The ground surface.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Terrain {
    /// A horizontal plane.
    Flat {
        /// Height, metres (scene frame). Default 0.
        #[serde(default)]
        height_m: f64,
        /// Material name. Default "ground".
        #[serde(default = "ground")]
        material: String,
    },
    /// A tilted plane through (0, 0, `height_m`).
    Plane {
        /// Height at the origin, metres. Default 0.
        #[serde(default)]
        height_m: f64,
        /// Slope, degrees from horizontal (0 ≤ slope < 80).
        slope_deg: f64,
        /// Direction the slope faces (downhill), degrees clockwise from north.
        #[serde(default)]
        aspect_deg: f64,
        /// Material name. Default "ground".
        #[serde(default = "ground")]
        material: String,
    },
    /// A GeoTIFF DEM (one band of heights, metres), placed with its centre at the scene origin
    /// and its columns east, rows north (its own CRS is not used: a simulated scene is local).
    Geotiff {
        /// Path of the GeoTIFF, relative to the scene file's folder.
        path: PathBuf,
        /// Height subtracted from the DEM's values, metres. Default 0.
        #[serde(default)]
        datum_m: f64,
        /// Material name. Default "ground".
        #[serde(default = "ground")]
        material: String,
    },
}

impl Default for Terrain {
    fn default() -> Self {
        Terrain::Flat {
            height_m: 0.0,
            material: ground(),
        }
    }
}

/// Shape of a crown envelope.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CrownShape {
    /// An ellipsoid of revolution between the crown base and the tree top.
    Ellipsoid,
    /// A cone with its base at the crown base and its apex at the tree top (conifers).
    Cone,
    /// A vertical cylinder.
    Cylinder,
}

/// A crown envelope.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Crown {
    /// Shape. Default ellipsoid.
    #[serde(default = "default_shape")]
    pub shape: CrownShape,
    /// Height of the crown's bottom above the terrain, metres.
    pub base_m: f64,
    /// Largest horizontal radius, metres.
    pub radius_m: f64,
}

/// One first-order branch: a cylinder from the stem.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Branch {
    /// Height of its base on the stem above the terrain, metres.
    pub height_m: f64,
    /// Direction it grows, degrees clockwise from north.
    pub azimuth_deg: f64,
    /// Angle from vertical (0 = up, 90 = horizontal), degrees.
    pub zenith_deg: f64,
    /// Length, metres.
    pub length_m: f64,
    /// Radius, metres.
    pub radius_m: f64,
}

/// A tree standing on the terrain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tree {
    /// Stem base, metres east and north.
    pub position_m: [f64; 2],
    /// Tree height above the terrain, metres.
    pub height_m: f64,
    /// Stem radius, metres. Default 0.15.
    #[serde(default = "default_stem_radius")]
    pub stem_radius_m: f64,
    /// The crown envelope.
    pub crown: Crown,
    /// Leaf area density inside the crown, m² of one-sided leaf area per m³ (0: leaf-off).
    /// Default 0.
    #[serde(default)]
    pub leaf_area_density: f64,
    /// Leaf angle distribution's projection function G (0.5 for spherical). Default 0.5.
    #[serde(default = "default_g")]
    pub g_function: f64,
    /// Branches listed explicitly. Default none.
    #[serde(default)]
    pub branches: Vec<Branch>,
    /// Branches generated from the seed in addition to the listed ones (spread up the crown,
    /// golden-angle azimuths, 50-70° from vertical, reaching the envelope). Default 0.
    #[serde(default)]
    pub branch_count: u32,
    /// Radius of generated branches, metres. Default 0.04.
    #[serde(default = "default_branch_radius")]
    pub branch_radius_m: f64,
    /// Material of stem and branches. Default "bark".
    #[serde(default = "bark")]
    pub bark: String,
    /// Material of the leaves. Default "leaf".
    #[serde(default = "leaf")]
    pub leaf: String,
}

/// A stand of trees generated from the scene's seed: positions uniform over the rectangle
/// (at least a crown radius apart is not enforced: crowns may overlap, as in real stands),
/// heights uniform in `height_range_m`, crowns and leaves in proportion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Forest {
    /// `[west, south, east, north]` edges, metres.
    pub rectangle_m: [f64; 4],
    /// Trees per hectare.
    pub trees_per_ha: f64,
    /// Tree heights `[lowest, highest]`, metres.
    pub height_range_m: [f64; 2],
    /// Crown radius as a fraction of the tree's height. Default 0.25.
    #[serde(default = "default_crown_radius_fraction")]
    pub crown_radius_fraction: f64,
    /// Crown base as a fraction of the tree's height. Default 0.4.
    #[serde(default = "default_crown_base_fraction")]
    pub crown_base_fraction: f64,
    /// Crown shape. Default ellipsoid.
    #[serde(default = "default_shape")]
    pub shape: CrownShape,
    /// Leaf area density, m²/m³ (0: leaf-off). Default 0.8.
    #[serde(default = "default_forest_lad")]
    pub leaf_area_density: f64,
    /// Branches per tree. Default 0.
    #[serde(default)]
    pub branch_count: u32,
}

impl Forest {
    /// The trees of this stand (deterministic for `seed` and the stand's index `index`).
    pub fn trees(&self, seed: u64, index: usize) -> Vec<Tree> {
        let r = self.rectangle_m;
        let area_ha = (r[2] - r[0]) * (r[3] - r[1]) / 10_000.0;
        let n = (area_ha * self.trees_per_ha).round().max(0.0) as usize;
        let mut state = seed ^ 0xF0_4E57u64.wrapping_mul(index as u64 + 1);
        let mut next = || {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let x = r[0] + next() * (r[2] - r[0]);
                let y = r[1] + next() * (r[3] - r[1]);
                let [lo, hi] = self.height_range_m;
                let h = lo + next() * (hi - lo);
                Tree {
                    position_m: [x, y],
                    height_m: h,
                    stem_radius_m: 0.012 * h,
                    crown: Crown {
                        shape: self.shape,
                        base_m: self.crown_base_fraction * h,
                        radius_m: self.crown_radius_fraction * h,
                    },
                    leaf_area_density: self.leaf_area_density,
                    g_function: default_g(),
                    branches: Vec::new(),
                    branch_count: self.branch_count,
                    branch_radius_m: default_branch_radius(),
                    bark: bark(),
                    leaf: leaf(),
                }
            })
            .collect()
    }
}

/// A grass patch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Grass {
    /// `[west, south, east, north]` edges, metres.
    pub rectangle_m: [f64; 4],
    /// Height of the grass above the terrain, metres.
    pub height_m: f64,
    /// Leaf area density, m²/m³ (leaf area index = density × height).
    pub leaf_area_density: f64,
    /// G function. Default 0.5.
    #[serde(default = "default_g")]
    pub g_function: f64,
    /// Material. Default "grass".
    #[serde(default = "grass")]
    pub material: String,
}

/// A box standing on the terrain (its base at the terrain's height at its centre).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxObject {
    /// `[west, south, east, north]` edges, metres.
    pub rectangle_m: [f64; 4],
    /// Height above its base, metres.
    pub height_m: f64,
    /// Material. Default "roof".
    #[serde(default = "roof")]
    pub material: String,
}

/// Direction of a gable roof's ridge.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Ridge {
    /// The ridge runs east-west (the roof planes face north and south).
    EastWest,
    /// The ridge runs north-south.
    NorthSouth,
}

/// A gable-roofed building standing on the terrain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Roof {
    /// `[west, south, east, north]` edges, metres.
    pub rectangle_m: [f64; 4],
    /// Eave height above the base, metres.
    pub eave_height_m: f64,
    /// Ridge height above the base, metres.
    pub ridge_height_m: f64,
    /// Ridge direction. Default east-west.
    #[serde(default = "default_ridge")]
    pub ridge: Ridge,
    /// Material of the roof planes. Default "roof".
    #[serde(default = "roof")]
    pub material: String,
    /// Material of the walls. Default "wall".
    #[serde(default = "wall")]
    pub wall: String,
}

/// One flight line, flown at constant height and speed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Line {
    /// Start, metres east and north.
    pub start_m: [f64; 2],
    /// End, metres east and north.
    pub end_m: [f64; 2],
}

/// The scan pattern.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "pattern", rename_all = "snake_case", deny_unknown_fields)]
pub enum ScanPattern {
    /// One fixed beam direction: `zenith_deg` from nadir towards `azimuth_deg` (clockwise from
    /// the aircraft's heading). The seed's experiments.
    Fixed {
        /// Off-nadir angle, degrees. Default 0.
        #[serde(default)]
        zenith_deg: f64,
        /// Direction of the tilt, degrees clockwise from the heading. Default 0.
        #[serde(default)]
        azimuth_deg: f64,
    },
    /// An oscillating mirror: the cross-track angle sweeps −half..+half and back, a zig-zag on
    /// the ground (Optech ALTM). `rate_hz` full periods (two scan lines) per second.
    Oscillating {
        /// Largest cross-track angle, degrees.
        half_angle_deg: f64,
        /// Mirror periods per second.
        rate_hz: f64,
    },
    /// A rotating polygon: the angle sweeps −half..+half, then jumps back (parallel lines,
    /// RIEGL). `rate_hz` scan lines per second.
    Polygon {
        /// Largest cross-track angle, degrees.
        half_angle_deg: f64,
        /// Scan lines per second.
        rate_hz: f64,
    },
    /// A Palmer scanner: the beam turns on a cone of `half_angle_deg` around nadir, an
    /// elliptical pattern on the ground. `rate_hz` turns per second.
    Palmer {
        /// Cone half-angle, degrees.
        half_angle_deg: f64,
        /// Turns per second.
        rate_hz: f64,
    },
}

impl Default for ScanPattern {
    fn default() -> Self {
        ScanPattern::Fixed {
            zenith_deg: 0.0,
            azimuth_deg: 0.0,
        }
    }
}

/// The seed's plot sampling: a regular grid of beams on the ground (the DIRSIG set-up), flown
/// along the rows so that each pulse's beam, at the fixed zenith and azimuth of the scan,
/// reaches its grid cell. Replaces `lines`; the speed is what the grid and the pulse rate make.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlotGrid {
    /// Centre of the grid, metres east and north. Default [0, 0].
    #[serde(default)]
    pub centre_m: [f64; 2],
    /// Beams across track (per row).
    pub columns: u32,
    /// Rows along track.
    pub rows: u32,
    /// Spacing of beams on the ground, metres.
    pub spacing_m: f64,
}

/// The flight plan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Flight {
    /// Flying height above the scene origin, metres. Default 1000.
    #[serde(default = "default_altitude")]
    pub altitude_m: f64,
    /// Ground speed, metres per second. Default 60.
    #[serde(default = "default_speed")]
    pub speed_mps: f64,
    /// Pulse repetition rate, hertz. Default: the sensor's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pulse_rate_hz: Option<f64>,
    /// Lines, flown in order (a line's pulses start `turn_s` after the previous line's end).
    #[serde(default)]
    pub lines: Vec<Line>,
    /// Time between lines, seconds (no pulses; navigation continues). Default 20.
    #[serde(default = "default_turn")]
    pub turn_s: f64,
    /// The seed's grid of beams instead of lines.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid: Option<PlotGrid>,
    /// Scan pattern. Default fixed at nadir.
    #[serde(default)]
    pub scan: ScanPattern,
    /// Stop after this many pulses (all when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_pulses: Option<u64>,
}

/// The sensor as the scene uses it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSensor {
    /// Sensor profile file (relative to the scene file's folder), or the inline `[sensor.inline]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<PathBuf>,
    /// An inline profile.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inline: Option<SensorProfile>,
    /// Outgoing pulse FWHM, ns. Default: the profile's `pulse_fwhm_ns`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outgoing_fwhm_ns: Option<f64>,
    /// Shape of the outgoing pulse. Default a Gaussian of `outgoing_fwhm_ns`.
    #[serde(default)]
    pub pulse_shape: PulseShape,
    /// Receiver impulse response, a Gaussian of this FWHM, ns (0: ideal). Default 0.
    #[serde(default)]
    pub receiver_fwhm_ns: f64,
    /// Peak counts above the baseline of the echo of a white (ρ = 1) Lambertian plane filling
    /// the footprint at nadir at `reference_range_m`, with an ideal receiver. Default 200.
    #[serde(default = "default_peak")]
    pub peak_dn: f64,
    /// Range of `peak_dn`, metres. Default 1000.
    #[serde(default = "default_altitude")]
    pub reference_range_m: f64,
    /// Peak of the recorded outgoing pulse above the baseline, counts. Default 200.
    #[serde(default = "default_peak")]
    pub outgoing_peak_dn: f64,
    /// Digitizer baseline, counts. Default 12.
    #[serde(default = "default_baseline")]
    pub baseline_dn: f64,
    /// Height above the terrain (along the beam's vertical) of the first return sample,
    /// metres. Default 25 (the seed's 24.995 m).
    #[serde(default = "default_window_top")]
    pub window_top_m: f64,
    /// Return samples recorded. Default 225.
    #[serde(default = "default_samples")]
    pub return_samples: u32,
    /// Group refractive index of the air (as `[georeference] refractive_index`). Default
    /// 1.00027.
    #[serde(default = "default_n")]
    pub refractive_index: f64,
}

/// Shape of the outgoing laser pulse (its peak is the pulse's reference time t0).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum PulseShape {
    /// A Gaussian of the sensor's (or `outgoing_fwhm_ns`) full width at half maximum.
    #[default]
    Gaussian,
    /// Two half-Gaussians joined at the peak: a fast rise and a slower fall, as Q-switched
    /// lasers emit. Half widths at half maximum, ns (FWHM = rise + fall).
    Bigaussian {
        /// Rise, peak to half maximum before it, ns.
        rise_ns: f64,
        /// Fall, peak to half maximum after it, ns.
        fall_ns: f64,
    },
    /// A measured pulse: samples every `sample_ns` (any scale; normalised to peak 1 at the
    /// largest sample, which becomes t0), linearly interpolated.
    Measured {
        /// The samples.
        samples: Vec<f64>,
        /// Their spacing, ns.
        sample_ns: f64,
    },
}

/// Digitizer noise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Noise {
    /// Uniform in ±`amplitude_dn` (the seed's model).
    Uniform {
        /// Half-width, counts.
        amplitude_dn: f64,
    },
    /// Gaussian with `sigma_dn`.
    Gaussian {
        /// Standard deviation, counts.
        sigma_dn: f64,
    },
    /// Poisson shot noise: the signal above the baseline is `photons_per_dn` photo-electrons
    /// per count, drawn from a Poisson law, plus Gaussian `dark_sigma_dn`.
    Poisson {
        /// Photo-electrons per count.
        photons_per_dn: f64,
        /// Standard deviation of the dark/thermal noise, counts. Default 0.
        #[serde(default)]
        dark_sigma_dn: f64,
    },
}

/// Receiver ringing after an echo: `amplitude × echo × exp(−t/decay) × sin(2π t/period)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ringing {
    /// Relative amplitude. Default 0.15.
    #[serde(default = "default_ring_amp")]
    pub amplitude: f64,
    /// Period, ns. Default 12.
    #[serde(default = "default_ring_period")]
    pub period_ns: f64,
    /// Decay time, ns. Default 20.
    #[serde(default = "default_ring_decay")]
    pub decay_ns: f64,
}

impl Default for Ringing {
    fn default() -> Self {
        Ringing {
            amplitude: default_ring_amp(),
            period_ns: default_ring_period(),
            decay_ns: default_ring_decay(),
        }
    }
}

fn default_gps_start() -> f64 {
    345_600.0
}
fn default_lat() -> f64 {
    -24.99
}
fn default_lon() -> f64 {
    31.59
}
fn default_origin_height() -> f64 {
    0.0
}
fn ground() -> String {
    "ground".into()
}
fn bark() -> String {
    "bark".into()
}
fn leaf() -> String {
    "leaf".into()
}
fn grass() -> String {
    "grass".into()
}
fn roof() -> String {
    "roof".into()
}
fn wall() -> String {
    "wall".into()
}
fn default_shape() -> CrownShape {
    CrownShape::Ellipsoid
}
fn default_ridge() -> Ridge {
    Ridge::EastWest
}
fn default_crown_radius_fraction() -> f64 {
    0.25
}
fn default_crown_base_fraction() -> f64 {
    0.4
}
fn default_forest_lad() -> f64 {
    0.8
}
fn default_stem_radius() -> f64 {
    0.15
}
fn default_branch_radius() -> f64 {
    0.04
}
fn default_g() -> f64 {
    0.5
}
fn default_altitude() -> f64 {
    1000.0
}
fn default_speed() -> f64 {
    60.0
}
fn default_turn() -> f64 {
    20.0
}
fn default_peak() -> f64 {
    200.0
}
fn default_baseline() -> f64 {
    12.0
}
fn default_window_top() -> f64 {
    25.0
}
fn default_samples() -> u32 {
    225
}
fn default_n() -> f64 {
    1.00027
}
fn default_jitter() -> f64 {
    0.2
}
fn default_loss() -> f64 {
    0.001
}
fn default_rings() -> u32 {
    3
}
fn default_ring_amp() -> f64 {
    0.15
}
fn default_ring_period() -> f64 {
    12.0
}
fn default_ring_decay() -> f64 {
    20.0
}

/// The default reflectances by material name.
pub const DEFAULT_MATERIALS: [(&str, f64); 6] = [
    ("ground", 0.3),
    ("bark", 0.35),
    ("leaf", 0.45),
    ("grass", 0.4),
    ("roof", 0.2),
    ("wall", 0.25),
];

fn invalid(field: &'static str, reason: String) -> SceneError {
    SceneError::Invalid { field, reason }
}

fn need(ok: bool, field: &'static str, reason: impl FnOnce() -> String) -> Result<(), SceneError> {
    if ok {
        Ok(())
    } else {
        Err(invalid(field, reason()))
    }
}

impl WorldScene {
    /// Whether the scene asks for `effect`.
    pub fn has(&self, effect: Effect) -> bool {
        self.effects.contains(&effect)
    }

    /// Reflectance of material `name` (scene's table, else the defaults).
    pub fn reflectance(&self, name: &str) -> Option<f64> {
        self.materials.get(name).copied().or_else(|| {
            DEFAULT_MATERIALS
                .iter()
                .find(|(n, _)| *n == name)
                .map(|(_, r)| *r)
        })
    }

    /// Reads a described scene file and resolves its sensor profile.
    pub fn load(path: &Path) -> Result<(WorldScene, SensorProfile), SceneError> {
        Self::load_with(path, &[])
    }

    /// As [`WorldScene::load`], with `KEY=VALUE` overrides applied to the file's TOML first
    /// (`KEY` a dotted path such as `flight.scan.zenith_deg`, with list indices such as
    /// `tree[0].height_m`; `VALUE` a TOML value, anything else taken as a string):
    /// [`crate::core::overrides`].
    pub fn load_with(
        path: &Path,
        sets: &[String],
    ) -> Result<(WorldScene, SensorProfile), SceneError> {
        let mut text = crate::sim::analytic_scene::read(path)?;
        if !sets.is_empty() {
            let what = path.display().to_string();
            let mut table: toml::Table = crate::sim::analytic_scene::parse_toml(&text, &what)?;
            crate::core::overrides::apply_all(&mut table, sets).map_err(|e| {
                SceneError::Invalid {
                    field: "--set",
                    reason: e.to_string(),
                }
            })?;
            text = toml::to_string(&table).map_err(|e| SceneError::Parse {
                what,
                field: String::new(),
                message: e.to_string(),
            })?;
        }
        let scene: WorldScene =
            crate::sim::analytic_scene::parse_toml(&text, &path.display().to_string())?;
        let base = path.parent().unwrap_or(Path::new("."));
        let sensor = scene.resolve_sensor(base)?;
        scene.validate(&sensor)?;
        Ok((scene, sensor))
    }

    /// The sensor profile, from the file or inline.
    pub fn resolve_sensor(&self, base_dir: &Path) -> Result<SensorProfile, SceneError> {
        let analytic = crate::sim::analytic_scene::Scene {
            sensor: self.sensor.inline.clone(),
            sensor_profile: self.sensor.profile.clone(),
            ..Default::default()
        };
        analytic.resolve_sensor(base_dir).map_err(|e| match e {
            SceneError::Invalid {
                field: "scene.sensor",
                ..
            } => invalid(
                "sensor",
                "give exactly one of `profile` and `[sensor.inline]`".into(),
            ),
            e => e,
        })
    }

    /// The pulse rate in force, hertz.
    pub fn pulse_rate_hz(&self, sensor: &SensorProfile) -> f64 {
        self.flight.pulse_rate_hz.unwrap_or(sensor.pulse_rate_hz)
    }

    /// Checks every value (sensor-dependent ones against `sensor`).
    pub fn validate(&self, sensor: &SensorProfile) -> Result<(), SceneError> {
        self.validate_general()?;
        self.validate_terrain()?;
        for t in &self.tree {
            self.validate_tree(t)?;
        }
        for f in &self.forest {
            validate_forest(f)?;
        }
        for g in &self.grass {
            self.validate_grass(g)?;
        }
        self.validate_buildings()?;
        self.validate_flight(sensor)?;
        self.validate_scan()?;
        self.validate_sensor()?;
        self.validate_effects()?;
        self.validate_navigation()
    }

    /// The scene's top-level values: no `multiple_scattering` effect, the GPS start time
    /// (s, >= 0) and the origin's latitude (degrees, within ±89°).
    fn validate_general(&self) -> Result<(), SceneError> {
        need(!self.has(Effect::MultipleScattering), "effects", || {
            "`multiple_scattering` is not simulated: the simulator traces single-bounce returns \
             only (leave it out)"
                .into()
        })?;
        need(
            self.gps_time_start_s.is_finite() && self.gps_time_start_s >= 0.0,
            "gps_time_start_s",
            || format!("must be >= 0, got {}", self.gps_time_start_s),
        )?;
        need(self.origin.lat_deg.abs() < 89.0, "origin.lat_deg", || {
            format!("must be within ±89°, got {}", self.origin.lat_deg)
        })
    }

    /// Material `name` (reported as `field`) is in `[materials]` or a default, with a
    /// reflectance in 0..1.
    fn validate_material(&self, name: &str, field: &'static str) -> Result<(), SceneError> {
        match self.reflectance(name) {
            Some(r) if (0.0..=1.0).contains(&r) => Ok(()),
            Some(r) => Err(invalid(
                field,
                format!("material `{name}` reflectance {r} is not in 0..1"),
            )),
            None => Err(invalid(
                field,
                format!(
                    "material `{name}` is not in [materials] nor a default ({})",
                    DEFAULT_MATERIALS.map(|m| m.0).join(", ")
                ),
            )),
        }
    }

    /// `[terrain]`: its material, and a plane's slope (degrees, 0..80).
    fn validate_terrain(&self) -> Result<(), SceneError> {
        match &self.terrain {
            Terrain::Flat { material: m, .. } => self.validate_material(m, "terrain.material"),
            Terrain::Plane {
                slope_deg,
                material: m,
                ..
            } => {
                need((0.0..80.0).contains(slope_deg), "terrain.slope_deg", || {
                    format!("must be in 0..80, got {slope_deg}")
                })?;
                self.validate_material(m, "terrain.material")
            }
            Terrain::Geotiff { material: m, .. } => self.validate_material(m, "terrain.material"),
        }
    }

    /// One `[[tree]]`: heights and radii (m), leaf area density (m²/m³), G function, listed
    /// branches, bark and leaf materials.
    fn validate_tree(&self, t: &Tree) -> Result<(), SceneError> {
        need(pos(t.height_m), "tree.height_m", || {
            format!("must be > 0, got {}", t.height_m)
        })?;
        need(
            nonneg(t.crown.base_m) && t.crown.base_m < t.height_m,
            "tree.crown.base_m",
            || {
                format!(
                    "must be in 0..height_m ({}), got {}",
                    t.height_m, t.crown.base_m
                )
            },
        )?;
        need(pos(t.crown.radius_m), "tree.crown.radius_m", || {
            format!("must be > 0, got {}", t.crown.radius_m)
        })?;
        need(
            nonneg(t.leaf_area_density),
            "tree.leaf_area_density",
            || format!("must be >= 0 m²/m³, got {}", t.leaf_area_density),
        )?;
        need(
            pos(t.g_function) && t.g_function <= 1.0,
            "tree.g_function",
            || format!("must be in (0, 1], got {}", t.g_function),
        )?;
        need(nonneg(t.stem_radius_m), "tree.stem_radius_m", || {
            format!("must be >= 0, got {}", t.stem_radius_m)
        })?;
        for b in &t.branches {
            need(
                pos(b.length_m) && pos(b.radius_m) && nonneg(b.height_m),
                "tree.branches",
                || format!("length, radius must be > 0 and height >= 0: {b:?}"),
            )?;
        }
        self.validate_material(&t.bark, "tree.bark")?;
        self.validate_material(&t.leaf, "tree.leaf")
    }

    /// One `[[grass]]`: rectangle (m), height (m), leaf area density (m²/m³), G function and
    /// material.
    fn validate_grass(&self, g: &Grass) -> Result<(), SceneError> {
        rect(&g.rectangle_m, "grass.rectangle_m")?;
        need(pos(g.height_m), "grass.height_m", || {
            format!("must be > 0, got {}", g.height_m)
        })?;
        need(
            nonneg(g.leaf_area_density),
            "grass.leaf_area_density",
            || format!("must be >= 0, got {}", g.leaf_area_density),
        )?;
        need(
            pos(g.g_function) && g.g_function <= 1.0,
            "grass.g_function",
            || format!("must be in (0, 1], got {}", g.g_function),
        )?;
        self.validate_material(&g.material, "grass.material")
    }

    /// Every `[[boxes]]` then every `[[roof]]`: rectangles (m), heights (m) and materials.
    fn validate_buildings(&self) -> Result<(), SceneError> {
        for b in &self.boxes {
            rect(&b.rectangle_m, "box.rectangle_m")?;
            need(pos(b.height_m), "box.height_m", || {
                format!("must be > 0, got {}", b.height_m)
            })?;
            self.validate_material(&b.material, "box.material")?;
        }
        for r in &self.roof {
            rect(&r.rectangle_m, "roof.rectangle_m")?;
            need(
                pos(r.eave_height_m) && r.ridge_height_m >= r.eave_height_m,
                "roof.ridge_height_m",
                || {
                    format!(
                        "need 0 < eave_height_m ({}) <= ridge_height_m ({})",
                        r.eave_height_m, r.ridge_height_m
                    )
                },
            )?;
            self.validate_material(&r.material, "roof.material")?;
            self.validate_material(&r.wall, "roof.wall")?;
        }
        Ok(())
    }

    /// `[flight]`: altitude (m), speed (m/s), turn time (s), the pulse rate in force (Hz, at
    /// most 10 MHz; the sensor's unless the flight gives one), and `lines` or a `grid`.
    fn validate_flight(&self, sensor: &SensorProfile) -> Result<(), SceneError> {
        let f = &self.flight;
        need(pos(f.altitude_m), "flight.altitude_m", || {
            format!("must be > 0, got {}", f.altitude_m)
        })?;
        need(pos(f.speed_mps), "flight.speed_mps", || {
            format!("must be > 0, got {}", f.speed_mps)
        })?;
        need(nonneg(f.turn_s), "flight.turn_s", || {
            format!("must be >= 0, got {}", f.turn_s)
        })?;
        let prf = self.pulse_rate_hz(sensor);
        need(pos(prf) && prf <= 10e6, "flight.pulse_rate_hz", || {
            format!("must be in (0, 10 MHz], got {prf}")
        })?;
        match (&f.grid, f.lines.is_empty()) {
            (Some(g), true) => {
                need(
                    g.columns > 0 && g.rows > 0 && pos(g.spacing_m),
                    "flight.grid",
                    || "columns, rows and spacing_m must be > 0".into(),
                )?;
                need(
                    matches!(f.scan, ScanPattern::Fixed { .. }),
                    "flight.scan",
                    || "a plot grid takes a `fixed` scan (its zenith and azimuth)".into(),
                )
            }
            (None, false) => {
                for l in &f.lines {
                    need(l.start_m != l.end_m, "flight.lines", || {
                        format!("a line needs two different ends: {l:?}")
                    })?;
                }
                Ok(())
            }
            (Some(_), false) => Err(invalid("flight", "give `lines` or `grid`, not both".into())),
            (None, true) => Err(invalid(
                "flight.lines",
                "a flight needs at least one line (or a `grid`)".into(),
            )),
        }
    }

    /// `[flight.scan]`: a fixed zenith (degrees, 0..60), or a scanning half angle (degrees,
    /// 0..60 exclusive) and rate (Hz, > 0).
    fn validate_scan(&self) -> Result<(), SceneError> {
        match &self.flight.scan {
            ScanPattern::Fixed { zenith_deg, .. } => need(
                (0.0..60.0).contains(zenith_deg),
                "flight.scan.zenith_deg",
                || format!("must be in 0..60, got {zenith_deg}"),
            ),
            ScanPattern::Oscillating {
                half_angle_deg,
                rate_hz,
            }
            | ScanPattern::Polygon {
                half_angle_deg,
                rate_hz,
            }
            | ScanPattern::Palmer {
                half_angle_deg,
                rate_hz,
            } => {
                need(
                    *half_angle_deg > 0.0 && *half_angle_deg < 60.0,
                    "flight.scan.half_angle_deg",
                    || format!("must be in (0, 60), got {half_angle_deg}"),
                )?;
                need(pos(*rate_hz), "flight.scan.rate_hz", || {
                    format!("must be > 0, got {rate_hz}")
                })
            }
        }
    }

    /// `[sensor]`: levels (counts), reference range (m), pulse shape, receiver and outgoing
    /// widths (ns), return samples, window top (m, below the flight altitude) and refractive
    /// index.
    fn validate_sensor(&self) -> Result<(), SceneError> {
        let s = &self.sensor;
        for (v, field) in [
            (s.peak_dn, "sensor.peak_dn"),
            (s.reference_range_m, "sensor.reference_range_m"),
            (s.outgoing_peak_dn, "sensor.outgoing_peak_dn"),
        ] {
            need(pos(v), field, || format!("must be > 0, got {v}"))?;
        }
        need(nonneg(s.baseline_dn), "sensor.baseline_dn", || {
            format!("must be >= 0, got {}", s.baseline_dn)
        })?;
        validate_pulse_shape(&s.pulse_shape)?;
        need(
            nonneg(s.receiver_fwhm_ns),
            "sensor.receiver_fwhm_ns",
            || format!("must be >= 0, got {}", s.receiver_fwhm_ns),
        )?;
        if let Some(w) = s.outgoing_fwhm_ns {
            need(pos(w), "sensor.outgoing_fwhm_ns", || {
                format!("must be > 0, got {w}")
            })?;
        }
        need(
            s.return_samples > 0 && s.return_samples <= 65_535,
            "sensor.return_samples",
            || format!("must be in 1..=65535, got {}", s.return_samples),
        )?;
        need(
            pos(s.window_top_m) && s.window_top_m < self.flight.altitude_m,
            "sensor.window_top_m",
            || format!("must be in (0, altitude), got {}", s.window_top_m),
        )?;
        need(
            (1.0..=1.001).contains(&s.refractive_index),
            "sensor.refractive_index",
            || format!("must be in 1..=1.001, got {}", s.refractive_index),
        )
    }

    /// The effects' settings: `[noise]` (counts) when the `noise` effect is named, packet
    /// loss (fraction, 0..1), timing jitter (ns), footprint rings (1..=8) and `[ringing]`.
    fn validate_effects(&self) -> Result<(), SceneError> {
        if self.has(Effect::Noise) {
            validate_noise(self.noise.as_ref())?;
        }
        need(
            (0.0..1.0).contains(&self.packet_loss),
            "packet_loss",
            || format!("must be in 0..1, got {}", self.packet_loss),
        )?;
        need(nonneg(self.timing_jitter_ns), "timing_jitter_ns", || {
            format!("must be >= 0, got {}", self.timing_jitter_ns)
        })?;
        need(
            (1..=8).contains(&self.footprint_rings),
            "footprint_rings",
            || format!("must be in 1..=8, got {}", self.footprint_rings),
        )?;
        let r = &self.ringing;
        need(
            nonneg(r.amplitude) && pos(r.period_ns) && pos(r.decay_ns),
            "ringing",
            || "amplitude >= 0, period_ns and decay_ns > 0".into(),
        )
    }

    /// `[navigation]`: its own checks, and the tables the navigation effects named need.
    fn validate_navigation(&self) -> Result<(), SceneError> {
        let n = &self.navigation;
        n.validate()
            .map_err(|e| invalid("navigation", e.to_string()))?;
        need(
            !self.has(Effect::NavigationNoise) || n.noise.is_some(),
            "navigation.noise",
            || {
                "the `navigation_noise` effect needs [navigation.noise] (position_m, attitude_deg, heading_deg)".into()
            },
        )?;
        need(
            !self.has(Effect::NavigationDropouts)
                || !n.dropouts.is_empty()
                || n.random_dropout_probability > 0.0,
            "navigation.dropouts",
            || {
                "the `navigation_dropouts` effect needs `dropouts` or `random_dropout_probability`"
                    .into()
            },
        )
    }
}

/// `v` is finite and > 0.
fn pos(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

/// `v` is finite and >= 0.
fn nonneg(v: f64) -> bool {
    v.is_finite() && v >= 0.0
}

/// One `[[forest]]`: rectangle (m), height range (m), density (trees per hectare, at most
/// 20 000 and a million trees in all), crown fractions and leaf area density (m²/m³).
fn validate_forest(f: &Forest) -> Result<(), SceneError> {
    rect(&f.rectangle_m, "forest.rectangle_m")?;
    let [lo, hi] = f.height_range_m;
    need(
        pos(lo) && hi >= lo && hi.is_finite(),
        "forest.height_range_m",
        || {
            format!(
                "must be [lowest > 0, highest >= lowest], got {:?}",
                f.height_range_m
            )
        },
    )?;
    need(
        nonneg(f.trees_per_ha) && f.trees_per_ha <= 20_000.0,
        "forest.trees_per_ha",
        || format!("must be in 0..=20000, got {}", f.trees_per_ha),
    )?;
    let area = (f.rectangle_m[2] - f.rectangle_m[0]) * (f.rectangle_m[3] - f.rectangle_m[1]);
    need(
        area / 10_000.0 * f.trees_per_ha <= 1e6,
        "forest.trees_per_ha",
        || "more than a million trees: use a smaller rectangle".into(),
    )?;
    need(
        pos(f.crown_radius_fraction) && (0.0..1.0).contains(&f.crown_base_fraction),
        "forest.crown_radius_fraction",
        || "crown_radius_fraction must be > 0 and crown_base_fraction in 0..1".into(),
    )?;
    need(
        nonneg(f.leaf_area_density),
        "forest.leaf_area_density",
        || format!("must be >= 0, got {}", f.leaf_area_density),
    )
}

/// `[sensor.pulse_shape]`: a bigaussian's rise and fall (ns, > 0, together at most 1000 ns),
/// or a measured pulse's sample interval (ns, > 0) and 3 to 100 000 finite, non-negative
/// samples, not all zero.
fn validate_pulse_shape(shape: &PulseShape) -> Result<(), SceneError> {
    match shape {
        PulseShape::Gaussian => Ok(()),
        PulseShape::Bigaussian { rise_ns, fall_ns } => need(
            pos(*rise_ns) && pos(*fall_ns) && rise_ns + fall_ns <= 1000.0,
            "sensor.pulse_shape",
            || format!("rise_ns and fall_ns must be > 0, got {rise_ns} and {fall_ns}"),
        ),
        PulseShape::Measured { samples, sample_ns } => need(
            pos(*sample_ns)
                && samples.len() >= 3
                && samples.len() <= 100_000
                && samples.iter().all(|v| v.is_finite() && *v >= 0.0)
                && samples.iter().any(|v| *v > 0.0),
            "sensor.pulse_shape",
            || {
                "a measured pulse needs sample_ns > 0 and 3 to 100000 finite, non-negative \
                 samples, not all zero"
                    .into()
            },
        ),
    }
}

/// `[noise]` of a scene naming the `noise` effect: present, with amplitudes (counts) >= 0 or a
/// Poisson model's photons per count > 0 and dark noise (counts) >= 0.
fn validate_noise(noise: Option<&Noise>) -> Result<(), SceneError> {
    match noise {
        None => Err(invalid(
            "noise",
            "the `noise` effect needs a [noise] table (kind = uniform | gaussian | \
             poisson)"
                .into(),
        )),
        Some(Noise::Uniform { amplitude_dn: v }) | Some(Noise::Gaussian { sigma_dn: v }) => {
            need(nonneg(*v), "noise", || format!("must be >= 0, got {v}"))
        }
        Some(Noise::Poisson {
            photons_per_dn,
            dark_sigma_dn,
        }) => need(
            pos(*photons_per_dn) && nonneg(*dark_sigma_dn),
            "noise",
            || "photons_per_dn must be > 0 and dark_sigma_dn >= 0".into(),
        ),
    }
}

fn rect(r: &[f64; 4], field: &'static str) -> Result<(), SceneError> {
    need(
        r.iter().all(|v| v.is_finite()) && r[0] < r[2] && r[1] < r[3],
        field,
        || {
            format!(
                "must be [west, south, east, north] with west < east and south < north, got {r:?}"
            )
        },
    )
}

impl crate::core::validate::Validate for WorldScene {
    fn validate(&self, _path: &str, v: &mut crate::core::validate::Validator) {
        let base = v.base_dir().map(Path::to_path_buf).unwrap_or_default();
        let issue = |e: SceneError| match e {
            SceneError::Invalid { field, reason } => (field.to_string(), reason),
            SceneError::Parse {
                field,
                message,
                what,
            } => (
                "sensor.profile".to_string(),
                format!("{what}: {field}: {message}"),
            ),
            SceneError::Io { path, source } => (
                "sensor.profile".to_string(),
                format!("cannot read {}: {source}", path.display()),
            ),
        };
        match self.resolve_sensor(&base) {
            Ok(sensor) => {
                if let Err(e) = WorldScene::validate(self, &sensor) {
                    let (p, r) = issue(e);
                    v.report(p, r);
                }
            }
            Err(e) => {
                let (p, r) = issue(e);
                v.report(p, r);
            }
        }
    }
}
