//! The scene simulator: waveforms, navigation and truth from a described scene
//! ([`scene::WorldScene`]), simulating only the effects the scene lists.
//!
//! Per pulse: the flight plan and scan pattern give the shot ([`flight`]); the beam (its axis,
//! or sub-rays across the footprint with the `footprint` effect) is traced through the scene
//! ([`geometry`]); every solid hit becomes an echo of amplitude
//! `peak_dn · w · ρ · cos i · T · (R_ref / R)²` (`w` the sub-ray's share of the pulse energy,
//! `T` the fraction that crossed the media before it) at two-way time `2 R n / c`, and every
//! stretch of leaves intercepts `T_in − T_out` of the beam (Beer-Lambert, the hot-spot
//! assumption: the return retraces the gaps it came through), integrated in quarter-sample
//! bins. The received waveform is that cross-section convolved with the outgoing pulse and the
//! receiver response (Gaussians: `σ² = σ_out² + σ_rx²`, area preserved); the truth is the same
//! cross-section with a 2 ns pulse (the seed's truth), also area preserving. Then, only when
//! named: ringing, timing jitter, noise, quantisation, saturation, packet loss.
//!
//! Without `quantisation` the digitizer has `2^(14 − bits)` steps per count (at least 1) and
//! without `saturation` 4× the sensor's range, so that the samples are the analytic waveform to
//! within 1/512 count for sensors of up to 14 bits (the pulse records the finer gain).

pub mod flight;
pub mod geometry;
pub mod render;
pub mod scene;

use std::path::Path;

use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::core::sensor::SensorProfile;
use crate::pulse::{Pulse, SegmentKind};
use crate::sim::SimItem;
use crate::sim::analytic::FWHM_PER_SIGMA;
use crate::sim::analytic_scene::SceneError;
use crate::sim::navstream::NavStream;
use crate::sim::nmea_writer::NavFix;

use flight::{FlightPlan, Shot, footprint_rays};
use geometry::{Hit, MediumSpan, ObjectKind, TraceScratch, V3};
use render::{EchoShape, add_gaussian, add_ringing};
use scene::{Effect, Noise, PulseShape, Ringing, WorldScene};

/// Quarter-sample bins for media.
const FINE: usize = 4;

/// One thing a pulse met: the truth to score against.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scatterer {
    /// What it is.
    pub kind: ObjectKind,
    /// Index of the object (tree, grass patch, box, roof) in the scene file.
    pub object: u32,
    /// Range from the scanner where it starts, metres.
    pub range_m: f64,
    /// Range where it ends (media; = `range_m` for surfaces), metres.
    pub range_end_m: f64,
    /// Where it starts, scene frame, metres.
    pub position: V3,
    /// Fraction of the pulse's energy it intercepted (0..1).
    pub fraction: f64,
    /// Reflectance.
    pub reflectance: f64,
    /// Echo amplitude it contributes (surfaces: peak above the baseline with an ideal
    /// receiver; media: the sum over the stretch), counts.
    pub amplitude_dn: f64,
    /// The sub-ray that met it (0: the beam's axis; others with the `footprint` effect).
    pub ray: u32,
}

/// The truth of one pulse.
#[derive(Clone, Debug, Default)]
pub struct ShotTruth {
    /// Sequence number.
    pub seq: u64,
    /// GPS time, seconds.
    pub gps_time: f64,
    /// Lost by the `packet_loss` effect (not in the capture).
    pub lost: bool,
    /// The emission came this much after the recorded t0 (`timing_jitter`), ns.
    pub jitter_ns: f64,
    /// Scanner origin and unit beam, scene frame.
    pub origin: V3,
    /// Unit beam direction, scene frame.
    pub beam: V3,
    /// Scan angles recorded, degrees.
    pub scan_deg: [f64; 2],
    /// Time of the first return sample after t0, ns.
    pub return_start_ns: f64,
    /// Everything met, in the order traced (sub-ray by sub-ray).
    pub scatterers: Vec<Scatterer>,
    /// The truth waveform (2 ns pulse, area preserving), counts above the baseline at the
    /// sensor's gain, one value per return sample.
    pub truth: Vec<f64>,
    /// The noiseless received waveform before digitizing, counts above the baseline.
    pub clean: Vec<f64>,
}

