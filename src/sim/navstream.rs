//! The simulated navigation stream of a GNSS/INS receiver: what one receiver port would deliver
//! for each navigation epoch, in NMEA 0183 text and/or NovAtel OEM binary, with opt-in
//! imperfections (Gaussian position and attitude errors, configured outages, random epoch loss),
//! all seeded and deterministic.
//!
//! ```toml
//! [navigation]
//! rate_hz = 10.0
//! formats = ["nmea", "novatel"]
//! gps_week = 1690
//! gps_utc_offset_s = 18.0
//! noise = { position_m = 0.05, attitude_deg = 0.005, heading_deg = 0.02 }
//! dropouts = [{ start_s = 12.0, duration_s = 3.5 }]
//! random_dropout_probability = 0.01
//! ```
//!
//! Per epoch ([`NavStream::epoch_bytes`]):
//! - **nmea**: `$GPGGA` and `$PASHR`, plus `$GPZDA` when the epoch falls on a whole UTC second
//!   (the writers of [`crate::sim::nmea_writer`]);
//! - **novatel**: a binary INSPVAX (long header; position above mean sea level with an
//!   undulation of 0, velocity, attitude and their standard deviations; time in the header's
//!   GPS week and milliseconds), plus a binary TIME (GPS − UTC and the UTC date) when the epoch
//!   falls on a whole GPS second, as receivers log it `ontime 1`.
//!
//! INSPVAX is the one of our decoder's INS messages ([`crate::nav::novatel`]) that carries
//! everything a truth file needs (height above MSL and undulation, position and attitude
//! standard deviations) and the one the real SPAN log of the fixtures holds, against which the
//! byte layout is checked (`navstream/tests.rs`).
//!
//! Units: seconds, metres, degrees and metres per second as the names say.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::nav::crc::novatel_crc32;
use crate::nav::dating::{GPS_EPOCH_DAYS, WEEK_S, civil_of_days};
use crate::nav::trajectory::radii;
use crate::sim::nmea_writer::{NavFix, gga, pashr, zda};

#[cfg(test)]
mod tests;

/// Errors of parsing or validating a `[navigation]` table.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NavStreamError {
    /// The TOML did not parse into a [`NavigationConfig`].
    #[error("at `{field}`: {message}")]
    Parse {
        /// Path of the offending field, e.g. `navigation.formats[1]` (empty for a TOML syntax
        /// error, whose message gives the line).
        field: String,
        /// What went wrong.
        message: String,
    },
    /// A field has a value the stream cannot use.
    #[error("{field} {reason}")]
    Invalid {
        /// Path of the field, e.g. `navigation.dropouts[0].duration_s`.
        field: String,
        /// Why, e.g. `must be > 0 (got -1)`.
        reason: String,
    },
}

/// A record format of the stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StreamFormat {
    /// NMEA 0183: GGA + PASHR every epoch, ZDA on whole UTC seconds.
    Nmea,
    /// NovAtel OEM binary: INSPVAX every epoch, TIME on whole GPS seconds.
    Novatel,
}

/// Gaussian errors added to what the receiver reports (1-sigma values; each default 0).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavNoise {
    /// 1-sigma position error, metres, applied independently north, east and up. Default 0.
    #[serde(default)]
    pub position_m: f64,
    /// 1-sigma roll and pitch error, degrees (each independently). Default 0.
    #[serde(default)]
    pub attitude_deg: f64,
    /// 1-sigma heading error, degrees. Default 0.
    #[serde(default)]
    pub heading_deg: f64,
}

/// An outage of the receiver output: no bytes at all for epochs inside it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Dropout {
    /// Start, seconds after the first epoch (≥ 0). Required.
    pub start_s: f64,
    /// Length, seconds (> 0); the outage covers `[start_s, start_s + duration_s)` to within a
    /// microsecond. Required.
    pub duration_s: f64,
}

