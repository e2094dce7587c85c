//! Where the aircraft is and where the beam points: the flight plan (lines or the seed's plot
//! grid), the scan pattern, the sensor's lever arm and boresight, and the exact conversion of
//! the scene frame (the tangent plane at the origin) to WGS84 for the navigation stream.
//!
//! The aircraft flies level **in its local level frame** (roll = pitch = 0 exactly, heading
//! rounded to 0.01°, the resolution of `$PASHR`), so that the attitude the navigation stream
//! reports is the attitude that was simulated; its body axes are then expressed in the scene
//! frame through ECEF. Its track is straight in the scene frame at `altitude_m` above the origin.

use nalgebra::{Matrix3, Vector3};

use crate::core::sensor::SensorProfile;
use crate::geo::crs::{ecef_of, geodetic_of_ecef};
use crate::geo::direct_georeference::{beam_in_scanner, ned_to_ecef};
use crate::nav::trajectory::{Geodetic, attitude_quaternion};

use super::geometry::{V3, normalize};
use super::scene::{Effect, ScanPattern, WorldScene};

/// The scene frame on the ellipsoid.
#[derive(Clone, Debug)]
pub struct Frames {
    origin_ecef: Vector3<f64>,
    /// Columns: east, north, up in ECEF.
    enu_to_ecef: Matrix3<f64>,
}

impl Frames {
    /// The tangent plane at `lat`, `lon` (degrees), `height` (metres).
    pub fn new(lat: f64, lon: f64, height: f64) -> Self {
        let (sp, cp) = lat.to_radians().sin_cos();
        let (sl, cl) = lon.to_radians().sin_cos();
        let o = ecef_of(lat, lon, height).unwrap_or([0.0; 3]);
        Frames {
            origin_ecef: Vector3::from(o),
            enu_to_ecef: Matrix3::new(-sl, -sp * cl, cp * cl, cl, -sp * sl, cp * sl, 0.0, cp, sp),
        }
    }

    /// ECEF of a scene point.
    pub fn ecef(&self, p: V3) -> [f64; 3] {
        let e = self.origin_ecef + self.enu_to_ecef * Vector3::from(p);
        [e.x, e.y, e.z]
    }

    /// WGS84 of a scene point.
    pub fn geodetic(&self, p: V3) -> Geodetic {
        let g = geodetic_of_ecef(self.ecef(p)).unwrap_or([0.0; 3]);
        Geodetic {
            lat_deg: g[0],
            lon_deg: g[1],
            height_m: g[2],
        }
    }

    /// Rotation from the local NED frame at `g` to the scene frame.
    pub fn ned_to_enu(&self, g: &Geodetic) -> Matrix3<f64> {
        self.enu_to_ecef.transpose() * ned_to_ecef(g.lat_deg, g.lon_deg)
    }
}

/// The aircraft at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// IMU reference point, scene frame, metres.
    pub imu: V3,
    /// Its WGS84 position.
    pub geodetic: Geodetic,
    /// Roll, pitch, heading in the local level frame, degrees.
    pub attitude_deg: [f64; 3],
    /// Body → scene frame rotation.
    pub body_to_enu: Matrix3<f64>,
}

/// One laser shot's geometry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shot {
    /// GPS time, seconds.
    pub gps_time: f64,
    /// The aircraft.
    pub pose: Pose,
    /// Scan angles (primary θ, secondary φ; NaN for a one-axis scanner), degrees.
    pub scan_deg: [f64; 2],
    /// Scanner origin, scene frame.
    pub origin: V3,
    /// Unit beam direction, scene frame.
    pub beam: V3,
}

/// Segments of the flight in time: a line flown (pulses) or a turn (navigation only).
#[derive(Clone, Debug)]
struct Leg {
    t0: f64,
    duration: f64,
    from: V3,
    to: V3,
    heading_deg: f64,
    pulses: u64,
    first_pulse: u64,
}

