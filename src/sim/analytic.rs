//! The first, analytic simulator: a nadir-looking sensor over flat ground with one partially
//! covering plane above it ([`Scene`]).
//!
//! The received waveform is the sum over the two surfaces of
//! `reflectance × intercepted fraction × outgoing(t − 2R/c)` (plane: fraction `plane_cover`;
//! ground: `1 − plane_cover`), where the outgoing pulse is a unit Gaussian with the sensor's
//! FWHM. Times are relative to the pulse reference time t0 = the outgoing pulse's peak. The
//! return segment starts at the two-way time of the top of the recorded window and holds
//! `return_samples` samples at the sensor's interval; the outgoing segment holds
//! `ceil(10σ / interval)` samples centred on t0 (±5σ, so its first samples are pre-trigger
//! baseline for the denoise stage). Samples are scaled to counts
//! (`baseline_dn + peak_dn × waveform`, the outgoing pulse with `outgoing_peak_dn`), the optional
//! uniform noise is added (ChaCha8 seeded with the scene's seed, one draw per sample in segment
//! order, so the output is identical on every platform), rounded to the nearest count and
//! clipped to `0 ..= 2^bits − 1`. No range attenuation is modelled (the two surfaces are only
//! `plane_height_m` apart).

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::core::sensor::SensorProfile;
use crate::pulse::{Pulse, SegmentKind};
use crate::sim::analytic_scene::{NoiseConfig, Scene, SceneError};

/// Ratio of a Gaussian's FWHM to its standard deviation, `2 sqrt(2 ln 2)`.
pub const FWHM_PER_SIGMA: f64 = 2.354_820_045_030_949;

/// Which surface of the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SurfaceKind {
    /// The partially covering plane (canopy-like layer).
    Plane,
    /// The ground.
    Ground,
}

/// What one surface contributes to a pulse: the reference to score processing against.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceTruth {
    /// Which surface.
    pub kind: SurfaceKind,
    /// Height above the ground, metres (0 for the ground).
    pub height_m: f64,
    /// Range from the sensor, metres.
    pub range_m: f64,
    /// Two-way travel time relative to t0 (the outgoing peak), nanoseconds.
    pub two_way_ns: f64,
    /// Fraction of the footprint the surface intercepts, 0..1.
    pub fraction: f64,
    /// Reflectance, 0..1.
    pub reflectance: f64,
    /// Peak amplitude of its echo above the baseline before noise and quantisation, counts
    /// (`peak_dn × reflectance × fraction`).
    pub amplitude_dn: f64,
    /// Position of the echo's peak in the return segment, samples from its first sample
    /// (fractional).
    pub return_bin: f64,
}

/// The truth of one simulated pulse.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PulseTruth {
    /// The pulse's sequence number (and digitizer pulse id).
    pub seq: u64,
    /// Its GPS time, seconds.
    pub gps_time: f64,
    /// The plane, then the ground.
    pub surfaces: [SurfaceTruth; 2],
}

/// Generates the pulses of an analytic [`Scene`], in order.
#[derive(Clone, Debug)]
pub struct AnalyticSim {
    scene: Scene,
    sensor: SensorProfile,
    pulse_rate_hz: f64,
    sigma_ns: f64,
    outgoing_len: usize,
    outgoing_start_ns: f64,
    return_start_ns: f64,
    surfaces: [SurfaceTruth; 2],
    max_count: f64,
    rng: ChaCha8Rng,
    next_seq: u64,
}