/// The `[navigation]` table of a scene: what the simulated receiver sends and how imperfectly.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavigationConfig {
    /// Epoch rate, hertz: > 0, at most 100 with `nmea` (centisecond GGA times) and 1000 with
    /// `novatel` only (millisecond header times). Default 10.
    #[serde(default = "default_rate")]
    pub rate_hz: f64,
    /// Record formats sent each epoch, `"nmea"` and/or `"novatel"`, in this order on the wire;
    /// not empty, no repeats. Default `["nmea"]`.
    #[serde(default = "default_formats")]
    pub formats: Vec<StreamFormat>,
    /// Full GPS week (not modulo 1024) of epoch time 0 s, 1..=65535 (the NovAtel header holds
    /// it in 16 bits; 0 means "unknown" to receivers). Default 1690.
    #[serde(default = "default_gps_week")]
    pub gps_week: u32,
    /// GPS − UTC, whole seconds (leap seconds), 0..=255. Default 18 (since 2017).
    #[serde(default = "default_leap")]
    pub gps_utc_offset_s: f64,
    /// Gaussian errors of the reported position and attitude. Default: none (the truth is
    /// reported exactly, to the formats' resolution).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<NavNoise>,
    /// Outages relative to the first epoch. Default none.
    #[serde(default)]
    pub dropouts: Vec<Dropout>,
    /// Probability that an epoch is lost (no bytes), 0..=1, drawn per epoch. Default 0.
    #[serde(default)]
    pub random_dropout_probability: f64,
}

fn default_rate() -> f64 {
    10.0
}
fn default_formats() -> Vec<StreamFormat> {
    vec![StreamFormat::Nmea]
}
fn default_gps_week() -> u32 {
    1690
}
fn default_leap() -> f64 {
    18.0
}

impl Default for NavigationConfig {
    fn default() -> Self {
        NavigationConfig {
            rate_hz: default_rate(),
            formats: default_formats(),
            gps_week: default_gps_week(),
            gps_utc_offset_s: default_leap(),
            noise: None,
            dropouts: Vec::new(),
            random_dropout_probability: 0.0,
        }
    }
}

/// A TOML document holding one `[navigation]` table (for [`NavigationConfig::from_toml_str`]).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct NavigationDocument {
    #[serde(default)]
    navigation: NavigationConfig,
}

fn invalid(field: impl Into<String>, reason: String) -> NavStreamError {
    NavStreamError::Invalid {
        field: field.into(),
        reason,
    }
}

impl NavigationConfig {
    /// Parses a TOML document with a `[navigation]` table (the defaults when it has none) and
    /// validates it; errors name the field (`navigation.formats[0]`,
    /// `navigation.noise.position_m`, ...).
    pub fn from_toml_str(text: &str) -> Result<Self, NavStreamError> {
        let de = toml::Deserializer::parse(text).map_err(|e| NavStreamError::Parse {
            field: String::new(),
            message: e.to_string(),
        })?;
        let doc: NavigationDocument =
            serde_path_to_error::deserialize(de).map_err(|e| NavStreamError::Parse {
                field: e.path().to_string(),
                message: e.inner().to_string(),
            })?;
        doc.navigation.validate()?;
        Ok(doc.navigation)
    }

    /// Checks every field; the first problem found is returned with the field's path.
    pub fn validate(&self) -> Result<(), NavStreamError> {
        let nmea = self.formats.contains(&StreamFormat::Nmea);
        let max_rate = if nmea { 100.0 } else { 1000.0 };
        if !(self.rate_hz.is_finite() && self.rate_hz > 0.0) {
            return Err(invalid(
                "navigation.rate_hz",
                format!("must be > 0 (got {})", self.rate_hz),
            ));
        }
        if self.rate_hz > max_rate {
            return Err(invalid(
                "navigation.rate_hz",
                format!(
                    "must be at most {max_rate} Hz with these formats (got {})",
                    self.rate_hz
                ),
            ));
        }
        if self.formats.is_empty() {
            return Err(invalid(
                "navigation.formats",
                "must name at least one format (\"nmea\", \"novatel\")".into(),
            ));
        }
        for (i, f) in self.formats.iter().enumerate() {
            if self.formats[..i].contains(f) {
                return Err(invalid(
                    format!("navigation.formats[{i}]"),
                    format!("repeats {f:?}"),
                ));
            }
        }
        if !(1..=u16::MAX as u32).contains(&self.gps_week) {
            return Err(invalid(
                "navigation.gps_week",
                format!("must be in 1..=65535 (got {})", self.gps_week),
            ));
        }
        let leap = self.gps_utc_offset_s;
        if !(leap.is_finite() && (0.0..=255.0).contains(&leap) && leap.fract() == 0.0) {
            return Err(invalid(
                "navigation.gps_utc_offset_s",
                format!("must be a whole number of seconds in 0..=255 (got {leap})"),
            ));
        }
        if let Some(n) = &self.noise {
            for (name, v) in [
                ("position_m", n.position_m),
                ("attitude_deg", n.attitude_deg),
                ("heading_deg", n.heading_deg),
            ] {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(invalid(
                        format!("navigation.noise.{name}"),
                        format!("must be finite and >= 0 (got {v})"),
                    ));
                }
            }
        }
        for (i, d) in self.dropouts.iter().enumerate() {
            if !(d.start_s.is_finite() && d.start_s >= 0.0) {
                return Err(invalid(
                    format!("navigation.dropouts[{i}].start_s"),
                    format!("must be finite and >= 0 (got {})", d.start_s),
                ));
            }
            if !(d.duration_s.is_finite() && d.duration_s > 0.0) {
                return Err(invalid(
                    format!("navigation.dropouts[{i}].duration_s"),
                    format!("must be finite and > 0 (got {})", d.duration_s),
                ));
            }
        }
        let p = self.random_dropout_probability;
        if !(0.0..=1.0).contains(&p) {
            return Err(invalid(
                "navigation.random_dropout_probability",
                format!("must be in 0..=1 (got {p})"),
            ));
        }
        Ok(())
    }
}

