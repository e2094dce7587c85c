//! The simulator's scene configuration: a TOML document with one `[scene]` table
//! (`deny_unknown_fields`, every field documented with its default), checked by
//! [`Scene::validate`] and resolved against a sensor profile by [`Scene::resolve_sensor`].
//!
//! ```toml
//! [scene]
//! seed = 42
//! pulses = 2000
//! altitude_m = 1000.0
//! plane_height_m = 15.0
//! plane_cover = 0.4
//! noise = { kind = "uniform", amplitude_dn = 3.0 }
//! sensor_profile = "../sensors/optech_altm3100ea_cao.toml"
//!
//! [scene.flight]
//! start_lat_deg = -24.99
//! start_lon_deg = 31.59
//! speed_mps = 60.0
//! heading_deg = 90.0
//! ```
//!
//! Units: metres, seconds, hertz, degrees and digitizer counts (DN) as the field names say.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::core::sensor::{SensorFile, SensorProfile};

/// Errors of loading, validating or resolving a scene.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// A file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The TOML did not parse into a scene (or a sensor profile).
    #[error("{what}: at `{field}`: {message}")]
    Parse {
        /// What was being parsed (a file path or "scene").
        what: String,
        /// Path of the offending field, e.g. `scene.noise.kind`.
        field: String,
        /// What went wrong.
        message: String,
    },
    /// A field has a value the simulator cannot use.
    #[error("invalid scene: `{field}`: {reason}")]
    Invalid {
        /// Path of the field, e.g. `scene.plane_cover`.
        field: &'static str,
        /// Why.
        reason: String,
    },
}

/// The top level of a scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// The scene.
    pub scene: Scene,
}

/// Noise added to every digitized sample.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum NoiseConfig {
    /// Uniform white noise in `[-amplitude_dn, +amplitude_dn]`, independent per sample (the
    /// seed's simulation noise model).
    Uniform {
        /// Half-width of the uniform distribution, counts.
        amplitude_dn: f64,
    },
}

/// The straight flight line the navigation messages describe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlightConfig {
    /// Latitude of the aircraft at the first pulse, degrees (WGS84, north positive).
    /// Default -24.99 (Kruger National Park, where the seed's CAO data were flown).
    #[serde(default = "default_lat")]
    pub start_lat_deg: f64,
    /// Longitude at the first pulse, degrees (east positive). Default 31.59.
    #[serde(default = "default_lon")]
    pub start_lon_deg: f64,
    /// Ground speed, metres per second. Default 60.
    #[serde(default = "default_speed")]
    pub speed_mps: f64,
    /// True heading (course over ground), degrees clockwise from north. Default 0.
    #[serde(default)]
    pub heading_deg: f64,
    /// Rate of navigation messages (one GGA and one PASHR per epoch, a ZDA on whole UTC seconds), hertz. Default 10.
    #[serde(default = "default_nav_rate")]
    pub nav_rate_hz: f64,
    /// GPS − UTC offset (leap seconds) used for the UTC time of day in the sentences, seconds.
    /// Default 18.
    #[serde(default = "default_leap")]
    pub gps_utc_offset_s: f64,
    /// GPS week of the flight; with the scene's `gps_time_start_s` as seconds of that week it
    /// dates the navigation stream (a `$GPZDA` once per second, as receivers send it).
    /// Default 1690 (the week of 31 May 2012).
    #[serde(default = "default_gps_week")]
    pub gps_week: u32,
}

impl Default for FlightConfig {
    fn default() -> Self {
        FlightConfig {
            start_lat_deg: default_lat(),
            start_lon_deg: default_lon(),
            speed_mps: default_speed(),
            heading_deg: 0.0,
            nav_rate_hz: default_nav_rate(),
            gps_utc_offset_s: default_leap(),
            gps_week: default_gps_week(),
        }
    }
}