impl AnalyticSim {
    /// A simulator for `scene` seen by `sensor` (validated here).
    pub fn new(scene: &Scene, sensor: &SensorProfile) -> Result<Self, SceneError> {
        scene.validate()?;
        // Checks the sensor fields the simulator reads (an inline copy resolves to itself).
        let sensor = Scene {
            sensor: Some(sensor.clone()),
            sensor_profile: None,
            ..Scene::default()
        }
        .resolve_sensor(std::path::Path::new("."))?;
        let dt = sensor.sample_interval_ns;
        let sigma_ns = sensor.pulse_fwhm_ns / FWHM_PER_SIGMA;
        let outgoing_len = ((10.0 * sigma_ns / dt).ceil() as usize).max(1);
        let outgoing_start_ns = -((outgoing_len / 2) as f64) * dt;
        let two_way = |range_m: f64| 2.0 * range_m / crate::core::units::C_M_PER_NS;
        let return_start_ns = two_way(scene.altitude_m - scene.window_top_m);
        let surface = |kind, height_m: f64, fraction: f64, reflectance: f64| {
            let range_m = scene.altitude_m - height_m;
            let two_way_ns = two_way(range_m);
            SurfaceTruth {
                kind,
                height_m,
                range_m,
                two_way_ns,
                fraction,
                reflectance,
                amplitude_dn: scene.peak_dn * reflectance * fraction,
                return_bin: (two_way_ns - return_start_ns) / dt,
            }
        };
        let surfaces = [
            surface(
                SurfaceKind::Plane,
                scene.plane_height_m,
                scene.plane_cover,
                scene.plane_reflectance,
            ),
            surface(
                SurfaceKind::Ground,
                0.0,
                1.0 - scene.plane_cover,
                scene.ground_reflectance,
            ),
        ];
        Ok(AnalyticSim {
            pulse_rate_hz: scene.pulse_rate_hz(&sensor),
            max_count: ((1u32 << sensor.bits_per_sample) - 1) as f64,
            rng: ChaCha8Rng::seed_from_u64(scene.seed),
            scene: scene.clone(),
            sensor,
            sigma_ns,
            outgoing_len,
            outgoing_start_ns,
            return_start_ns,
            surfaces,
            next_seq: 0,
        })
    }

    /// The scene simulated.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// The sensor simulated.
    pub fn sensor(&self) -> &SensorProfile {
        &self.sensor
    }

    /// Standard deviation of the outgoing Gaussian, nanoseconds.
    pub fn sigma_ns(&self) -> f64 {
        self.sigma_ns
    }

    /// Time of the first return sample relative to t0, nanoseconds.
    pub fn return_start_ns(&self) -> f64 {
        self.return_start_ns
    }

    /// Time of the first outgoing sample relative to t0, nanoseconds.
    pub fn outgoing_start_ns(&self) -> f64 {
        self.outgoing_start_ns
    }

    /// Number of outgoing samples.
    pub fn outgoing_len(&self) -> usize {
        self.outgoing_len
    }

    /// GPS time of pulse `seq`, seconds.
    pub fn gps_time(&self, seq: u64) -> f64 {
        self.scene.gps_time_start_s + seq as f64 / self.pulse_rate_hz
    }

    /// Number of pulses still to generate.
    pub fn remaining(&self) -> u64 {
        self.scene.pulses - self.next_seq
    }

    /// The truth of pulse `seq` (every pulse of this scene sees the same surfaces).
    pub fn truth(&self, seq: u64) -> PulseTruth {
        PulseTruth {
            seq,
            gps_time: self.gps_time(seq),
            surfaces: self.surfaces,
        }
    }

    /// The noiseless return waveform at `t_ns` relative to t0, counts above the baseline.
    pub fn return_dn(&self, t_ns: f64) -> f64 {
        self.surfaces
            .iter()
            .map(|s| s.amplitude_dn * self.unit_pulse(t_ns - s.two_way_ns))
            .sum()
    }

    /// The noiseless outgoing waveform at `t_ns` relative to t0, counts above the baseline.
    pub fn outgoing_dn(&self, t_ns: f64) -> f64 {
        self.scene.outgoing_peak_dn * self.unit_pulse(t_ns)
    }

    fn unit_pulse(&self, t_ns: f64) -> f64 {
        let z = t_ns / self.sigma_ns;
        (-0.5 * z * z).exp()
    }

    /// Digitizes `clean_dn` above the baseline: noise, rounding, clipping.
    fn digitize(&mut self, clean_dn: f64) -> u16 {
        let mut v = self.scene.baseline_dn + clean_dn;
        if let Some(NoiseConfig::Uniform { amplitude_dn }) = self.scene.noise
            && amplitude_dn > 0.0
        {
            v += self.rng.random_range(-amplitude_dn..=amplitude_dn);
        }
        v.round().clamp(0.0, self.max_count) as u16
    }