/// The errors applied to one epoch (all 0 without `noise`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct NavErrors {
    /// Position error north, metres.
    pub north_m: f64,
    /// Position error east, metres.
    pub east_m: f64,
    /// Position error up, metres.
    pub up_m: f64,
    /// Roll error, degrees.
    pub roll_deg: f64,
    /// Pitch error, degrees.
    pub pitch_deg: f64,
    /// Heading error, degrees.
    pub heading_deg: f64,
}

/// Why an epoch was not sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DropReason {
    /// Inside one of `navigation.dropouts`.
    Dropout,
    /// Lost with `navigation.random_dropout_probability`.
    Random,
    /// The time or a truth value was not finite, or the time falls outside GPS weeks
    /// 1..=65535: nothing sensible can be encoded.
    InvalidInput,
}

/// What happened to one epoch, for a truth file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpochRecord {
    /// Epoch number from 0 (every call of [`NavStream::epoch_bytes`] counts, sent or not).
    pub index: u64,
    /// GPS time of the epoch, seconds of `gps_week`.
    pub gps_s: f64,
    /// Why it was not sent; `None` when its bytes were written.
    pub dropped: Option<DropReason>,
    /// The errors drawn for it (drawn for dropped epochs too, so that an outage does not
    /// change the errors of the epochs after it).
    pub errors: NavErrors,
    /// The state the records report: the truth with `errors` applied, UTC time of day from
    /// `gps_s` and `gps_utc_offset_s`.
    pub reported: NavFix,
}

/// The truth `fix` with `errors` applied: north/east/up metres converted to latitude and
/// longitude with the WGS84 meridian and prime-vertical radii at the fix's latitude (at a pole,
/// where longitude is undefined, an east error leaves it as it was); latitude and pitch clamped
/// to ±90, roll and longitude wrapped to -180..180 and heading to 0..360 when they leave those
/// ranges. Zero errors leave every value exactly as it was.
pub fn noisy_fix(fix: &NavFix, errors: &NavErrors) -> NavFix {
    if *errors == NavErrors::default() {
        return *fix;
    }
    let phi = fix.lat_deg.to_radians();
    let (m, n) = radii(phi);
    let parallel_m = n * phi.cos();
    let lat_deg = fix.lat_deg + (errors.north_m / m).to_degrees();
    let mut lon_deg = fix.lon_deg;
    if parallel_m > 1e-3 {
        lon_deg += (errors.east_m / parallel_m).to_degrees();
    }
    NavFix {
        utc_time_of_day_s: fix.utc_time_of_day_s,
        lat_deg: lat_deg.clamp(-90.0, 90.0),
        lon_deg: wrap_180(lon_deg),
        altitude_m: fix.altitude_m + errors.up_m,
        heading_deg: (fix.heading_deg + errors.heading_deg).rem_euclid(360.0),
        roll_deg: wrap_180(fix.roll_deg + errors.roll_deg),
        pitch_deg: (fix.pitch_deg + errors.pitch_deg).clamp(-90.0, 90.0),
    }
}