/// An analytic two-layer scene: flat ground and one partially covering plane above it (a
/// canopy-like layer that lets the rest of the footprint through), seen at nadir.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Seed of the noise generator (ChaCha8; the same seed gives the same samples on every
    /// platform). Default 0.
    #[serde(default)]
    pub seed: u64,
    /// Number of pulses to generate. Default 1000.
    #[serde(default = "default_pulses")]
    pub pulses: u64,
    /// Pulse repetition rate, hertz. Default: the sensor's `pulse_rate_hz`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pulse_rate_hz: Option<f64>,
    /// GPS time of the first pulse, seconds (of the GPS week); must not be negative.
    /// Default 0.
    #[serde(default)]
    pub gps_time_start_s: f64,
    /// Flying height above the ground, metres. Default 1000 (the seed's).
    #[serde(default = "default_altitude")]
    pub altitude_m: f64,
    /// Reflectance of the ground, 0..1. Default 0.3.
    #[serde(default = "default_ground_reflectance")]
    pub ground_reflectance: f64,
    /// Height of the plane above the ground, metres. Default 15.
    #[serde(default = "default_plane_height")]
    pub plane_height_m: f64,
    /// Fraction of the footprint the plane intercepts, 0..1; the ground receives the rest.
    /// Default 0.4.
    #[serde(default = "default_plane_cover")]
    pub plane_cover: f64,
    /// Reflectance of the plane, 0..1. Default 0.5.
    #[serde(default = "default_plane_reflectance")]
    pub plane_reflectance: f64,
    /// Return amplitude above the baseline of the strongest possible return (reflectance 1
    /// intercepting the whole footprint), counts. Default 200.
    #[serde(default = "default_peak_dn")]
    pub peak_dn: f64,
    /// Peak of the recorded outgoing pulse above the baseline, counts. Default 200.
    #[serde(default = "default_peak_dn")]
    pub outgoing_peak_dn: f64,
    /// Digitizer baseline (noise floor) of every segment, counts. Default 12.
    #[serde(default = "default_baseline_dn")]
    pub baseline_dn: f64,
    /// Height above the ground of the first return sample (top of the recorded window),
    /// metres; must lie below the aircraft. Default 25 (the seed's tree plots started at
    /// 24.995 m).
    #[serde(default = "default_window_top")]
    pub window_top_m: f64,
    /// Number of return samples recorded from the top of the window. Default 225 (the seed's
    /// tree plots: 25 m down to -8.6 m at 0.15 m).
    #[serde(default = "default_return_samples")]
    pub return_samples: u32,
    /// Noise added to every sample; none when absent. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<NoiseConfig>,
    /// Path of a sensor profile file (`[sensor]` table, see `config/sensors/`), relative to the
    /// scene file's folder. Exactly one of `sensor_profile` and `sensor` must be given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor_profile: Option<PathBuf>,
    /// An inline sensor profile (`[scene.sensor]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<SensorProfile>,
    /// The flight line of the navigation messages. Default: [`FlightConfig::default`].
    #[serde(default)]
    pub flight: FlightConfig,
}

fn default_lat() -> f64 {
    -24.99
}
fn default_lon() -> f64 {
    31.59
}
fn default_speed() -> f64 {
    60.0
}
fn default_nav_rate() -> f64 {
    10.0
}
fn default_leap() -> f64 {
    18.0
}
fn default_gps_week() -> u32 {
    1690
}
fn default_pulses() -> u64 {
    1000
}
fn default_altitude() -> f64 {
    1000.0
}
fn default_ground_reflectance() -> f64 {
    0.3
}
fn default_plane_height() -> f64 {
    15.0
}
fn default_plane_cover() -> f64 {
    0.4
}
fn default_plane_reflectance() -> f64 {
    0.5
}
fn default_peak_dn() -> f64 {
    200.0
}
fn default_baseline_dn() -> f64 {
    12.0
}
fn default_window_top() -> f64 {
    25.0
}
fn default_return_samples() -> u32 {
    225
}

