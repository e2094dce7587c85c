//! The simulator: synthetic pulses and navigation messages from a described scene, with the
//! truth to score processing against.
//!
//! - [`analytic_scene`]: the analytic scene's `[scene]` configuration (TOML) and its
//!   validation;
//! - [`analytic`]: the first scene generator, analytic nadir waveforms of flat ground under one
//!   partially covering plane;
//! - [`nmea_writer`]: NMEA 0183 GGA/PASHR sentences for a straight flight line (the reading side
//!   is `nav::nmea`);
//! - [`world`]: described scenes (terrain, trees, grass, buildings, flight plan, scan pattern,
//!   effects) and their simulator;
//! - [`truth`]: seeded truth cross-sections (sparse surfaces, canopy layers) with their 2 ns
//!   truth waveforms and noisy received waveforms, for scoring the signal chain.
//!
//! [`SimItems`] interleaves the two streams in time order, as a capture would hold them.

pub mod analytic;
pub mod analytic_scene;
pub mod capture_items;
pub mod live;
pub mod navstream;
pub mod nmea_writer;
pub mod truth;
pub mod world;

pub use analytic::{AnalyticSim, PulseTruth, SurfaceKind, SurfaceTruth};
pub use analytic_scene::{FlightConfig, NoiseConfig, Scene, SceneError, SceneFile};

use crate::core::sensor::SensorProfile;
use crate::pulse::Pulse;
use nmea_writer::FlightLine;

/// One item of the simulated stream.
// Nearly every item is a pulse (a navigation epoch comes once per thousands of pulses), so the
// enum's size is the pulse's either way; boxing it would add an allocation per simulated pulse.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum SimItem {
    /// A digitized pulse (its `gps_time` is its emission time).
    Pulse(Pulse),
    /// Bytes from the navigation receiver (serial port 0): one GGA and one PASHR sentence, and a
    /// ZDA on whole UTC seconds.
    Nav {
        /// When the bytes arrived: the epoch's GPS time in nanoseconds (same time base as the
        /// pulses' `gps_time`, seconds × 1e9, rounded).
        receive_time_ns: u64,
        /// The sentences, CR LF terminated.
        bytes: Vec<u8>,
    },
}

/// The simulated stream of a scene in time order: navigation epochs at `nav_rate_hz` from the
/// first pulse's time until one epoch at or after the last pulse (so a trajectory brackets every
/// pulse), interleaved with the pulses; an epoch at the same time as a pulse comes first.
#[derive(Debug)]
pub struct SimItems {
    sim: AnalyticSim,
    flight: FlightLine,
    next_nav: u64,
    nav_epochs: u64,
}

impl SimItems {
    /// The stream of `scene` seen by `sensor`.
    pub fn new(scene: &Scene, sensor: &SensorProfile) -> Result<Self, SceneError> {
        let sim = AnalyticSim::new(scene, sensor)?;
        let nav_epochs = if scene.pulses == 0 {
            0
        } else {
            let span_s = sim.gps_time(scene.pulses - 1) - scene.gps_time_start_s;
            (span_s * scene.flight.nav_rate_hz - 1e-9).ceil().max(0.0) as u64 + 1
        };
        Ok(SimItems {
            flight: FlightLine::new(&scene.flight, scene.gps_time_start_s, scene.altitude_m),
            sim,
            next_nav: 0,
            nav_epochs,
        })
    }

    /// The pulse generator (for the truth: [`AnalyticSim::truth`]).
    pub fn sim(&self) -> &AnalyticSim {
        &self.sim
    }

    /// The flight line the navigation messages describe.
    pub fn flight(&self) -> &FlightLine {
        &self.flight
    }

    fn nav_time(&self, j: u64) -> f64 {
        let s = self.sim.scene();
        s.gps_time_start_s + j as f64 / s.flight.nav_rate_hz
    }
}

impl Iterator for SimItems {
    type Item = SimItem;

    fn next(&mut self) -> Option<SimItem> {
        let pulse_time = (self.sim.remaining() > 0).then(|| {
            self.sim
                .gps_time(self.sim.scene().pulses - self.sim.remaining())
        });
        let nav_time = (self.next_nav < self.nav_epochs).then(|| self.nav_time(self.next_nav));
        match (nav_time, pulse_time) {
            (Some(tn), tp) if tp.is_none_or(|tp| tn <= tp) => {
                self.next_nav += 1;
                Some(SimItem::Nav {
                    receive_time_ns: (tn * 1e9).round() as u64,
                    bytes: self.flight.epoch_bytes(tn),
                })
            }
            (_, Some(_)) => self.sim.next_pulse().map(SimItem::Pulse),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::sensor::test_sensor;

    #[test]
    fn items_come_in_time_order_and_navigation_brackets_the_pulses() {
        let scene = Scene {
            pulses: 250,
            pulse_rate_hz: Some(1000.0),
            gps_time_start_s: 5000.0,
            sensor: Some(test_sensor()),
            ..Scene::default()
        };
        let items = SimItems::new(&scene, &test_sensor()).unwrap();
        let mut last_ns = 0u64;
        let (mut n_pulses, mut nav_times) = (0, Vec::new());
        for item in items {
            let t = match &item {
                SimItem::Pulse(p) => {
                    assert_eq!(p.seq, n_pulses);
                    n_pulses += 1;
                    (p.gps_time * 1e9).round() as u64
                }
                SimItem::Nav {
                    receive_time_ns,
                    bytes,
                } => {
                    let text = std::str::from_utf8(bytes).unwrap();
                    let lines: Vec<&str> = text.split_inclusive("\r\n").collect();
                    // GGA, PASHR, and a ZDA on whole UTC seconds.
                    assert!(lines.len() == 2 || lines.len() == 3, "{lines:?}");
                    assert!(lines[0].starts_with("$GPGGA") && lines[1].starts_with("$PASHR"));
                    assert!(lines.get(2).is_none_or(|l| l.starts_with("$GPZDA")));
                    assert!(lines.iter().all(|l| nmea_writer::checksum_ok(l)));
                    nav_times.push(*receive_time_ns);
                    *receive_time_ns
                }
            };
            assert!(t >= last_ns, "out of order");
            last_ns = t;
        }
        assert_eq!(n_pulses, 250);
        // 0.249 s of pulses at 10 Hz: epochs at 0.0, 0.1, 0.2 and 0.3 s.
        assert_eq!(
            nav_times,
            vec![
                5_000_000_000_000,
                5_000_100_000_000,
                5_000_200_000_000,
                5_000_300_000_000
            ]
        );
        let empty = Scene { pulses: 0, ..scene };
        assert_eq!(SimItems::new(&empty, &test_sensor()).unwrap().count(), 0);
    }
}