/// The flight plan in time.
#[derive(Clone, Debug)]
pub struct FlightPlan {
    frames: Frames,
    start_gps: f64,
    prf: f64,
    legs: Vec<Leg>,
    total: u64,
    scan: ScanPattern,
    off_nadir: bool,
    lever: Vector3<f64>,
    boresight: Matrix3<f64>,
    grid: Option<GridAim>,
}

#[derive(Clone, Debug)]
struct GridAim {
    columns: u64,
    /// Target of beam (row 0, column 0) and the step between columns (east) and rows (north).
    first: [f64; 2],
    spacing: f64,
    /// Ground height function is applied by the caller through `aim_height`.
    aim_height: Vec<f64>,
}

impl FlightPlan {
    /// The plan of `scene` flown with `sensor`; `ground` gives the terrain height for aiming
    /// the plot grid.
    pub fn new(
        scene: &WorldScene,
        sensor: &SensorProfile,
        ground: impl Fn(f64, f64) -> Option<f64>,
    ) -> Self {
        let f = &scene.flight;
        let o = &scene.origin;
        let frames = Frames::new(o.lat_deg, o.lon_deg, o.height_m);
        let prf = scene.pulse_rate_hz(sensor);
        let mut legs = Vec::new();
        let mut grid = None;
        let h = f.altitude_m;
        let off_nadir = scene.has(Effect::OffNadir);
        if let Some(g) = &f.grid {
            let (zen, az) = match (&f.scan, off_nadir) {
                (
                    ScanPattern::Fixed {
                        zenith_deg,
                        azimuth_deg,
                    },
                    true,
                ) => (zenith_deg.to_radians(), azimuth_deg.to_radians()),
                _ => (0.0, 0.0),
            };
            let (c, r) = (g.columns as u64, g.rows as u64);
            let first = [
                g.centre_m[0] - (c as f64 - 1.0) / 2.0 * g.spacing_m,
                g.centre_m[1] - (r as f64 - 1.0) / 2.0 * g.spacing_m,
            ];
            // Flying north along the rows, offset so the tilted beam reaches the plot.
            let off = [h * zen.tan() * az.sin(), h * zen.tan() * az.cos()];
            let v = g.spacing_m * prf / c as f64;
            let y0 = first[1] - off[1] - (c as f64 - 1.0) / 2.0 * g.spacing_m / c as f64;
            let x = g.centre_m[0] - off[0];
            let n = c * r;
            let duration = n as f64 / prf;
            legs.push(Leg {
                t0: 0.0,
                duration,
                from: [x, y0, h],
                to: [x, y0 + v * duration, h],
                heading_deg: 0.0,
                pulses: n,
                first_pulse: 0,
            });
            let mut aim_height = Vec::with_capacity(n as usize);
            for k in 0..n {
                let (row, col) = (k / c, k % c);
                let (x, y) = (
                    first[0] + col as f64 * g.spacing_m,
                    first[1] + row as f64 * g.spacing_m,
                );
                aim_height.push(ground(x, y).unwrap_or(0.0));
            }
            grid = Some(GridAim {
                columns: c,
                first,
                spacing: g.spacing_m,
                aim_height,
            });
        } else {
            let mut t = 0.0;
            let mut first_pulse = 0u64;
            for (i, l) in f.lines.iter().enumerate() {
                let (a, b) = (l.start_m, l.end_m);
                let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
                let duration = len / f.speed_mps;
                let pulses = (duration * prf).floor() as u64 + 1;
                let heading = (b[0] - a[0])
                    .atan2(b[1] - a[1])
                    .to_degrees()
                    .rem_euclid(360.0);
                legs.push(Leg {
                    t0: t,
                    duration,
                    from: [a[0], a[1], h],
                    to: [b[0], b[1], h],
                    heading_deg: heading,
                    pulses,
                    first_pulse,
                });
                first_pulse += pulses;
                t += duration;
                if let Some(next) = f.lines.get(i + 1) {
                    let c = next.start_m;
                    let hd = if c != b {
                        (c[0] - b[0])
                            .atan2(c[1] - b[1])
                            .to_degrees()
                            .rem_euclid(360.0)
                    } else {
                        heading
                    };
                    legs.push(Leg {
                        t0: t,
                        duration: f.turn_s,
                        from: [b[0], b[1], h],
                        to: [c[0], c[1], h],
                        heading_deg: hd,
                        pulses: 0,
                        first_pulse,
                    });
                    t += f.turn_s;
                }
            }
        }
        let total = legs.iter().map(|l| l.pulses).sum::<u64>();
        let total = f.max_pulses.map_or(total, |m| m.min(total));
        let b = sensor.boresight_deg;
        FlightPlan {
            frames,
            start_gps: scene.gps_time_start_s,
            prf,
            legs,
            total,
            scan: f.scan.clone(),
            off_nadir,
            lever: Vector3::from(sensor.lever_arm_m),
            boresight: attitude_quaternion(b[0], b[1], b[2])
                .to_rotation_matrix()
                .into_inner(),
            grid,
        }
    }