    /// Fills `pulse` (cleared first, its buffers reused) with the next pulse; `false` when the
    /// scene has no pulses left.
    pub fn fill_next(&mut self, pulse: &mut Pulse) -> bool {
        if self.next_seq >= self.scene.pulses {
            return false;
        }
        let seq = self.next_seq;
        self.next_seq += 1;
        pulse.reset();
        pulse.seq = seq;
        pulse.pulse_id = seq;
        pulse.gps_time = self.gps_time(seq);
        pulse.scan_angle_deg = [0.0, f32::NAN];
        pulse.sample_ns = self.sensor.sample_interval_ns;
        pulse.gain_v_per_dn = self.sensor.digitizer_gain_v_per_dn as f32;
        pulse.offset_v = self.sensor.digitizer_offset_v as f32;
        pulse.bits = self.sensor.bits_per_sample;
        let dt = self.sensor.sample_interval_ns;

        let first = pulse.raw.len();
        for i in 0..self.outgoing_len {
            let clean = self.outgoing_dn(self.outgoing_start_ns + i as f64 * dt);
            let c = self.digitize(clean);
            pulse.raw.push(c);
        }
        let out = pulse.push_segment(SegmentKind::Outgoing, 0, self.outgoing_start_ns, []);
        pulse.segments[out].first = first as u32;
        pulse.segments[out].len = self.outgoing_len as u32;

        let first = pulse.raw.len();
        for i in 0..self.scene.return_samples as usize {
            let clean = self.return_dn(self.return_start_ns + i as f64 * dt);
            let c = self.digitize(clean);
            pulse.raw.push(c);
        }
        let ret = pulse.push_segment(SegmentKind::Return, 0, self.return_start_ns, []);
        pulse.segments[ret].first = first as u32;
        pulse.segments[ret].len = self.scene.return_samples;
        true
    }