/// `deg` unchanged in -180..=180, else wrapped into -180..180.
fn wrap_180(deg: f64) -> f64 {
    if (-180.0..=180.0).contains(&deg) {
        deg
    } else {
        (deg + 180.0).rem_euclid(360.0) - 180.0
    }
}

/// Standard normal draws by the Box-Muller transform, the second value of each pair kept for
/// the next draw.
#[derive(Debug, Clone)]
struct Gaussian {
    rng: ChaCha8Rng,
    spare: Option<f64>,
}

impl Gaussian {
    fn new(rng: ChaCha8Rng) -> Self {
        Gaussian { rng, spare: None }
    }

    fn sample(&mut self) -> f64 {
        if let Some(z) = self.spare.take() {
            return z;
        }
        // u1 in (0, 1] keeps the logarithm finite.
        let u1 = 1.0 - self.rng.random::<f64>();
        let u2 = self.rng.random::<f64>();
        let r = (-2.0 * u1.ln()).sqrt();
        let a = std::f64::consts::TAU * u2;
        self.spare = Some(r * a.sin());
        r * a.cos()
    }
}

/// ChaCha8 stream numbers of the two generators: noise and epoch loss are drawn from separate
/// streams, so turning one on does not change the other's draws.
const NOISE_STREAM: u64 = 0x6e61_765f_6e6f_6973;
const DROP_STREAM: u64 = 0x6e61_765f_6472_6f70;

/// Tolerance of the dropout window comparison, seconds.
const DROPOUT_EPS_S: f64 = 1e-6;

/// The simulated receiver port (see the module documentation).
#[derive(Debug, Clone)]
pub struct NavStream {
    config: NavigationConfig,
    noise: Gaussian,
    loss: ChaCha8Rng,
    first_gps_s: Option<f64>,
    previous: Option<(f64, NavFix)>,
    next_index: u64,
    last: Option<EpochRecord>,
}

impl NavStream {
    /// A stream of `config` (validated here) whose draws come from ChaCha8 seeded with `seed`.
    pub fn new(config: NavigationConfig, seed: u64) -> Result<Self, NavStreamError> {
        config.validate()?;
        let mut noise = ChaCha8Rng::seed_from_u64(seed);
        noise.set_stream(NOISE_STREAM);
        let mut loss = ChaCha8Rng::seed_from_u64(seed);
        loss.set_stream(DROP_STREAM);
        Ok(NavStream {
            config,
            noise: Gaussian::new(noise),
            loss,
            first_gps_s: None,
            previous: None,
            next_index: 0,
            last: None,
        })
    }

    /// The configuration in force.
    pub fn config(&self) -> &NavigationConfig {
        &self.config
    }

    /// GPS time (seconds of `gps_week`) of epoch `k` of a stream whose first epoch is at
    /// `first_gps_s`: `first_gps_s + k / rate_hz`.
    pub fn epoch_gps_s(&self, first_gps_s: f64, k: u64) -> f64 {
        first_gps_s + k as f64 / self.config.rate_hz
    }

    /// What happened to the latest epoch (its errors, reported state, whether it was sent).
    pub fn last_epoch(&self) -> Option<&EpochRecord> {
        self.last.as_ref()
    }

    /// Tells the stream where the aircraft was at `gps_s` before the first epoch, so that the
    /// first epoch's INSPVAX velocity is the truth's too (sends nothing, draws nothing).
    pub fn prime(&mut self, gps_s: f64, truth: &NavFix) {
        if gps_s.is_finite() {
            self.previous = Some((gps_s, *truth));
        }
    }