impl Default for Scene {
    /// Every documented default, with no sensor (set `sensor` or `sensor_profile`).
    fn default() -> Self {
        Scene {
            seed: 0,
            pulses: default_pulses(),
            pulse_rate_hz: None,
            gps_time_start_s: 0.0,
            altitude_m: default_altitude(),
            ground_reflectance: default_ground_reflectance(),
            plane_height_m: default_plane_height(),
            plane_cover: default_plane_cover(),
            plane_reflectance: default_plane_reflectance(),
            peak_dn: default_peak_dn(),
            outgoing_peak_dn: default_peak_dn(),
            baseline_dn: default_baseline_dn(),
            window_top_m: default_window_top(),
            return_samples: default_return_samples(),
            noise: None,
            sensor_profile: None,
            sensor: None,
            flight: FlightConfig::default(),
        }
    }
}

/// Parses TOML `text` into `T`, reporting the failing field's path.
pub(crate) fn parse_toml<T: serde::de::DeserializeOwned>(
    text: &str,
    what: &str,
) -> Result<T, SceneError> {
    let de = toml::Deserializer::parse(text).map_err(|e| SceneError::Parse {
        what: what.to_string(),
        field: String::new(),
        message: e.to_string(),
    })?;
    serde_path_to_error::deserialize(de).map_err(|e| SceneError::Parse {
        what: what.to_string(),
        field: e.path().to_string(),
        message: e.inner().to_string(),
    })
}

/// Reads a referenced file as UTF-8 text, at most [`crate::core::toml_load::MAX_CONFIG_BYTES`].
pub(crate) fn read(path: &Path) -> Result<String, SceneError> {
    let io = |source| SceneError::Io {
        path: path.to_path_buf(),
        source,
    };
    let bytes = crate::core::toml_load::read_bounded(path).map_err(io)?;
    String::from_utf8(bytes)
        .map_err(|e| io(std::io::Error::new(std::io::ErrorKind::InvalidData, e)))
}

fn check(ok: bool, field: &'static str, reason: impl FnOnce() -> String) -> Result<(), SceneError> {
    if ok {
        Ok(())
    } else {
        Err(SceneError::Invalid {
            field,
            reason: reason(),
        })
    }
}

fn unit_interval(v: f64) -> bool {
    (0.0..=1.0).contains(&v)
}

impl Scene {
    /// Parses a scene document (`[scene]` table) and validates it. The sensor is not resolved.
    pub fn from_toml_str(text: &str) -> Result<Scene, SceneError> {
        let file: SceneFile = parse_toml(text, "scene")?;
        file.scene.validate()?;
        Ok(file.scene)
    }

    /// The scene as a TOML document with a `[scene]` table.
    pub fn to_toml_string(&self) -> Result<String, toml::ser::Error> {
        toml::to_string_pretty(&SceneFile {
            scene: self.clone(),
        })
    }

    /// Reads and validates a scene file and resolves its sensor (a `sensor_profile` path is
    /// taken relative to the scene file's folder).
    pub fn load(path: &Path) -> Result<(Scene, SensorProfile), SceneError> {
        let text = read(path)?;
        let file: SceneFile = parse_toml(&text, &path.display().to_string())?;
        let scene = file.scene;
        scene.validate()?;
        let base = path.parent().unwrap_or(Path::new("."));
        let sensor = scene.resolve_sensor(base)?;
        Ok((scene, sensor))
    }

    /// The sensor profile: the inline `[scene.sensor]`, or the file `sensor_profile` (relative
    /// paths are taken from `base_dir`), checked for what the simulator needs.
    pub fn resolve_sensor(&self, base_dir: &Path) -> Result<SensorProfile, SceneError> {
        let sensor = match (&self.sensor, &self.sensor_profile) {
            (Some(s), None) => s.clone(),
            (None, Some(p)) => {
                let path = base_dir.join(p);
                let text = read(&path)?;
                let file: SensorFile = parse_toml(&text, &path.display().to_string())?;
                file.sensor
            }
            _ => {
                return Err(SceneError::Invalid {
                    field: "scene.sensor",
                    reason: "give exactly one of `sensor_profile` and `[scene.sensor]`".into(),
                });
            }
        };
        check_sensor(&sensor)?;
        Ok(sensor)
    }

