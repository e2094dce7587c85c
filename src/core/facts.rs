//! What an input states about itself: its sensor, time base, coordinates and time origin. Read
//! from a file's header by the source that opens it; used by stages and sinks that depend on it
//! (calibration, LAS output CRS) and written into captures by `fwlidar import`.

/// What an input file states about itself (a source's `facts`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SourceFacts {
    /// A complete sensor description, when the file holds one (a capture header; a PulseWaves
    /// scanner record with wavelength, pulse width, rate and divergence).
    pub sensor: Option<crate::core::sensor::SensorProfile>,
    /// Time base of the pulses' `gps_time`: `gps_seconds_of_week` or `gps_adjusted_standard`.
    pub time_base: Option<String>,
    /// Coordinate reference system of the pulses' geometry: OGC WKT or `EPSG:<code>`.
    pub crs: Option<String>,
    /// Whether the pulses' reference time t0 is the emission of the shot (so that a bin `t` ns
    /// after t0 lies `t · c / (2 n)` from the sensor): true for digitizer frames recorded or
    /// simulated by fwlidar (t0 = the outgoing pulse's peak), false for LAS (t0 = the first
    /// digitised sample), PulseWaves (t0 = the anchor, anywhere on the beam) and imported
    /// captures; `None` when the input does not say. Read by the `calibrate` stage for pulses
    /// without an outgoing segment (`docs/calibration.md`).
    pub t0_is_emission: Option<bool>,
}