    /// Appends to `out` the bytes the receiver sends for the epoch at GPS time `gps_s` (seconds
    /// of `gps_week`; later weeks roll over) whose true state is `truth`, in the configured
    /// formats, with the configured errors; returns false and writes nothing when the epoch is
    /// lost (dropout, random loss, or invalid input: a non-finite time or truth value, or a time
    /// outside GPS weeks 1..=65535).
    ///
    /// `truth.utc_time_of_day_s` is not used: every record's time comes from `gps_s`,
    /// `gps_week` and `gps_utc_offset_s`, so the formats agree. Call it once per epoch, in time
    /// order; the first call's `gps_s` is the origin of `dropouts`. The INSPVAX velocity is the
    /// truth's change since the previous call (or [`NavStream::prime`]; 0 at the first without it).
    pub fn epoch_bytes(&mut self, gps_s: f64, truth: &NavFix, out: &mut Vec<u8>) -> bool {
        let index = self.next_index;
        self.next_index += 1;
        if self.first_gps_s.is_none() && gps_s.is_finite() {
            self.first_gps_s = Some(gps_s);
        }
        let first = self.first_gps_s.unwrap_or(gps_s);
        // Draws come first and for every epoch, so each epoch's errors and loss depend only on
        // the seed and its index.
        let errors = match self.config.noise {
            Some(n) => {
                let mut g = || self.noise.sample();
                NavErrors {
                    north_m: n.position_m * g(),
                    east_m: n.position_m * g(),
                    up_m: n.position_m * g(),
                    roll_deg: n.attitude_deg * g(),
                    pitch_deg: n.attitude_deg * g(),
                    heading_deg: n.heading_deg * g(),
                }
            }
            None => NavErrors::default(),
        };
        let p = self.config.random_dropout_probability;
        let lost = p > 0.0 && self.loss.random::<f64>() < p;
        let finite = [
            gps_s,
            first,
            truth.lat_deg,
            truth.lon_deg,
            truth.altitude_m,
            truth.heading_deg,
            truth.roll_deg,
            truth.pitch_deg,
        ]
        .iter()
        .all(|v| v.is_finite());
        let week_ms = week_ms(self.config.gps_week, gps_s);
        let finite = finite && week_ms.is_some();
        let leap = self.config.gps_utc_offset_s;
        let mut reported = noisy_fix(truth, &errors);
        reported.utc_time_of_day_s = (gps_s - leap).rem_euclid(86_400.0);
        let rel = gps_s - first;
        let dropped = if !finite {
            Some(DropReason::InvalidInput)
        } else if self.config.dropouts.iter().any(|d| {
            rel >= d.start_s - DROPOUT_EPS_S && rel < d.start_s + d.duration_s - DROPOUT_EPS_S
        }) {
            Some(DropReason::Dropout)
        } else if lost {
            Some(DropReason::Random)
        } else {
            None
        };
        let velocity = match self.previous {
            Some((t0, f0)) if finite && gps_s > t0 => truth_velocity(&f0, truth, gps_s - t0),
            _ => [0.0; 3],
        };
        if finite {
            self.previous = Some((gps_s, *truth));
        }
        self.last = Some(EpochRecord {
            index,
            gps_s,
            dropped,
            errors,
            reported,
        });
        if dropped.is_some() {
            return false;
        }
        for format in &self.config.formats {
            match format {
                StreamFormat::Nmea => {
                    out.extend_from_slice(gga(&reported).as_bytes());
                    out.extend_from_slice(pashr(&reported).as_bytes());
                    let centis = (reported.utc_time_of_day_s * 100.0).round() as i64;
                    if centis % 100 == 0 {
                        out.extend_from_slice(zda(self.config.gps_week, gps_s, leap).as_bytes());
                    }
                }
                StreamFormat::Novatel => {
                    let Some((week, ms)) = week_ms else {
                        // Unreachable: such an epoch was dropped as invalid input above.
                        continue;
                    };
                    let sigma = self.config.noise.unwrap_or(NOMINAL_SIGMA);
                    let rec = InspvaxRecord {
                        ins_status: INS_SOLUTION_GOOD,
                        position_type: INS_RTKFIXED,
                        lat_deg: reported.lat_deg,
                        lon_deg: reported.lon_deg,
                        height_msl_m: reported.altitude_m,
                        undulation_m: 0.0,
                        velocity_neu_mps: velocity,
                        roll_deg: reported.roll_deg,
                        pitch_deg: reported.pitch_deg,
                        azimuth_deg: reported.heading_deg,
                        position_sigma_m: [sigma.position_m as f32; 3],
                        velocity_sigma_mps: [NOMINAL_VELOCITY_SIGMA_MPS; 3],
                        attitude_sigma_deg: [
                            sigma.attitude_deg as f32,
                            sigma.attitude_deg as f32,
                            sigma.heading_deg as f32,
                        ],
                        extended_status: 0,
                        time_since_update_s: 0,
                    };
                    let header = LongHeader::new(id::INSPVAX, week, ms);
                    write_frame(&header, &rec.encode(), out);
                    if ms % 1000 == 0 {
                        let time = TimeRecord::at(week, ms, leap);
                        let header = LongHeader::new(id::TIME, week, ms);
                        write_frame(&header, &time.encode(), out);
                    }
                }
            }
        }
        true
    }
}