    /// The pulse repetition rate in force, hertz: the scene's, else the sensor's.
    pub fn pulse_rate_hz(&self, sensor: &SensorProfile) -> f64 {
        self.pulse_rate_hz.unwrap_or(sensor.pulse_rate_hz)
    }

    /// Checks every field that does not depend on the sensor.
    pub fn validate(&self) -> Result<(), SceneError> {
        let finite_pos = |v: f64| v.is_finite() && v > 0.0;
        let finite_nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if let Some(r) = self.pulse_rate_hz {
            check(finite_pos(r), "scene.pulse_rate_hz", || {
                format!("must be a positive rate in Hz, got {r}")
            })?;
        }
        check(
            finite_nonneg(self.gps_time_start_s),
            "scene.gps_time_start_s",
            || {
                format!(
                    "must be a finite time >= 0 s, got {}",
                    self.gps_time_start_s
                )
            },
        )?;
        check(finite_pos(self.altitude_m), "scene.altitude_m", || {
            format!("must be a positive height in m, got {}", self.altitude_m)
        })?;
        check(
            unit_interval(self.ground_reflectance),
            "scene.ground_reflectance",
            || format!("must lie in 0..1, got {}", self.ground_reflectance),
        )?;
        check(
            self.plane_height_m > 0.0 && self.plane_height_m < self.altitude_m,
            "scene.plane_height_m",
            || {
                format!(
                    "must lie between the ground and the aircraft (0..{} m), got {}",
                    self.altitude_m, self.plane_height_m
                )
            },
        )?;
        check(unit_interval(self.plane_cover), "scene.plane_cover", || {
            format!("must lie in 0..1, got {}", self.plane_cover)
        })?;
        check(
            unit_interval(self.plane_reflectance),
            "scene.plane_reflectance",
            || format!("must lie in 0..1, got {}", self.plane_reflectance),
        )?;
        check(finite_nonneg(self.peak_dn), "scene.peak_dn", || {
            format!("must be >= 0 DN, got {}", self.peak_dn)
        })?;
        check(
            finite_nonneg(self.outgoing_peak_dn),
            "scene.outgoing_peak_dn",
            || format!("must be >= 0 DN, got {}", self.outgoing_peak_dn),
        )?;
        check(finite_nonneg(self.baseline_dn), "scene.baseline_dn", || {
            format!("must be >= 0 DN, got {}", self.baseline_dn)
        })?;
        check(
            self.window_top_m.is_finite() && self.window_top_m < self.altitude_m,
            "scene.window_top_m",
            || {
                format!(
                    "must lie below the aircraft ({} m), got {}",
                    self.altitude_m, self.window_top_m
                )
            },
        )?;
        check(self.return_samples > 0, "scene.return_samples", || {
            "must be at least 1".into()
        })?;
        if let Some(NoiseConfig::Uniform { amplitude_dn }) = &self.noise {
            check(
                finite_nonneg(*amplitude_dn),
                "scene.noise.amplitude_dn",
                || format!("must be >= 0 DN, got {amplitude_dn}"),
            )?;
        }
        check(
            self.sensor.is_some() != self.sensor_profile.is_some(),
            "scene.sensor",
            || "give exactly one of `sensor_profile` and `[scene.sensor]`".into(),
        )?;
        let f = &self.flight;
        check(
            f.start_lat_deg.is_finite() && f.start_lat_deg.abs() < 89.0,
            "scene.flight.start_lat_deg",
            || format!("must lie within +-89 deg, got {}", f.start_lat_deg),
        )?;
        check(
            f.start_lon_deg.is_finite(),
            "scene.flight.start_lon_deg",
            || format!("must be finite, got {}", f.start_lon_deg),
        )?;
        check(finite_nonneg(f.speed_mps), "scene.flight.speed_mps", || {
            format!("must be >= 0 m/s, got {}", f.speed_mps)
        })?;
        check(
            f.heading_deg.is_finite(),
            "scene.flight.heading_deg",
            || format!("must be finite, got {}", f.heading_deg),
        )?;
        check(
            finite_pos(f.nav_rate_hz),
            "scene.flight.nav_rate_hz",
            || format!("must be a positive rate in Hz, got {}", f.nav_rate_hz),
        )?;
        check(
            f.gps_utc_offset_s.is_finite(),
            "scene.flight.gps_utc_offset_s",
            || format!("must be finite, got {}", f.gps_utc_offset_s),
        )?;
        Ok(())
    }
}