/// Generates the pulses of a described scene, in order.
#[derive(Debug)]
pub struct WorldSim {
    scene: WorldScene,
    sensor: SensorProfile,
    geo: geometry::Scene,
    plan: FlightPlan,
    metres_per_ns: f64,
    dt: f64,
    sigma_out: f64,
    sigma_rx: f64,
    /// The received echo of a unit point target.
    echo: EchoShape,
    /// Area of the outgoing pulse (peak 1), ns.
    outgoing_area_ns: f64,
    sigma_truth: f64,
    outgoing_len: usize,
    outgoing_start_ns: f64,
    /// Steps per sensor count in the recorded samples.
    steps_per_count: f64,
    max_raw: f64,
    bits: u8,
    noise: Normals,
    /// The noise to add: the scene's `[noise]` when it names the `noise` effect.
    noise_model: Option<Noise>,
    jitter_rng: ChaCha8Rng,
    loss_rng: ChaCha8Rng,
    next: u64,
    scratch: TraceScratch,
    rays: Vec<(V3, f64)>,
    fine: Vec<f64>,
    kernels: Kernels,
    outgoing: Vec<f64>,
}

fn rng(seed: u64, stream: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// A uniform draw in [0, 1) from the generator's next 53 bits.
#[inline]
fn unit(rng: &mut ChaCha8Rng) -> f64 {
    (rng.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// A standard normal draw (Box-Muller, one of the pair).
pub fn normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1 = 1.0 - unit(rng);
    let u2 = unit(rng);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// The standard normal quantile function Φ⁻¹(p) for 0 < p < 1, by P. J. Acklam's rational
/// approximation (relative error below 1.2e-9): a rational function of `p − ½` in the centre,
/// of `sqrt(−2 ln p)` in the tails.
pub fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    const LOW: f64 = 0.024_25;
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < LOW {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - LOW {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// Standard normal draws for the per-sample noise: the quantile function of a uniform draw
/// (one generator call and a rational function a sample, no logarithm in 95 % of draws).
#[derive(Debug)]
struct Normals {
    rng: ChaCha8Rng,
}

impl Normals {
    #[inline]
    fn next(&mut self) -> f64 {
        // (k + ½) / 2^53: strictly inside (0, 1).
        let u = ((self.rng.next_u64() >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64);
        normal_quantile(u)
    }
}

/// A Poisson draw of mean `lambda` (exact below 30, normal approximation above).
fn poisson(rng: &mut ChaCha8Rng, lambda: f64) -> f64 {
    if lambda <= 0.0 {
        return 0.0;
    }
    if lambda < 30.0 {
        let l = (-lambda).exp();
        let (mut k, mut p) = (0.0, 1.0);
        loop {
            p *= unit(rng);
            if p <= l {
                return k;
            }
            k += 1.0;
        }
    }
    (lambda + lambda.sqrt() * normal(rng)).round().max(0.0)
}

impl WorldSim {
    /// A simulator for `scene` (its relative paths from `base_dir`) seen by `sensor`.
    pub fn new(
        scene: &WorldScene,
        sensor: &SensorProfile,
        base_dir: &Path,
    ) -> Result<Self, SceneError> {
        scene.validate(sensor)?;
        let geo = geometry::Scene::build(scene, base_dir)?;
        let plan = FlightPlan::new(scene, sensor, |x, y| geo.ground_height(x, y));
        let dt = sensor.sample_interval_ns;
        let fwhm = scene
            .sensor
            .outgoing_fwhm_ns
            .unwrap_or(sensor.pulse_fwhm_ns);
        let sigma_out = fwhm / FWHM_PER_SIGMA;
        let sigma_rx = scene.sensor.receiver_fwhm_ns / FWHM_PER_SIGMA;
        let sigma_k = (sigma_out * sigma_out + sigma_rx * sigma_rx).sqrt();
        let (echo, outgoing_area_ns, reach) = match &scene.sensor.pulse_shape {
            PulseShape::Gaussian => (
                EchoShape::Gaussian {
                    sigma: sigma_k,
                    gain: sigma_out / sigma_k,
                },
                sigma_out * (2.0 * std::f64::consts::PI).sqrt(),
                5.0 * sigma_out,
            ),
            PulseShape::Bigaussian { rise_ns, fall_ns } => {
                let (sr, sf) = (
                    rise_ns * 2.0 / FWHM_PER_SIGMA,
                    fall_ns * 2.0 / FWHM_PER_SIGMA,
                );
                let shape = move |t: f64| {
                    let z = if t < 0.0 { t / sr } else { t / sf };
                    if z.abs() <= 7.0 {
                        (-0.5 * z * z).exp()
                    } else {
                        0.0
                    }
                };
                (
                    EchoShape::tabulate(shape, (-7.0 * sr, 7.0 * sf), sigma_rx, dt / 64.0),
                    (sr + sf) / 2.0 * (2.0 * std::f64::consts::PI).sqrt(),
                    5.0 * sr.max(sf),
                )
            }
            PulseShape::Measured { samples, sample_ns } => {
                let (k, peak) = samples
                    .iter()
                    .enumerate()
                    .fold((0, f64::MIN), |m, (i, &v)| if v > m.1 { (i, v) } else { m });
                let norm: Vec<f64> = samples.iter().map(|v| v / peak).collect();
                let step = *sample_ns;
                let first = -(k as f64) * step;
                let last = first + (norm.len() - 1) as f64 * step;
                let shape = move |t: f64| {
                    let f = (t - first) / step;
                    if !(f >= 0.0 && f <= (norm.len() - 1) as f64) {
                        return 0.0;
                    }
                    let i = (f as usize).min(norm.len() - 2);
                    let w = f - i as f64;
                    norm[i] * (1.0 - w) + norm[i + 1] * w
                };
                let area = samples.iter().sum::<f64>() / peak * step;
                (
                    EchoShape::tabulate(shape, (first, last), sigma_rx, dt / 64.0),
                    area,
                    first.abs().max(last),
                )
            }
        };
        let outgoing_len = ((2.0 * reach / dt).ceil() as usize).max(1);
        let bits = sensor.bits_per_sample;
        let steps_per_count = if scene.has(Effect::Quantisation) {
            1.0
        } else {
            2f64.powi((14 - bits.min(14) as i32).max(0))
        };
        let full = ((1u64 << bits) - 1) as f64;
        let max_raw = if scene.has(Effect::Saturation) {
            full * steps_per_count
        } else {
            65_535.0
        };
        Ok(WorldSim {
            metres_per_ns: crate::core::units::half_c_in_m_per_ns(scene.sensor.refractive_index),
            dt,
            sigma_out,
            sigma_rx,
            outgoing_area_ns,
            sigma_truth: 2.0 / FWHM_PER_SIGMA,
            outgoing_len,
            outgoing_start_ns: -((outgoing_len / 2) as f64) * dt,
            steps_per_count,
            max_raw,
            bits: if steps_per_count == 1.0 && scene.has(Effect::Saturation) {
                bits
            } else {
                16
            },
            noise_model: if scene.has(Effect::Noise) {
                scene.noise.clone()
            } else {
                None
            },
            noise: Normals {
                rng: rng(scene.seed, 1),
            },
            jitter_rng: rng(scene.seed, 2),
            loss_rng: rng(scene.seed, 3),
            next: 0,
            scratch: TraceScratch::default(),
            rays: Vec::new(),
            fine: Vec::new(),
            kernels: Kernels {
                clean: PhaseKernel::from_shape(&echo, dt),
                truth: PhaseKernel::from_shape(
                    &EchoShape::Gaussian {
                        sigma: 2.0 / FWHM_PER_SIGMA,
                        gain: 1.0,
                    },
                    dt,
                ),
            },
            outgoing: Vec::new(),
            echo,
            geo,
            plan,
            scene: scene.clone(),
            sensor: sensor.clone(),
        })
    }

    /// The scene.
    pub fn scene(&self) -> &WorldScene {
        &self.scene
    }

    /// The sensor.
    pub fn sensor(&self) -> &SensorProfile {
        &self.sensor
    }

    /// The flight plan.
    pub fn plan(&self) -> &FlightPlan {
        &self.plan
    }

    /// The traced geometry.
    pub fn geometry(&self) -> &geometry::Scene {
        &self.geo
    }

    /// Metres of range per nanosecond of two-way time.
    pub fn metres_per_ns(&self) -> f64 {
        self.metres_per_ns
    }

    /// Standard deviation of the received echo of a point target, ns.
    pub fn echo_sigma_ns(&self) -> f64 {
        (self.sigma_out * self.sigma_out + self.sigma_rx * self.sigma_rx).sqrt()
    }

    /// Pulses still to generate.
    pub fn remaining(&self) -> u64 {
        self.plan.pulses() - self.next
    }

    /// Fills `pulse` and `truth` with the next pulse; `None` at the end, `Some(false)` when the
    /// pulse was lost (`packet_loss`: not to be recorded).
    pub fn fill_next(&mut self, pulse: &mut Pulse, truth: &mut ShotTruth) -> Option<bool> {
        if self.next >= self.plan.pulses() {
            return None;
        }
        let k = self.next;
        self.next += 1;
        let shot = self.plan.shot(k);
        let jitter = if self.scene.has(Effect::TimingJitter) {
            self.scene.timing_jitter_ns * normal(&mut self.jitter_rng)
        } else {
            0.0
        };
        let lost = self.scene.has(Effect::PacketLoss)
            && self.loss_rng.random_range(0.0..1.0f64) < self.scene.packet_loss;
        self.render(k, &shot, jitter, pulse, truth);
        truth.lost = lost;
        Some(!lost)
    }

    fn window_start_ns(&self, shot: &Shot) -> f64 {
        let top = self.scene.sensor.window_top_m;
        let down = (-shot.beam[2]).max(1e-6);
        let s_ground = self
            .geo
            .ground_hit(shot.origin, shot.beam)
            .map(|(s, _)| s)
            .unwrap_or(shot.origin[2] / down);
        let t = (s_ground - top / down) / self.metres_per_ns;
        (t / self.dt).round() * self.dt
    }

    fn render(
        &mut self,
        k: u64,
        shot: &Shot,
        jitter: f64,
        pulse: &mut Pulse,
        truth: &mut ShotTruth,
    ) {
        let frame = self.begin_pulse(k, shot, jitter, truth);
        self.set_rays(shot);
        for ri in 0..self.rays.len() {
            self.render_ray(ri, shot, &frame, truth);
        }
        self.spread_media_bins(&frame, truth);
        self.write_pulse(k, shot, &frame, pulse, truth);
    }

    /// Starts pulse `k`: its window and fine bins (cleared), and `truth`'s header with its
    /// waveforms zeroed over the window.
    fn begin_pulse(&mut self, k: u64, shot: &Shot, jitter: f64, truth: &mut ShotTruth) -> Frame {
        let s = &self.scene;
        let n = s.sensor.return_samples as usize;
        let dt = self.dt;
        let start = self.window_start_ns(shot);
        truth.seq = k;
        truth.gps_time = shot.gps_time;
        truth.jitter_ns = jitter;
        truth.origin = shot.origin;
        truth.beam = shot.beam;
        truth.scan_deg = shot.scan_deg;
        truth.return_start_ns = start;
        truth.scatterers.clear();
        truth.clean.clear();
        truth.clean.resize(n, 0.0);
        truth.truth.clear();
        truth.truth.resize(n, 0.0);
        let sigma_k = self.echo_sigma_ns();
        // Area preserving: the truth's 2 ns pulse carries the outgoing pulse's energy.
        let gain_t =
            self.outgoing_area_ns / (self.sigma_truth * (2.0 * std::f64::consts::PI).sqrt());
        let ringing = s.has(Effect::Ringing).then(|| s.ringing.clone());
        // Fine bins over the window and a margin of 6σ each side.
        let margin = (self.echo.reach().max(6.0 * sigma_k) / dt).ceil() as usize + 1;
        let fine_t0 = start - margin as f64 * dt;
        let fine_n = (n + 2 * margin) * FINE;
        let delta = dt / FINE as f64;
        let frame = Frame {
            n,
            start,
            jitter,
            gain_t,
            ringing,
            margin,
            fine_t0,
            fine_n,
            delta,
            peak: s.sensor.peak_dn,
            r_ref: s.sensor.reference_range_m,
            mpn: self.metres_per_ns,
        };
        self.fine.clear();
        self.fine.resize(fine_n, 0.0);
        frame
    }

    /// The sub-rays of `shot` and their shares of the pulse's energy: across the footprint
    /// with the `footprint` effect, else the beam's axis alone.
    fn set_rays(&mut self, shot: &Shot) {
        let s = &self.scene;
        if s.has(Effect::Footprint) {
            footprint_rays(
                shot.beam,
                self.sensor.beam_divergence_mrad * 1e-3,
                s.footprint_rings,
                &mut self.rays,
            );
        } else {
            self.rays.clear();
            self.rays.push((shot.beam, 1.0));
        }
    }

    /// Traces sub-ray `ri`: the media it crosses go to the fine bins and its first solid hit
    /// to the waveforms, both to the truth's scatterers.
    #[inline]
    fn render_ray(&mut self, ri: usize, shot: &Shot, frame: &Frame, truth: &mut ShotTruth) {
        let (d, w) = self.rays[ri];
        self.geo.trace(shot.origin, d, &mut self.scratch);
        let stop = self
            .scratch
            .hits
            .first()
            .map_or(f64::INFINITY, |h| h.range_m);
        let ray = Ray {
            origin: shot.origin,
            d,
            w,
            index: ri as u32,
        };
        let media = &self.scratch.media;
        let trans = if media.is_empty() {
            1.0f64
        } else {
            deposit_media(
                media,
                stop,
                &ray,
                frame,
                &mut self.fine,
                &mut truth.scatterers,
            )
        };
        if let Some(&h) = self.scratch.hits.first() {
            self.add_surface_echo(&h, trans, &ray, frame, truth);
        }
    }

    /// The echo of solid hit `h` of `ray`, reached with transmission `trans` (0..1): a
    /// scatterer, the received echo (delayed by the jitter, with its ringing) and the
    /// truth's 2 ns pulse.
    #[inline]
    fn add_surface_echo(
        &self,
        h: &Hit,
        trans: f64,
        ray: &Ray,
        frame: &Frame,
        truth: &mut ShotTruth,
    ) {
        let (start, dt, jitter) = (frame.start, self.dt, frame.jitter);
        let amp = frame.peak
            * ray.w
            * h.reflectance
            * h.cos_incidence
            * trans
            * (frame.r_ref / h.range_m).powi(2);
        let t = h.range_m / frame.mpn;
        truth.scatterers.push(Scatterer {
            kind: h.kind,
            object: h.object,
            range_m: h.range_m,
            range_end_m: h.range_m,
            position: at(ray.origin, h.range_m, ray.d),
            fraction: ray.w * trans,
            reflectance: h.reflectance,
            amplitude_dn: amp,
            ray: ray.index,
        });
        self.echo.add(&mut truth.clean, start, dt, t + jitter, amp);
        add_gaussian(
            &mut truth.truth,
            start,
            dt,
            t,
            amp * frame.gain_t,
            self.sigma_truth,
        );
        if let Some(r) = &frame.ringing {
            add_ringing(&mut truth.clean, start, dt, t + jitter, amp, r);
        }
    }

    /// The media's fine bins onto the waveforms: from the per-phase kernel tables (no
    /// exponential per bin), or one by one when jitter or ringing move or add to them.
    fn spread_media_bins(&self, frame: &Frame, truth: &mut ShotTruth) {
        let (start, dt, jitter, margin) = (frame.start, self.dt, frame.jitter, frame.margin);
        let exact = jitter != 0.0 || frame.ringing.is_some();
        let fine = &self.fine[..frame.fine_n];
        // Most bins are empty: each non-empty one is found by a scan of its own, which keeps
        // the bin's work (and anything the optimiser would hoist from it) off the empty ones.
        let mut f = 0;
        while let Some(k) = fine[f..].iter().position(|&a| a != 0.0) {
            f += k;
            let amp = fine[f];
            let (q, phase) = (f / FINE, f % FINE);
            // Sample i lies (i + margin − q)·dt − (phase + ½)·δ after the bin's centre.
            self.kernels
                .truth
                .add(&mut truth.truth, margin, q, phase, amp * frame.gain_t);
            if exact {
                let t = frame.fine_t0 + (f as f64 + 0.5) * frame.delta + jitter;
                self.echo.add(&mut truth.clean, start, dt, t, amp);
                if let Some(r) = &frame.ringing {
                    add_ringing(&mut truth.clean, start, dt, t, amp, r);
                }
            } else {
                self.kernels
                    .clean
                    .add(&mut truth.clean, margin, q, phase, amp);
            }
            f += 1;
        }
    }

    /// The recorded pulse: its header, the digitized outgoing pulse (delayed by the jitter)
    /// and the digitized return window of `truth.clean`.
    fn write_pulse(
        &mut self,
        k: u64,
        shot: &Shot,
        frame: &Frame,
        pulse: &mut Pulse,
        truth: &ShotTruth,
    ) {
        let (dt, jitter, n) = (self.dt, frame.jitter, frame.n);
        pulse.reset();
        pulse.seq = k;
        pulse.pulse_id = k;
        pulse.gps_time = shot.gps_time;
        pulse.scan_angle_deg = [shot.scan_deg[0] as f32, shot.scan_deg[1] as f32];
        pulse.sample_ns = dt;
        pulse.gain_v_per_dn = (self.sensor.digitizer_gain_v_per_dn / self.steps_per_count) as f32;
        pulse.offset_v = self.sensor.digitizer_offset_v as f32;
        pulse.bits = self.bits;
        let first = pulse.raw.len();
        let out_peak = self.scene.sensor.outgoing_peak_dn;
        if self.outgoing.len() != self.outgoing_len {
            self.outgoing = (0..self.outgoing_len)
                .map(|i| out_peak * self.echo.value(self.outgoing_start_ns + i as f64 * dt))
                .collect();
        }
        for i in 0..self.outgoing_len {
            let clean = if jitter == 0.0 {
                self.outgoing[i]
            } else {
                out_peak
                    * self
                        .echo
                        .value(self.outgoing_start_ns + i as f64 * dt - jitter)
            };
            let raw = self.digitize(clean);
            pulse.raw.push(raw);
        }
        let out = pulse.push_segment(SegmentKind::Outgoing, 0, self.outgoing_start_ns, []);
        pulse.segments[out].first = first as u32;
        pulse.segments[out].len = self.outgoing_len as u32;
        let first = pulse.raw.len();
        for i in 0..n {
            let raw = self.digitize(truth.clean[i]);
            pulse.raw.push(raw);
        }
        let ret = pulse.push_segment(SegmentKind::Return, 0, frame.start, []);
        pulse.segments[ret].first = first as u32;
        pulse.segments[ret].len = n as u32;
    }

    /// Noise, quantisation and saturation of one sample `clean` counts above the baseline.
    fn digitize(&mut self, clean: f64) -> u16 {
        let baseline = self.scene.sensor.baseline_dn;
        let mut v = baseline + clean;
        match self.noise_model {
            Some(Noise::Uniform { amplitude_dn }) if amplitude_dn > 0.0 => {
                v += amplitude_dn * (2.0 * unit(&mut self.noise.rng) - 1.0)
            }
            Some(Noise::Gaussian { sigma_dn }) => v += sigma_dn * self.noise.next(),
            Some(Noise::Poisson {
                photons_per_dn,
                dark_sigma_dn,
            }) => {
                let photons = poisson(&mut self.noise.rng, clean.max(0.0) * photons_per_dn);
                v = baseline + photons / photons_per_dn + dark_sigma_dn * self.noise.next();
            }
            _ => {}
        }
        // Round half to even by the 1.5·2^52 trick (exact for |x| < 2^51; x is clamped to
        // 0..=65535 first), a few instructions instead of a libm call.
        const ROUND: f64 = 6_755_399_441_055_744.0;
        let x = (v * self.steps_per_count).clamp(0.0, self.max_raw);
        ((x + ROUND) - ROUND) as u16
    }
}

/// What the steps of rendering one pulse share: its window, the fine bins of the media and
/// the constants of the echo amplitude.
#[derive(Debug)]
struct Frame {
    /// Return samples.
    n: usize,
    /// Time of the first return sample after t0, ns.
    start: f64,
    /// The emission came this much after the recorded t0, ns.
    jitter: f64,
    /// Gain of the truth's 2 ns pulse (area preserving).
    gain_t: f64,
    /// The ringing to add, with the `ringing` effect.
    ringing: Option<Ringing>,
    /// Samples of fine bins before (and after) the window.
    margin: usize,
    /// Time of the first fine bin's start after t0, ns.
    fine_t0: f64,
    /// Fine bins.
    fine_n: usize,
    /// Width of a fine bin, ns.
    delta: f64,
    /// Echo amplitude of a unit reflector at the reference range, counts.
    peak: f64,
    /// The reference range, metres.
    r_ref: f64,
    /// Metres of range per nanosecond of two-way time.
    mpn: f64,
}

/// One sub-ray of a pulse.
#[derive(Clone, Copy, Debug)]
struct Ray {
    /// Scanner origin, scene frame, metres.
    origin: V3,
    /// Unit direction.
    d: V3,
    /// Share of the pulse's energy (0..1).
    w: f64,
    /// Number of the sub-ray (0: the beam's axis).
    index: u32,
}

/// A stretch `a..b` (range, metres) of one or more media along a ray.
#[derive(Clone, Copy, Debug)]
struct Stretch {
    /// Range where it starts, metres.
    a: f64,
    /// Range where it ends, metres.
    b: f64,
    /// Transmission where it starts (0..1).
    t_a: f64,
    /// Extinction of the media active in it, per metre.
    k_tot: f64,
    /// Their mean reflectance, weighted by extinction.
    rho: f64,
}

impl Stretch {
    /// Transmission at range `r` (metres) inside the stretch.
    #[inline]
    fn transmission_at(&self, r: f64) -> f64 {
        self.t_a * (-self.k_tot * (r - self.a)).exp()
    }
}

/// Walks the breakpoints of the `media` (the first 8) `ray` crosses before `stop_m` (range of
/// its first solid hit, metres): in each stretch the active media share the extinction, the
/// energy they intercept goes to the `fine` bins and one scatterer per medium to
/// `scatterers`. Returns the transmission (0..1) past the last stretch.
#[inline]
fn deposit_media(
    media: &[MediumSpan],
    stop_m: f64,
    ray: &Ray,
    frame: &Frame,
    fine: &mut [f64],
    scatterers: &mut Vec<Scatterer>,
) -> f64 {
    let mut trans = 1.0f64;
    let mut cuts = [0.0f64; 16];
    let mut nc = 0;
    for m in media.iter().take(8) {
        cuts[nc] = m.enter_m;
        cuts[nc + 1] = m.exit_m.min(stop_m);
        nc += 2;
    }
    let cuts = &mut cuts[..nc];
    cuts.sort_by(f64::total_cmp);
    for c in 0..nc.saturating_sub(1) {
        let (a, b) = (cuts[c], cuts[c + 1]);
        if b <= a {
            continue;
        }
        let mid = 0.5 * (a + b);
        let (mut k_tot, mut k_rho) = (0.0, 0.0);
        for m in media.iter().take(8) {
            if m.enter_m <= mid && mid < m.exit_m {
                k_tot += m.extinction_per_m;
                k_rho += m.extinction_per_m * m.reflectance;
            }
        }
        if k_tot <= 0.0 {
            continue;
        }
        let st = Stretch {
            a,
            b,
            t_a: trans,
            k_tot,
            rho: k_rho / k_tot,
        };
        let sum_amp = deposit_stretch(&st, ray, frame, fine);
        // The whole stretch attenuates, inside the recorded window or not.
        let whole = st.transmission_at(b);
        trans = whole;
        for m in media.iter().take(8) {
            if m.enter_m <= mid && mid < m.exit_m {
                let share = m.extinction_per_m / k_tot;
                scatterers.push(Scatterer {
                    kind: m.kind,
                    object: m.object,
                    range_m: a,
                    range_end_m: b,
                    position: at(ray.origin, a, ray.d),
                    fraction: ray.w * (st.t_a - whole) * share,
                    reflectance: m.reflectance,
                    amplitude_dn: sum_amp * share * m.reflectance / st.rho.max(1e-300),
                    ray: ray.index,
                });
            }
        }
    }
    trans
}

/// The energy stretch `st` of `ray` intercepts, into the quarter-sample `fine` bins (true
/// time), each bin's at its centre; inside the stretch the transmission falls by a constant
/// factor per whole bin. Returns the sum of the amplitudes deposited, counts.
#[inline]
fn deposit_stretch(st: &Stretch, ray: &Ray, frame: &Frame, fine: &mut [f64]) -> f64 {
    let (mpn, delta, fine_t0, fine_n) = (frame.mpn, frame.delta, frame.fine_t0, frame.fine_n);
    let (ta, tb) = (st.a / mpn, st.b / mpn);
    let f_lo = ((ta - fine_t0) / delta).floor().max(0.0) as usize;
    let f_hi = (((tb - fine_t0) / delta).ceil().max(0.0) as usize).min(fine_n);
    let per_bin = (-st.k_tot * delta * mpn).exp();
    let mut sum_amp = 0.0;
    let mut t_u = f64::NAN;
    for (f, bin) in fine.iter_mut().enumerate().take(f_hi).skip(f_lo) {
        let u = (fine_t0 + f as f64 * delta).max(ta);
        let v = (fine_t0 + (f + 1) as f64 * delta).min(tb);
        if v <= u {
            continue;
        }
        let (ru, rv) = (u * mpn, v * mpn);
        if t_u.is_nan() {
            t_u = st.transmission_at(ru);
        }
        let t_v = if v < tb && u > ta {
            t_u * per_bin
        } else {
            st.transmission_at(rv)
        };
        let e = t_u - t_v;
        t_u = t_v;
        let r_mid = 0.5 * (ru + rv);
        let amp = frame.peak * ray.w * st.rho * e * (frame.r_ref / r_mid).powi(2);
        *bin += amp;
        sum_amp += amp;
    }
    sum_amp
}

/// An echo shape sampled at the sample interval for each of the [`FINE`] phases of a bin
/// centre: `table[phase][m + half]` = the unit echo at `x = m·dt − (phase + ½)·dt/FINE`,
/// `m = −half..=half` (its reach).
#[derive(Debug, Default)]
struct PhaseKernel {
    half: usize,
    table: Vec<Vec<f64>>,
}

impl PhaseKernel {
    fn from_shape(shape: &EchoShape, dt: f64) -> Self {
        let half = (shape.reach() / dt).ceil() as usize + 1;
        let delta = dt / FINE as f64;
        let table = (0..FINE)
            .map(|p| {
                (0..=2 * half)
                    .map(|k| shape.value((k as f64 - half as f64) * dt - (p as f64 + 0.5) * delta))
                    .collect()
            })
            .collect();
        PhaseKernel { half, table }
    }

    /// Adds `amp ×` the kernel of fine bin (`q`, `phase`) to `out`, whose sample `i` is fine
    /// sample `i + margin`.
    #[inline]
    fn add(&self, out: &mut [f64], margin: usize, q: usize, phase: usize, amp: f64) {
        // m = i + margin − q, so i = m + q − margin for m in −half..=half.
        let i_min = q as isize - margin as isize - self.half as isize;
        let lo = i_min.max(0);
        let hi = (i_min + 2 * self.half as isize + 1).min(out.len() as isize);
        if lo >= hi {
            return;
        }
        let first = (lo - i_min) as usize;
        let k = &self.table[phase][first..first + (hi - lo) as usize];
        for (o, &v) in out[lo as usize..hi as usize].iter_mut().zip(k) {
            *o += amp * v;
        }
    }
}

/// The kernels of a simulator: the received echo's and the truth's.
#[derive(Debug, Default)]
struct Kernels {
    clean: PhaseKernel,
    truth: PhaseKernel,
}

fn at(o: V3, s: f64, d: V3) -> V3 {
    [o[0] + s * d[0], o[1] + s * d[1], o[2] + s * d[2]]
}

/// The interleaved stream of a described scene: navigation epochs and pulses in time order,
/// as a capture holds them (lost pulses are left out and listed in [`WorldItems::lost`]).
#[derive(Debug)]
pub struct WorldItems {
    sim: WorldSim,
    nav: NavStream,
    next_nav: u64,
    nav_epochs: u64,
    nav_rate: f64,
    truth: ShotTruth,
    lost: Vec<u64>,
    pending: Option<Pulse>,
}

impl WorldItems {
    /// The stream of `sim`.
    pub fn new(sim: WorldSim) -> Result<Self, SceneError> {
        let nav = &sim.scene.navigation;
        let span = if sim.plan.pulses() == 0 {
            0.0
        } else {
            let (a, b) = sim.plan.span_gps();
            b - a
        };
        let nav_epochs = if sim.plan.pulses() == 0 {
            0
        } else {
            (span * nav.rate_hz - 1e-9).ceil().max(0.0) as u64 + 1
        };
        // Noise and dropouts only when their effects are named.
        let mut config = nav.clone();
        if !sim.scene.has(Effect::NavigationNoise) {
            config.noise = None;
        }
        if !sim.scene.has(Effect::NavigationDropouts) {
            config.dropouts.clear();
            config.random_dropout_probability = 0.0;
        }
        let nav_stream = NavStream::new(config, sim.scene.seed ^ 0x4E41_5653).map_err(|e| {
            SceneError::Invalid {
                field: "navigation",
                reason: e.to_string(),
            }
        })?;
        let mut items = WorldItems {
            nav: nav_stream,
            nav_rate: nav.rate_hz,
            sim,
            next_nav: 0,
            nav_epochs,
            truth: ShotTruth::default(),
            lost: Vec::new(),
            pending: None,
        };
        // The state one epoch before the first, for the first epoch's velocity.
        let before = items.nav_time(0) - 1.0 / items.nav_rate;
        let fix = items.fix_at(before);
        items.nav.prime(before, &fix);
        Ok(items)
    }

    /// The generator.
    pub fn sim(&self) -> &WorldSim {
        &self.sim
    }

    /// The truth of the last pulse generated (recorded or lost).
    pub fn last_truth(&self) -> &ShotTruth {
        &self.truth
    }

    /// Sequence numbers of the pulses lost so far.
    pub fn lost(&self) -> &[u64] {
        &self.lost
    }

    fn nav_time(&self, j: u64) -> f64 {
        self.sim.scene.gps_time_start_s + j as f64 / self.nav_rate
    }

    /// The true navigation state at `gps`.
    fn fix_at(&self, gps: f64) -> NavFix {
        let s = &self.sim.scene;
        let pose = self.sim.plan.pose(gps - s.gps_time_start_s);
        NavFix {
            utc_time_of_day_s: (gps - s.navigation.gps_utc_offset_s).rem_euclid(86_400.0),
            lat_deg: pose.geodetic.lat_deg,
            lon_deg: pose.geodetic.lon_deg,
            altitude_m: pose.geodetic.height_m,
            heading_deg: pose.attitude_deg[2],
            roll_deg: pose.attitude_deg[0],
            pitch_deg: pose.attitude_deg[1],
        }
    }

    /// The navigation bytes of epoch `gps` (None when the epoch is dropped).
    fn nav_bytes(&mut self, gps: f64) -> Option<Vec<u8>> {
        let fix = self.fix_at(gps);
        let mut out = Vec::new();
        self.nav.epoch_bytes(gps, &fix, &mut out).then_some(out)
    }
}

impl Iterator for WorldItems {
    type Item = SimItem;

    fn next(&mut self) -> Option<SimItem> {
        loop {
            if self.pending.is_none() {
                let mut p = Pulse::default();
                match self.sim.fill_next(&mut p, &mut self.truth) {
                    None => {}
                    Some(true) => self.pending = Some(p),
                    Some(false) => {
                        self.lost.push(self.truth.seq);
                        continue;
                    }
                }
            }
            let pulse_time = self.pending.as_ref().map(|p| p.gps_time);
            let nav_time = (self.next_nav < self.nav_epochs).then(|| self.nav_time(self.next_nav));
            match (nav_time, pulse_time) {
                (Some(tn), tp) if tp.is_none_or(|tp| tn <= tp) => {
                    self.next_nav += 1;
                    if let Some(bytes) = self.nav_bytes(tn) {
                        return Some(SimItem::Nav {
                            receive_time_ns: (tn * 1e9).round() as u64,
                            bytes,
                        });
                    }
                }
                (_, Some(_)) => return self.pending.take().map(SimItem::Pulse),
                _ => return None,
            }
        }
    }
}

#[cfg(test)]
mod tests;