/// Standard deviations written into INSPVAX without `noise`: the accuracies the PASHR writer
/// states (0.01° roll and pitch, 0.02° heading) and 2 cm in position.
const NOMINAL_SIGMA: NavNoise = NavNoise {
    position_m: 0.02,
    attitude_deg: 0.01,
    heading_deg: 0.02,
};
/// Velocity standard deviation written into INSPVAX, m/s.
const NOMINAL_VELOCITY_SIGMA_MPS: f32 = 0.01;

/// North, east, up velocity (m/s) of moving from `a` to `b` in `dt_s` seconds.
fn truth_velocity(a: &NavFix, b: &NavFix, dt_s: f64) -> [f64; 3] {
    let phi = a.lat_deg.to_radians();
    let (m, n) = radii(phi);
    let dlon = (b.lon_deg - a.lon_deg + 540.0).rem_euclid(360.0) - 180.0;
    [
        (b.lat_deg - a.lat_deg).to_radians() * m / dt_s,
        dlon.to_radians() * n * phi.cos() / dt_s,
        (b.altitude_m - a.altitude_m) / dt_s,
    ]
}

/// The full GPS week and milliseconds of the week of time `gps_s` seconds after the start of
/// week `week` (rolling over into later or earlier weeks, to the nearest millisecond); `None`
/// when the week falls outside 1..=65535 (what the NovAtel header can state) or `gps_s` is not
/// finite.
pub fn week_ms(week: u32, gps_s: f64) -> Option<(u16, u32)> {
    if !gps_s.is_finite() {
        return None;
    }
    let week_ms = (WEEK_S * 1000.0) as i64;
    // Saturating float-to-integer conversion; anything near the limits fails the range below.
    let total_ms = (gps_s * 1000.0).round() as i64;
    let w = (week as i64).saturating_add(total_ms.div_euclid(week_ms));
    let w = u16::try_from(w).ok().filter(|&w| w > 0)?;
    Some((w, total_ms.rem_euclid(week_ms) as u32))
}

// ---- NovAtel OEM binary encoding (byte layouts from the OEM7 firmware reference manual) ----

/// NovAtel message identifiers written here.
pub mod id {
    /// INSPVAX: extended INS position, velocity and attitude with standard deviations.
    pub const INSPVAX: u16 = crate::nav::novatel::id::INSPVAX;
    /// TIME: receiver clock and UTC offset.
    pub const TIME: u16 = crate::nav::novatel::id::TIME;
}

/// INS status `INS_SOLUTION_GOOD`.
pub const INS_SOLUTION_GOOD: u32 = 3;
/// Position type `INS_RTKFIXED`.
pub const INS_RTKFIXED: u32 = 56;
/// Header time status `FINESTEERING`.
pub const FINESTEERING: u8 = 180;
/// Length of the long header, bytes.
pub const LONG_HEADER_LEN: usize = 28;
/// Length of an INSPVAX message body, bytes.
pub const INSPVAX_LEN: usize = 126;
/// Length of a TIME message body, bytes.
pub const TIME_LEN: usize = 44;

/// The 28-byte long header of a NovAtel binary message (the message length is the body's).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LongHeader {
    /// Message identifier (byte 4, u16).
    pub message_id: u16,
    /// Message type (byte 6): bits 5–6 format (0 binary), bit 7 response. We write 0.
    pub message_type: u8,
    /// Port address (byte 7) the receiver stamps. We write 0.
    pub port_address: u8,
    /// Sequence (byte 10, u16): remaining messages with the same id and time. We write 0.
    pub sequence: u16,
    /// Idle time of the processor (byte 12), half-percent units. We write 0.
    pub idle_time: u8,
    /// Time status (byte 13). We write [`FINESTEERING`].
    pub time_status: u8,
    /// GPS week (byte 14, u16).
    pub week: u16,
    /// Milliseconds of the GPS week (byte 16, u32).
    pub ms: u32,
    /// Receiver status word (byte 20, u32). We write 0.
    pub receiver_status: u32,
    /// Reserved (byte 24, u16). We write 0.
    pub reserved: u16,
    /// Receiver software build (byte 26, u16). We write 0.
    pub sw_version: u16,
}