/// Checks the sensor fields the simulator reads.
fn check_sensor(s: &SensorProfile) -> Result<(), SceneError> {
    check(
        s.sample_interval_ns.is_finite() && s.sample_interval_ns > 0.0,
        "sensor.sample_interval_ns",
        || format!("must be positive, got {}", s.sample_interval_ns),
    )?;
    check(
        s.pulse_fwhm_ns.is_finite() && s.pulse_fwhm_ns > 0.0,
        "sensor.pulse_fwhm_ns",
        || format!("must be positive, got {}", s.pulse_fwhm_ns),
    )?;
    check(
        s.bits_per_sample == 8 || s.bits_per_sample == 16,
        "sensor.bits_per_sample",
        || format!("must be 8 or 16, got {}", s.bits_per_sample),
    )?;
    check(
        s.pulse_rate_hz.is_finite() && s.pulse_rate_hz > 0.0,
        "sensor.pulse_rate_hz",
        || format!("must be positive, got {}", s.pulse_rate_hz),
    )?;
    check(
        s.digitizer_gain_v_per_dn.is_finite() && s.digitizer_offset_v.is_finite(),
        "sensor.digitizer_gain_v_per_dn",
        || "digitizer gain and offset must be finite".into(),
    )
}

impl crate::core::validate::Validate for SceneFile {
    fn validate(&self, _path: &str, v: &mut crate::core::validate::Validator) {
        let issue = |e: SceneError| match e {
            SceneError::Invalid { field, reason } => (field.to_string(), reason),
            SceneError::Parse { field, message, .. } => (
                "scene.sensor_profile".to_string(),
                format!("{field}: {message}"),
            ),
            SceneError::Io { path, source } => (
                "scene.sensor_profile".to_string(),
                format!("cannot read {}: {source}", path.display()),
            ),
        };
        if let Err(e) = self.scene.validate() {
            let (p, r) = issue(e);
            v.report(p, r);
        }
        let base = v.base_dir().map(Path::to_path_buf).unwrap_or_default();
        if let Err(e) = self.scene.resolve_sensor(&base) {
            let (p, r) = issue(e);
            v.report(p, r);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::sensor::test_sensor;

    #[test]
    fn scene_round_trips_through_toml() {
        let scene = Scene {
            seed: 7,
            pulses: 12,
            pulse_rate_hz: Some(1000.0),
            noise: Some(NoiseConfig::Uniform { amplitude_dn: 3.0 }),
            sensor: Some(test_sensor()),
            flight: FlightConfig {
                heading_deg: 45.0,
                ..Default::default()
            },
            ..Default::default()
        };
        let text = scene.to_toml_string().unwrap();
        assert!(text.contains("[scene.sensor]"), "{text}");
        let back = Scene::from_toml_str(&text).unwrap();
        assert_eq!(back, scene);
        // And by reference to a profile file.
        let scene = Scene {
            sensor_profile: Some("../sensors/x.toml".into()),
            ..Default::default()
        };
        let back = Scene::from_toml_str(&scene.to_toml_string().unwrap()).unwrap();
        assert_eq!(back, scene);
    }

    #[test]
    fn defaults_are_the_documented_ones() {
        let s = Scene::from_toml_str("[scene]\nsensor_profile = \"s.toml\"\n").unwrap();
        assert_eq!(s.altitude_m, 1000.0);
        assert_eq!(s.ground_reflectance, 0.3);
        assert_eq!(s.plane_height_m, 15.0);
        assert_eq!(s.plane_cover, 0.4);
        assert_eq!(s.plane_reflectance, 0.5);
        assert_eq!(s.peak_dn, 200.0);
        assert_eq!(s.baseline_dn, 12.0);
        assert_eq!(s.flight.nav_rate_hz, 10.0);
        assert_eq!(s.noise, None);
    }

    #[test]
    fn unknown_keys_are_rejected_with_their_path() {
        for (text, field) in [
            (
                "[scene]\nsensor_profile = \"s\"\nplane_covr = 0.2\n",
                "scene.plane_covr",
            ),
            (
                "[scene]\nsensor_profile = \"s\"\nnoise = { kind = \"uniform\", amplitude = 1 }\n",
                "scene.noise",
            ),
            (
                "[scene]\nsensor_profile = \"s\"\nnoise = { kind = \"gaussian\", amplitude_dn = 1 }\n",
                "scene.noise.kind",
            ),
            (
                "[scene]\nsensor_profile = \"s\"\n[scene.flight]\nspeed = 3\n",
                "scene.flight.speed",
            ),
            ("[other]\n", "other"),
        ] {
            match Scene::from_toml_str(text) {
                Err(SceneError::Parse { field: f, .. }) => assert_eq!(f, field, "{text}"),
                other => panic!("{text}: expected a parse error, got {other:?}"),
            }
        }
    }

    #[test]
    fn invalid_values_name_their_field() {
        let base = || Scene {
            sensor: Some(test_sensor()),
            ..Default::default()
        };
        let cases: [(Scene, &str); 5] = [
            (
                Scene {
                    plane_cover: 1.5,
                    ..base()
                },
                "scene.plane_cover",
            ),
            (
                Scene {
                    plane_height_m: 2000.0,
                    ..base()
                },
                "scene.plane_height_m",
            ),
            (
                Scene {
                    sensor_profile: Some("x".into()),
                    ..base()
                },
                "scene.sensor",
            ),
            (
                Scene {
                    noise: Some(NoiseConfig::Uniform { amplitude_dn: -1.0 }),
                    ..base()
                },
                "scene.noise.amplitude_dn",
            ),
            (
                Scene {
                    return_samples: 0,
                    ..base()
                },
                "scene.return_samples",
            ),
        ];
        for (scene, field) in cases {
            match scene.validate() {
                Err(SceneError::Invalid { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{field}: {other:?}"),
            }
        }
        let mut bad_sensor = test_sensor();
        bad_sensor.bits_per_sample = 12;
        let scene = Scene {
            sensor: Some(bad_sensor),
            ..Default::default()
        };
        assert!(matches!(
            scene.resolve_sensor(Path::new(".")),
            Err(SceneError::Invalid {
                field: "sensor.bits_per_sample",
                ..
            })
        ));
    }

    #[test]
    fn a_sensor_profile_path_is_resolved_from_the_scene_folder() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("scenes")).unwrap();
        std::fs::create_dir_all(dir.path().join("sensors")).unwrap();
        let sensor = test_sensor();
        std::fs::write(
            dir.path().join("sensors/s.toml"),
            toml::to_string(&SensorFile {
                sensor: sensor.clone(),
            })
            .unwrap(),
        )
        .unwrap();
        let scene_path = dir.path().join("scenes/a.toml");
        std::fs::write(
            &scene_path,
            "[scene]\npulses = 3\nsensor_profile = \"../sensors/s.toml\"\n",
        )
        .unwrap();
        let (scene, resolved) = Scene::load(&scene_path).unwrap();
        assert_eq!(scene.pulses, 3);
        assert_eq!(resolved, sensor);
    }

    #[test]
    fn the_shipped_two_layer_scene_parses() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/scenes/two_layer.toml");
        let scene = Scene::from_toml_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        assert_eq!(scene.pulses, 2000);
        assert_eq!(
            scene.noise,
            Some(NoiseConfig::Uniform { amplitude_dn: 3.0 })
        );
        assert!(scene.sensor_profile.is_some());
    }
}