    /// The scene frame.
    pub fn frames(&self) -> &Frames {
        &self.frames
    }

    /// Pulses in the flight.
    pub fn pulses(&self) -> u64 {
        self.total
    }

    /// GPS time of the first pulse and of the last, seconds.
    pub fn span_gps(&self) -> (f64, f64) {
        let last = self.pulse_leg(self.total.saturating_sub(1));
        (self.start_gps, self.start_gps + last.1)
    }

    /// The leg of pulse `k` and its time from the start, seconds.
    fn pulse_leg(&self, k: u64) -> (&Leg, f64) {
        let leg = self
            .legs
            .iter()
            .rfind(|l| l.pulses > 0 && l.first_pulse <= k)
            .unwrap_or(&self.legs[0]);
        (leg, leg.t0 + (k - leg.first_pulse) as f64 / self.prf)
    }

    /// The aircraft at `t` seconds after the first pulse.
    pub fn pose(&self, t: f64) -> Pose {
        let leg = self
            .legs
            .iter()
            .rfind(|l| l.t0 <= t)
            .unwrap_or(&self.legs[0]);
        let f = if leg.duration > 0.0 {
            (t - leg.t0) / leg.duration
        } else {
            0.0
        };
        let imu = [
            leg.from[0] + f * (leg.to[0] - leg.from[0]),
            leg.from[1] + f * (leg.to[1] - leg.from[1]),
            leg.from[2] + f * (leg.to[2] - leg.from[2]),
        ];
        let geodetic = self.frames.geodetic(imu);
        // The track's direction in the local level frame: the scene's heading turned by the
        // meridian convergence, rounded to the navigation stream's 0.01°.
        let ned_to_enu = self.frames.ned_to_enu(&geodetic);
        let hd = leg.heading_deg.to_radians();
        let fwd_enu = Vector3::new(hd.sin(), hd.cos(), 0.0);
        let fwd_ned = ned_to_enu.transpose() * fwd_enu;
        let heading =
            ((fwd_ned.y.atan2(fwd_ned.x).to_degrees() * 100.0).round() / 100.0).rem_euclid(360.0);
        let body_to_ned = attitude_quaternion(0.0, 0.0, heading)
            .to_rotation_matrix()
            .into_inner();
        Pose {
            imu,
            geodetic,
            attitude_deg: [0.0, 0.0, heading],
            body_to_enu: ned_to_enu * body_to_ned,
        }
    }

    /// The geometry of pulse `k` (0-based, `k < pulses()`).
    pub fn shot(&self, k: u64) -> Shot {
        let (leg, t) = self.pulse_leg(k);
        let pose = self.pose(t);
        let r = pose.body_to_enu;
        let origin_v = Vector3::from(pose.imu) + r * self.lever;
        let origin = [origin_v.x, origin_v.y, origin_v.z];
        let scan_deg = if let Some(g) = &self.grid {
            let (row, col) = (k / g.columns, k % g.columns);
            let target = [
                g.first[0] + col as f64 * g.spacing,
                g.first[1] + row as f64 * g.spacing,
                g.aim_height[k as usize],
            ];
            let d = normalize([
                target[0] - origin[0],
                target[1] - origin[1],
                target[2] - origin[2],
            ]);
            let b = self.boresight.transpose() * r.transpose() * Vector3::from(d);
            [b.y.asin().to_degrees(), b.x.atan2(b.z).to_degrees()]
        } else if self.off_nadir {
            scan_angles(&self.scan, t - leg.t0)
        } else {
            [0.0, f64::NAN]
        };
        // What the pulse records (f32) is what the beam follows.
        let stored = [scan_deg[0] as f32 as f64, scan_deg[1] as f32 as f64];
        let b = r * self.boresight * beam_in_scanner(stored[0], stored[1]);
        Shot {
            gps_time: self.start_gps + t,
            pose,
            scan_deg: stored,
            origin,
            beam: normalize([b.x, b.y, b.z]),
        }
    }