impl LongHeader {
    /// The header of message `message_id` at `week`, `ms`, other fields as documented.
    pub fn new(message_id: u16, week: u16, ms: u32) -> Self {
        LongHeader {
            message_id,
            message_type: 0,
            port_address: 0,
            sequence: 0,
            idle_time: 0,
            time_status: FINESTEERING,
            week,
            ms,
            receiver_status: 0,
            reserved: 0,
            sw_version: 0,
        }
    }

    /// The header bytes for a body of `body_len` bytes (sync `AA 44 12`, header length 28).
    pub fn encode(&self, body_len: u16) -> [u8; LONG_HEADER_LEN] {
        let mut h = [0u8; LONG_HEADER_LEN];
        h[..4].copy_from_slice(&[0xAA, 0x44, 0x12, LONG_HEADER_LEN as u8]);
        h[4..6].copy_from_slice(&self.message_id.to_le_bytes());
        h[6] = self.message_type;
        h[7] = self.port_address;
        h[8..10].copy_from_slice(&body_len.to_le_bytes());
        h[10..12].copy_from_slice(&self.sequence.to_le_bytes());
        h[12] = self.idle_time;
        h[13] = self.time_status;
        h[14..16].copy_from_slice(&self.week.to_le_bytes());
        h[16..20].copy_from_slice(&self.ms.to_le_bytes());
        h[20..24].copy_from_slice(&self.receiver_status.to_le_bytes());
        h[24..26].copy_from_slice(&self.reserved.to_le_bytes());
        h[26..28].copy_from_slice(&self.sw_version.to_le_bytes());
        h
    }
}

/// Appends `header` + `body` + CRC-32 (little-endian, over header and body) to `out`.
pub fn write_frame(header: &LongHeader, body: &[u8], out: &mut Vec<u8>) {
    let start = out.len();
    // Bodies written here are at most 126 bytes; saturate rather than wrap for others.
    let len = u16::try_from(body.len()).unwrap_or(u16::MAX);
    out.extend_from_slice(&header.encode(len));
    out.extend_from_slice(body);
    let crc = novatel_crc32(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// The fields of an INSPVAX message body, in wire order (126 bytes, little-endian).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InspvaxRecord {
    /// INS status (offset 0, u32).
    pub ins_status: u32,
    /// Position type (offset 4, u32).
    pub position_type: u32,
    /// Latitude, degrees (offset 8, f64).
    pub lat_deg: f64,
    /// Longitude, degrees (offset 16, f64).
    pub lon_deg: f64,
    /// Height above mean sea level, metres (offset 24, f64).
    pub height_msl_m: f64,
    /// Undulation (geoid − ellipsoid separation), metres (offset 32, f32).
    pub undulation_m: f32,
    /// Velocity north, east, up, m/s (offsets 36, 44, 52, f64).
    pub velocity_neu_mps: [f64; 3],
    /// Roll, degrees (offset 60, f64).
    pub roll_deg: f64,
    /// Pitch, degrees (offset 68, f64).
    pub pitch_deg: f64,
    /// Azimuth (heading), degrees clockwise from true north (offset 76, f64).
    pub azimuth_deg: f64,
    /// Standard deviations of latitude, longitude, height, metres (offsets 84, 88, 92, f32).
    pub position_sigma_m: [f32; 3],
    /// Standard deviations of north, east, up velocity, m/s (offsets 96, 100, 104, f32).
    pub velocity_sigma_mps: [f32; 3],
    /// Standard deviations of roll, pitch, azimuth, degrees (offsets 108, 112, 116, f32).
    pub attitude_sigma_deg: [f32; 3],
    /// Extended solution status (offset 120, u32).
    pub extended_status: u32,
    /// Seconds since the last update (offset 124, u16).
    pub time_since_update_s: u16,
}

impl InspvaxRecord {
    /// The message body.
    pub fn encode(&self) -> [u8; INSPVAX_LEN] {
        let mut w = Writer::<INSPVAX_LEN>::new();
        w.put(&self.ins_status.to_le_bytes());
        w.put(&self.position_type.to_le_bytes());
        for v in [self.lat_deg, self.lon_deg, self.height_msl_m] {
            w.put(&v.to_le_bytes());
        }
        w.put(&self.undulation_m.to_le_bytes());
        for v in self.velocity_neu_mps {
            w.put(&v.to_le_bytes());
        }
        for v in [self.roll_deg, self.pitch_deg, self.azimuth_deg] {
            w.put(&v.to_le_bytes());
        }
        for v in self
            .position_sigma_m
            .iter()
            .chain(&self.velocity_sigma_mps)
            .chain(&self.attitude_sigma_deg)
        {
            w.put(&v.to_le_bytes());
        }
        w.put(&self.extended_status.to_le_bytes());
        w.put(&self.time_since_update_s.to_le_bytes());
        debug_assert_eq!(w.at, INSPVAX_LEN);
        w.buf
    }
}

/// Little-endian fields written in order into a fixed-size body.
struct Writer<const N: usize> {
    buf: [u8; N],
    at: usize,
}

impl<const N: usize> Writer<N> {
    fn new() -> Self {
        Writer { buf: [0; N], at: 0 }
    }

    /// Writes `bytes` at the cursor (bytes past the end are dropped: the layouts are fixed).
    fn put(&mut self, bytes: &[u8]) {
        for (d, s) in self.buf.iter_mut().skip(self.at).zip(bytes) {
            *d = *s;
        }
        self.at += bytes.len();
    }
}

/// The fields of a TIME message body, in wire order (44 bytes, little-endian).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimeRecord {
    /// Clock model status (offset 0, u32; 0 valid).
    pub clock_status: u32,
    /// Receiver clock offset from GPS time, seconds (offset 4, f64).
    pub offset_s: f64,
    /// Its standard deviation, seconds (offset 12, f64).
    pub offset_std_s: f64,
    /// UTC − GPS, seconds (offset 20, f64): −18 since 2017.
    pub utc_offset_s: f64,
    /// UTC year (offset 28, u32).
    pub utc_year: u32,
    /// UTC month 1..=12 (offset 32, u8).
    pub utc_month: u8,
    /// UTC day 1..=31 (offset 33, u8).
    pub utc_day: u8,
    /// UTC hour (offset 34, u8).
    pub utc_hour: u8,
    /// UTC minute (offset 35, u8).
    pub utc_min: u8,
    /// UTC milliseconds of the minute (offset 36, u32).
    pub utc_ms: u32,
    /// UTC status (offset 40, u32): 0 invalid, 1 valid, 2 warning.
    pub utc_status: u32,
}