    /// The next pulse in a new allocation, or `None` at the end of the scene.
    pub fn next_pulse(&mut self) -> Option<Pulse> {
        let mut p = Pulse::default();
        self.fill_next(&mut p).then_some(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::sensor::test_sensor;

    fn scene(noise: Option<f64>) -> Scene {
        Scene {
            seed: 1,
            pulses: 20,
            pulse_rate_hz: Some(1000.0),
            gps_time_start_s: 100.0,
            noise: noise.map(|a| NoiseConfig::Uniform { amplitude_dn: a }),
            sensor: Some(test_sensor()),
            ..Scene::default()
        }
    }

    fn pulses(scene: &Scene) -> Vec<Pulse> {
        let mut sim = AnalyticSim::new(scene, scene.sensor.as_ref().unwrap()).unwrap();
        std::iter::from_fn(|| sim.next_pulse()).collect()
    }

    #[test]
    fn a_noiseless_scene_gives_the_analytic_waveform() {
        let s = scene(None);
        let sim = AnalyticSim::new(&s, s.sensor.as_ref().unwrap()).unwrap();
        let ps = pulses(&s);
        assert_eq!(ps.len(), 20);
        let c = crate::core::units::C_M_PER_NS;
        let sigma = 16.0 / 2.354_820_045;
        let start = 2.0 * (1000.0 - 25.0) / c;
        for (i, p) in ps.iter().enumerate() {
            assert_eq!(p.seq, i as u64);
            assert!((p.gps_time - (100.0 + i as f64 / 1000.0)).abs() < 1e-12);
            assert_eq!(p.segments.len(), 2);
            assert_eq!(p.segments[1].kind, SegmentKind::Return);
            assert!((p.segments[1].start_ns - start).abs() < 1e-9);
            // Sample by sample, from the formula written out independently.
            let ret = p.raw_of(1);
            assert_eq!(ret.len(), 225);
            for (k, &v) in ret.iter().enumerate() {
                let t = start + k as f64;
                let g = |range: f64| {
                    let z = (t - 2.0 * range / c) / sigma;
                    (-0.5 * z * z).exp()
                };
                let want =
                    (12.0 + 200.0 * (0.5 * 0.4 * g(985.0) + 0.3 * 0.6 * g(1000.0))).round() as u16;
                assert_eq!(v, want, "bin {k}");
            }
            // Outgoing: peak at t0, ~10 sigma long.
            let out = p.raw_of(0);
            assert_eq!(out.len(), (10.0 * sigma).ceil() as usize);
            let k0 = (-p.segments[0].start_ns) as usize;
            assert_eq!(out[k0], 212);
            assert_eq!(out.iter().max(), Some(&212));
        }
        // Peaks at the expected bins: 2 x 10 m / c = 66.7 ns (plane), 2 x 25 m / c = 166.8 ns.
        let ret = ps[0].raw_of(1);
        let argmax = |r: std::ops::Range<usize>| r.clone().max_by_key(|&k| ret[k]).unwrap();
        let (plane, ground) = (argmax(0..117), argmax(117..225));
        assert_eq!(plane, (20.0 / c).round() as usize);
        assert_eq!(ground, (50.0 / c).round() as usize);
        let truth = sim.truth(0);
        assert_eq!(truth.surfaces[0].return_bin.round() as usize, plane);
        assert_eq!(truth.surfaces[1].return_bin.round() as usize, ground);
        assert!((truth.surfaces[0].range_m - 985.0).abs() < 1e-12);
        assert_eq!(truth.surfaces[1].fraction, 0.6);
        // Amplitudes in the ratio (0.5 x 0.4) : (0.3 x 0.6), to within quantisation and the
        // sub-sample offset of each peak.
        let ratio = (ret[plane] as f64 - 12.0) / (ret[ground] as f64 - 12.0);
        assert!((ratio - 0.2 / 0.18).abs() < 0.02, "ratio {ratio}");
        assert!((truth.surfaces[0].amplitude_dn - 40.0).abs() < 1e-12);
        assert!((truth.surfaces[1].amplitude_dn - 36.0).abs() < 1e-12);
    }

    #[test]
    fn the_same_seed_repeats_and_another_seed_differs() {
        let a = pulses(&scene(Some(3.0)));
        let b = pulses(&scene(Some(3.0)));
        assert!(a.iter().zip(&b).all(|(x, y)| x.raw == y.raw));
        let mut other = scene(Some(3.0));
        other.seed = 2;
        let c = pulses(&other);
        assert!(a.iter().zip(&c).any(|(x, y)| x.raw != y.raw));
        // Pulses within one run differ from each other (the stream is not reseeded).
        assert_ne!(a[0].raw, a[1].raw);
        // Fixed values pin the generator across platforms and crate updates.
        assert_eq!(
            &a[0].raw_of(1)[..12],
            &[11, 11, 13, 11, 14, 13, 10, 13, 11, 11, 15, 12]
        );
        let sum: u64 = a.iter().flat_map(|p| p.raw.iter()).map(|&v| v as u64).sum();
        let clean: u64 = pulses(&scene(None))
            .iter()
            .flat_map(|p| p.raw.iter())
            .map(|&v| v as u64)
            .sum();
        assert!(
            sum.abs_diff(clean) < 500,
            "noise is zero-mean: {sum} vs {clean}"
        );
    }

    #[test]
    fn noise_stays_within_its_amplitude() {
        let s = scene(Some(3.0));
        let sim = AnalyticSim::new(&s, s.sensor.as_ref().unwrap()).unwrap();
        let (mut lo, mut hi) = (0.0f64, 0.0f64);
        for p in pulses(&s) {
            for (k, &v) in p.raw_of(1).iter().enumerate() {
                let clean = 12.0 + sim.return_dn(sim.return_start_ns() + k as f64);
                let d = v as f64 - clean;
                assert!(d.abs() <= 3.5, "bin {k}: {v} vs {clean}");
                lo = lo.min(d);
                hi = hi.max(d);
            }
        }
        assert!(lo < -2.5 && hi > 2.5, "noise spans its range: {lo}..{hi}");
    }

    #[test]
    fn samples_clip_at_the_digitizer_range() {
        let mut s = scene(Some(3.0));
        s.peak_dn = 2000.0;
        s.outgoing_peak_dn = 1000.0;
        s.baseline_dn = 1.0;
        let ps = pulses(&s);
        assert_eq!(ps[0].bits, 8);
        assert!(ps.iter().all(|p| p.raw.iter().all(|&v| v <= 255)));
        assert!(ps[0].raw_of(0).contains(&255) && ps[0].raw_of(1).contains(&255));
        assert!(
            ps[0].raw.contains(&0),
            "noise below a 1 DN baseline clips at 0"
        );
        let mut sensor = test_sensor();
        sensor.bits_per_sample = 16;
        s.sensor = Some(sensor);
        s.peak_dn = 1e6;
        let ps = pulses(&s);
        assert_eq!(ps[0].raw.iter().max(), Some(&65535));
    }
}