    /// GPS time of pulse `k`, seconds.
    pub fn gps_time(&self, k: u64) -> f64 {
        self.start_gps + self.pulse_leg(k).1
    }

    /// End of the flight (last leg's end) after the first pulse, seconds.
    pub fn duration_s(&self) -> f64 {
        self.legs.last().map_or(0.0, |l| l.t0 + l.duration)
    }
}

/// Scan angles `[θ, φ]` in degrees of `pattern` at `t` seconds into a line.
pub fn scan_angles(pattern: &ScanPattern, t: f64) -> [f64; 2] {
    match *pattern {
        ScanPattern::Fixed {
            zenith_deg,
            azimuth_deg,
        } => {
            let (z, a) = (zenith_deg.to_radians(), azimuth_deg.to_radians());
            let b = [z.sin() * a.cos(), z.sin() * a.sin(), z.cos()];
            [b[1].asin().to_degrees(), b[0].atan2(b[2]).to_degrees()]
        }
        ScanPattern::Oscillating {
            half_angle_deg,
            rate_hz,
        } => {
            let p = (t * rate_hz).rem_euclid(1.0);
            let tri = if p < 0.5 {
                4.0 * p - 1.0
            } else {
                3.0 - 4.0 * p
            };
            [half_angle_deg * tri, f64::NAN]
        }
        ScanPattern::Polygon {
            half_angle_deg,
            rate_hz,
        } => {
            let p = (t * rate_hz).rem_euclid(1.0);
            [half_angle_deg * (2.0 * p - 1.0), f64::NAN]
        }
        ScanPattern::Palmer {
            half_angle_deg,
            rate_hz,
        } => {
            let a = half_angle_deg.to_radians();
            let psi = std::f64::consts::TAU * (t * rate_hz).rem_euclid(1.0);
            let b = [a.sin() * psi.cos(), a.sin() * psi.sin(), a.cos()];
            [b[1].asin().to_degrees(), b[0].atan2(b[2]).to_degrees()]
        }
    }
}

/// Sub-ray directions across a Gaussian beam of full 1/e² divergence `divergence_rad` around
/// unit `axis`: `rings` rings of equal energy (the axis ray for the first, `6j` rays on ring
/// `j` at the radius that splits the ring's energy in half), with weights summing to 1.
pub fn footprint_rays(axis: V3, divergence_rad: f64, rings: u32, out: &mut Vec<(V3, f64)>) {
    out.clear();
    let a = Vector3::from(axis);
    let helper = if a.z.abs() < 0.9 {
        Vector3::z()
    } else {
        Vector3::x()
    };
    let u = a.cross(&helper).normalize();
    let v = a.cross(&u);
    let j_n = rings.max(1);
    for j in 0..j_n {
        let w_ring = 1.0 / j_n as f64;
        if j == 0 {
            out.push((axis, w_ring));
            continue;
        }
        let q = (j as f64 + 0.5) / j_n as f64;
        let alpha = divergence_rad / 2.0 * (-(1.0 - q).ln() / 2.0).sqrt();
        let n = 6 * j;
        for i in 0..n {
            let psi = std::f64::consts::TAU * i as f64 / n as f64 + 0.5 * j as f64;
            let d = a + alpha.tan() * (psi.cos() * u + psi.sin() * v);
            let d = d.normalize();
            out.push(([d.x, d.y, d.z], w_ring / n as f64));
        }
    }
}