impl TimeRecord {
    /// The TIME message of a receiver at `week`, `ms` of GPS time with GPS − UTC =
    /// `gps_minus_utc_s` (whole seconds), clock offset 0, UTC valid.
    pub fn at(week: u16, ms: u32, gps_minus_utc_s: f64) -> Self {
        let utc_ms = week as i64 * (WEEK_S as i64 * 1000) + ms as i64
            - (gps_minus_utc_s * 1000.0).round() as i64;
        let days = utc_ms.div_euclid(86_400_000);
        let tod_ms = utc_ms.rem_euclid(86_400_000);
        let (y, m, d) = civil_of_days(GPS_EPOCH_DAYS + days);
        TimeRecord {
            clock_status: 0,
            offset_s: 0.0,
            offset_std_s: 0.0,
            utc_offset_s: -gps_minus_utc_s,
            utc_year: y.clamp(0, u32::MAX as i64) as u32,
            utc_month: m as u8,
            utc_day: d as u8,
            utc_hour: (tod_ms / 3_600_000) as u8,
            utc_min: (tod_ms / 60_000 % 60) as u8,
            utc_ms: (tod_ms % 60_000) as u32,
            utc_status: 1,
        }
    }

    /// The message body.
    pub fn encode(&self) -> [u8; TIME_LEN] {
        let mut b = [0u8; TIME_LEN];
        b[0..4].copy_from_slice(&self.clock_status.to_le_bytes());
        b[4..12].copy_from_slice(&self.offset_s.to_le_bytes());
        b[12..20].copy_from_slice(&self.offset_std_s.to_le_bytes());
        b[20..28].copy_from_slice(&self.utc_offset_s.to_le_bytes());
        b[28..32].copy_from_slice(&self.utc_year.to_le_bytes());
        b[32] = self.utc_month;
        b[33] = self.utc_day;
        b[34] = self.utc_hour;
        b[35] = self.utc_min;
        b[36..40].copy_from_slice(&self.utc_ms.to_le_bytes());
        b[40..44].copy_from_slice(&self.utc_status.to_le_bytes());
        b
    }
}
