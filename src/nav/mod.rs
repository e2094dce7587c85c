//! Navigation: GNSS/INS records from receivers' byte streams and post-processed trajectories.
//!
//! Bytes from a port (or a recorded capture) go through one resynchronising [`framer::Framer`]
//! that finds NMEA 0183 sentences and NovAtel OEM binary messages in a mixed stream, checks
//! their checksums and counts what it skips; [`nmea`] and [`novatel`] decode the frames into
//! [`NavSample`]s; [`sbet`] reads Applanix SBET files. [`dating::NmeaDater`] gives NMEA times,
//! which carry no date, their date from ZDA/RMC and turns them into GPS time.
//!
//! Units: angles in degrees, positions in degrees (WGS84 latitude/longitude) and metres, speeds in
//! metres per second, times in seconds.

pub mod consumer;
pub mod crc;
pub mod dating;
pub mod decoder;
pub mod framer;
pub mod nmea;
pub mod novatel;
pub mod sbet;
pub mod trajectory;

use serde::Serialize;

/// How the time of a [`NavSample`] is stated by its record.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NavTime {
    /// GPS week (full, not modulo 1024) and seconds of that week (NovAtel, SBET with a week).
    Gps {
        /// Full GPS week number since 1980-01-06.
        week: u32,
        /// Seconds of the week, GPS time scale.
        sow: f64,
    },
    /// GPS seconds of an unknown week (SBET files carry no week).
    GpsSecondsOfWeek {
        /// Seconds of the week, GPS time scale.
        sow: f64,
    },
    /// UTC time of day without a date (most NMEA sentences); [`dating::NmeaDater`] dates it.
    UtcTimeOfDay {
        /// Seconds since UTC midnight.
        seconds: f64,
    },
    /// UTC date and time (RMC, ZDA).
    Utc {
        /// Days since 1970-01-01 (civil, proleptic Gregorian).
        days: i64,
        /// Seconds since UTC midnight.
        seconds: f64,
    },
    /// The record carries no time.
    None,
}

/// Which record a sample came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum NavKind {
    /// NMEA GGA: fix data.
    Gga,
    /// NMEA RMC: recommended minimum (position, speed, course, date).
    Rmc,
    /// NMEA ZDA: UTC date and time.
    Zda,
    /// NMEA HDT: true heading.
    Hdt,
    /// NMEA VTG: course and speed over ground.
    Vtg,
    /// NMEA GST: pseudorange error statistics.
    Gst,
    /// PASHR attitude (heading, roll, pitch, heave), as OxTS and others send it.
    Pashr,
    /// NovAtel INSPVA: INS position, velocity, attitude.
    Inspva,
    /// NovAtel INSPVAX: INSPVA with standard deviations.
    Inspvax,
    /// NovAtel BESTPOS: best GNSS position.
    Bestpos,
    /// NovAtel CORRIMUDATA: corrected IMU increments.
    Corrimudata,
    /// NovAtel TIME: receiver clock and UTC offset.
    Time,
    /// Applanix SBET record.
    Sbet,
}

/// One decoded navigation record: whichever quantities the record carries.
///
/// Positions are WGS84 geodetic; `height` is ellipsoidal (when the record gives only a height
/// above mean sea level and no geoid separation, `height` is empty and `height_msl` set).
/// Attitude follows the receivers' own conventions, which agree: roll positive right wing down,
/// pitch positive nose up, heading clockwise from true north (0..360).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct NavSample {
    /// The record it came from.
    pub kind: NavKind,
    /// Time as the record states it.
    #[serde(skip)]
    pub time: NavTime,
    /// Latitude, degrees north.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lat: Option<f64>,
    /// Longitude, degrees east.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lon: Option<f64>,
    /// Ellipsoidal height, metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height: Option<f64>,
    /// Height above mean sea level (geoid), metres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_msl: Option<f64>,
    /// Roll, degrees (right wing down positive).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roll: Option<f64>,
    /// Pitch, degrees (nose up positive).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pitch: Option<f64>,
    /// Heading (true), degrees clockwise from north, 0..360.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub heading: Option<f64>,
    /// Heave, metres (PASHR).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub heave: Option<f64>,
    /// Velocity north, m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vel_north: Option<f64>,
    /// Velocity east, m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vel_east: Option<f64>,
    /// Velocity up, m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vel_up: Option<f64>,
    /// Speed over ground, m/s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed: Option<f64>,
    /// Course over ground (true), degrees.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub course: Option<f64>,
    /// Standard deviations of latitude, longitude and height, metres (GST, INSPVAX, BESTPOS).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub position_sigma: Option<[f64; 3]>,
    /// Standard deviations of roll, pitch and heading, degrees (INSPVAX, PASHR).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub attitude_sigma: Option<[f64; 3]>,
    /// Fix quality as the record codes it (GGA quality, NovAtel position type, PASHR aiding).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fix: Option<u32>,
    /// INS status (NovAtel INS status, PASHR IMU status).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ins_status: Option<u32>,
    /// Satellites used.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub satellites: Option<u32>,
    /// GPS − UTC in seconds as the receiver states it (NovAtel TIME: 18 in 2017–).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gps_minus_utc: Option<f64>,
    /// Angular increments about x, y, z in the IMU frame over one IMU sample, radians
    /// (CORRIMUDATA pitch, roll, yaw; SBET angular rates x, y, z in rad/s).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub angular: Option<[f64; 3]>,
    /// Velocity increments (CORRIMUDATA lateral, longitudinal, vertical, m/s) or accelerations
    /// (SBET x, y, z, m/s²).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub linear: Option<[f64; 3]>,
    /// SBET velocities along the wander-angle frame's x, y, z, m/s, and the wander angle,
    /// degrees (the frame is rotated from north by it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub wander_velocity: Option<[f64; 4]>,
}

impl NavSample {
    /// A sample of `kind` at `time` with nothing else set.
    pub fn new(kind: NavKind, time: NavTime) -> Self {
        NavSample {
            kind,
            time,
            lat: None,
            lon: None,
            height: None,
            height_msl: None,
            roll: None,
            pitch: None,
            heading: None,
            heave: None,
            vel_north: None,
            vel_east: None,
            vel_up: None,
            speed: None,
            course: None,
            position_sigma: None,
            attitude_sigma: None,
            fix: None,
            ins_status: None,
            satellites: None,
            gps_minus_utc: None,
            angular: None,
            linear: None,
            wander_velocity: None,
        }
    }
}

/// A navigation input format, as `inspect --nav` names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NavFormat {
    /// NMEA 0183 text (PASHR attitude included).
    Nmea,
    /// NovAtel OEM binary messages.
    Novatel,
    /// Applanix SBET (17 little-endian f64 per record).
    Sbet,
}
