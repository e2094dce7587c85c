//! The text of a capture's Header record: a TOML document with the capture's own facts
//! (`[capture]`), the sensor description in force (`[sensor]`, a [`SensorProfile`]) and, for
//! simulated captures, the scene that made it (`[scene]`, kept as written).
//!
//! Unknown keys are tolerated here (unlike in configuration files): a newer fwlidar may add
//! facts to the header within the same major format version.

use serde::{Deserialize, Serialize};

use crate::core::sensor::SensorProfile;

/// The parsed Header record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaptureHeader {
    /// Facts about the recording.
    pub capture: CaptureMeta,
    /// The sensor as configured when recording.
    pub sensor: SensorProfile,
    /// The scene a simulated capture was made from, as written (absent for real flights).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<toml::Table>,
}

/// Facts about a recording.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaptureMeta {
    /// Program and version that wrote the capture, e.g. `fwlidar 0.1.0`.
    pub software: String,
    /// When recording started, seconds since the Unix epoch (host clock).
    pub created_unix_s: u64,
    /// Time base of the frames' `gps_time`: `gps_seconds_of_week` or `gps_adjusted_standard`
    /// (GPS seconds since 1980-01-06 minus 10^9, as LAS uses).
    pub time_base: String,
    /// `simulated`, `flight`, or `imported` (converted from another file format by `fwlidar
    /// import`).
    pub origin: String,
    /// Coordinate reference system of the pulses' geometry (GeoFrame records), as the source file
    /// stated it: OGC WKT, or `EPSG:<code>`. Absent when no pulse carries geometry or the file did
    /// not say.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crs: Option<String>,
    /// The file an imported capture was converted from (as given on the command line).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_file: Option<String>,
}

impl CaptureHeader {
    /// Parses a Header record's text.
    pub fn parse(text: &str) -> Result<Self, toml::de::Error> {
        toml::from_str(text)
    }

    /// The header of a simulated capture: made by this fwlidar, GPS seconds of week, no CRS,
    /// `origin` (e.g. `simulated`), the scene that made it. Its creation time is 0, not the
    /// wall clock, so the same scene and seed give identical bytes.
    pub fn simulated(sensor: &SensorProfile, scene: Option<toml::Table>, origin: &str) -> Self {
        CaptureHeader {
            capture: CaptureMeta {
                software: format!("fwlidar {}", env!("CARGO_PKG_VERSION")),
                created_unix_s: 0,
                time_base: "gps_seconds_of_week".into(),
                origin: origin.into(),
                crs: None,
                source_file: None,
            },
            sensor: sensor.clone(),
            scene,
        }
    }

    /// The header as TOML text.
    pub fn to_text(&self) -> String {
        toml::to_string(self).unwrap_or_default()
    }
}
