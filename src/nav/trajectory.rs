//! The trajectory buffer: a bounded ring of positions and one of attitudes, each in time order,
//! interpolated at a pulse's time.
//!
//! - **Position**: linear in latitude, longitude and height, or cubic Hermite when both
//!   bracketing samples carry velocities (north/east/up, converted to degrees per second with the
//!   WGS84 meridian and prime-vertical radii of curvature at the sample).
//! - **Attitude**: roll, pitch and heading become a unit quaternion of the body → NED rotation
//!   `R = Rz(heading) · Ry(pitch) · Rx(roll)` (z down, heading from north, applied roll first);
//!   between two samples, spherical linear interpolation (SLERP), so a heading passing 359° → 1°
//!   goes through 0°, not 180°.
//! - **No extrapolation**: a time before the first or after the last sample, or between two
//!   samples further apart than `max_gap_s`, is a [`Miss`] with its reason; the caller (the
//!   georeference stage) decides to wait, flag or drop.
//!
//! Times are seconds on one continuous GPS scale (see [`Trajectory::time_of`]): GPS seconds of
//! the week of the first sample, continuing past the week's end, so that week crossings
//! interpolate.

use std::collections::VecDeque;

use nalgebra::UnitQuaternion;
use serde::Serialize;

use super::NavSample;
use super::dating::{GpsTime, WEEK_S};

/// WGS84 semi-major axis, metres.
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS84 first eccentricity squared.
pub const WGS84_E2: f64 = 6.694_379_990_141_316e-3;

/// cos(θ/2) above which two attitudes (θ apart) are interpolated by NLERP instead of SLERP:
/// θ < 0.5°.
const NLERP_MIN_DOT: f64 = 0.999_990_480_720_734_4;

/// How positions are interpolated.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Interpolation {
    /// Linear in latitude, longitude, height.
    Linear,
    /// Cubic Hermite with the samples' velocities (linear where a sample has none).
    Hermite,
}

/// Trajectory settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryConfig {
    /// Samples kept per ring (positions, attitudes); the oldest go first.
    pub capacity: usize,
    /// Longest interval between two samples that is interpolated, seconds.
    pub max_gap_s: f64,
    /// Position interpolation.
    pub interpolation: Interpolation,
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        TrajectoryConfig {
            capacity: 4096,
            max_gap_s: 0.5,
            interpolation: Interpolation::Hermite,
        }
    }
}

/// A geodetic position (WGS84).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Geodetic {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Ellipsoidal height, metres.
    pub height_m: f64,
}

#[derive(Clone, Copy, Debug)]
struct PosSample {
    t: f64,
    p: Geodetic,
    /// Rates: degrees of latitude per second, degrees of longitude per second, metres per
    /// second up.
    rate: Option<[f64; 3]>,
}

#[derive(Clone, Copy, Debug)]
struct AttSample {
    t: f64,
    q: UnitQuaternion<f64>,
}

/// Why the trajectory has no answer at a time.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Miss {
    /// Nothing buffered yet.
    Empty,
    /// Before the oldest sample kept (too old, or before the first).
    Before,
    /// After the newest sample: navigation has not caught up (yet).
    After,
    /// The bracketing samples are further apart than `max_gap_s`.
    Gap,
}

/// What the buffer counted.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct TrajectoryStats {
    /// Position samples taken.
    pub positions: u64,
    /// Attitude samples taken.
    pub attitudes: u64,
    /// Samples refused because their time was earlier than the newest one.
    pub time_backwards: u64,
    /// Samples refused because their time equals the newest one's (duplicate epoch).
    pub duplicate_epoch: u64,
    /// Positions that had only a height above mean sea level (no geoid separation), used as is.
    pub msl_heights: u64,
    /// Samples without a usable time.
    pub untimed: u64,
}

impl TrajectoryStats {
    /// Adds `other`'s counts.
    pub fn add(&mut self, other: &TrajectoryStats) {
        self.positions += other.positions;
        self.attitudes += other.attitudes;
        self.time_backwards += other.time_backwards;
        self.duplicate_epoch += other.duplicate_epoch;
        self.msl_heights += other.msl_heights;
        self.untimed += other.untimed;
    }
}

/// The trajectory buffer (see the module documentation).
#[derive(Debug)]
pub struct Trajectory {
    cfg: TrajectoryConfig,
    /// GPS week whose start is time 0.
    week0: Option<u32>,
    pos: VecDeque<PosSample>,
    att: VecDeque<AttSample>,
    stats: TrajectoryStats,
}

/// Radii of curvature (meridian M, prime vertical N) at latitude `lat` (radians), metres.
pub fn radii(lat: f64) -> (f64, f64) {
    let s = lat.sin();
    let w = (1.0 - WGS84_E2 * s * s).sqrt();
    let n = WGS84_A / w;
    let m = WGS84_A * (1.0 - WGS84_E2) / (w * w * w);
    (m, n)
}

/// The body → NED rotation of roll, pitch, heading (degrees).
pub fn attitude_quaternion(roll: f64, pitch: f64, heading: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(roll.to_radians(), pitch.to_radians(), heading.to_radians())
}

/// Roll, pitch, heading (degrees, heading in 0..360) of a body → NED rotation.
pub fn attitude_angles(q: &UnitQuaternion<f64>) -> [f64; 3] {
    let (r, p, y) = q.euler_angles();
    [
        r.to_degrees(),
        p.to_degrees(),
        y.to_degrees().rem_euclid(360.0),
    ]
}

impl Trajectory {
    /// An empty buffer.
    pub fn new(cfg: TrajectoryConfig) -> Self {
        Trajectory {
            cfg,
            week0: None,
            pos: VecDeque::with_capacity(cfg.capacity.max(2)),
            att: VecDeque::with_capacity(cfg.capacity.max(2)),
            stats: TrajectoryStats::default(),
        }
    }

    /// Counts so far.
    pub fn stats(&self) -> &TrajectoryStats {
        &self.stats
    }

    /// The buffer's time of a GPS time: seconds since the start of the first sample's week.
    /// `None` before a sample with a week has been seen.
    pub fn time_of(&self, t: GpsTime) -> Option<f64> {
        self.week0
            .map(|w0| (t.week as f64 - w0 as f64) * WEEK_S + t.sow)
    }

    /// Newest time covered by both rings (positions and, if any, attitudes).
    pub fn newest(&self) -> Option<f64> {
        let p = self.pos.back()?.t;
        Some(match self.att.back() {
            Some(a) => p.min(a.t),
            None => p,
        })
    }

    /// Takes a sample at GPS time `t` (or, for files without weeks, `sow` alone: pass week 0
    /// consistently). Positions and attitudes are kept separately; a sample may carry both.
    pub fn push(&mut self, t: GpsTime, s: &NavSample) {
        let w0 = *self.week0.get_or_insert(t.week);
        let t = (t.week as f64 - w0 as f64) * WEEK_S + t.sow;
        if !t.is_finite() {
            self.stats.untimed += 1;
            return;
        }
        if let (Some(lat), Some(lon)) = (s.lat, s.lon) {
            let h = match (s.height, s.height_msl) {
                (Some(h), _) => Some(h),
                (None, Some(h)) => {
                    self.stats.msl_heights += 1;
                    Some(h)
                }
                _ => None,
            };
            if let Some(h) = h
                && self.admit(t, self.pos.back().map(|p| p.t))
            {
                let rate = match (s.vel_north, s.vel_east, s.vel_up) {
                    (Some(vn), Some(ve), Some(vu)) => {
                        let (m, n) = radii(lat.to_radians());
                        Some([
                            (vn / (m + h)).to_degrees(),
                            (ve / ((n + h) * lat.to_radians().cos())).to_degrees(),
                            vu,
                        ])
                    }
                    _ => None,
                };
                if self.pos.len() == self.cfg.capacity.max(2) {
                    self.pos.pop_front();
                }
                self.pos.push_back(PosSample {
                    t,
                    p: Geodetic {
                        lat_deg: lat,
                        lon_deg: lon,
                        height_m: h,
                    },
                    rate: rate.filter(|r| r.iter().all(|v| v.is_finite())),
                });
                self.stats.positions += 1;
            }
        }
        if let (Some(r), Some(p), Some(h)) = (s.roll, s.pitch, s.heading)
            && self.admit(t, self.att.back().map(|a| a.t))
        {
            if self.att.len() == self.cfg.capacity.max(2) {
                self.att.pop_front();
            }
            self.att.push_back(AttSample {
                t,
                q: attitude_quaternion(r, p, h),
            });
            self.stats.attitudes += 1;
        }
    }

    fn admit(&mut self, t: f64, newest: Option<f64>) -> bool {
        match newest {
            Some(n) if t < n => {
                self.stats.time_backwards += 1;
                false
            }
            Some(n) if t == n => {
                self.stats.duplicate_epoch += 1;
                false
            }
            _ => true,
        }
    }

    /// Indices of the samples bracketing `t` in a ring of times, or the miss.
    fn bracket<T>(
        &self,
        ring: &VecDeque<T>,
        time: impl Fn(&T) -> f64,
        t: f64,
    ) -> Result<(usize, f64), Miss> {
        let (first, last) = match (ring.front(), ring.back()) {
            (Some(f), Some(l)) => (time(f), time(l)),
            _ => return Err(Miss::Empty),
        };
        if t.is_nan() || t < first {
            return Err(Miss::Before);
        }
        if t > last {
            return Err(Miss::After);
        }
        if t == last {
            return Ok((ring.len() - 1, 0.0));
        }
        let i = ring.partition_point(|s| time(s) <= t) - 1;
        let (t0, t1) = (time(&ring[i]), time(&ring[i + 1]));
        if t1 - t0 > self.cfg.max_gap_s {
            return Err(Miss::Gap);
        }
        Ok((i, (t - t0) / (t1 - t0)))
    }

    /// Position at buffer time `t`.
    pub fn position_at(&self, t: f64) -> Result<Geodetic, Miss> {
        let (i, s) = self.bracket(&self.pos, |p| p.t, t)?;
        let a = &self.pos[i];
        if s == 0.0 {
            return Ok(a.p);
        }
        let b = &self.pos[i + 1];
        let lerp = |x: f64, y: f64| x + (y - x) * s;
        let mut dlon = b.p.lon_deg - a.p.lon_deg;
        if dlon > 180.0 {
            dlon -= 360.0;
        } else if dlon < -180.0 {
            dlon += 360.0;
        }
        match (self.cfg.interpolation, a.rate, b.rate) {
            (Interpolation::Hermite, Some(ra), Some(rb)) => {
                let h = b.t - a.t;
                let (s2, s3) = (s * s, s * s * s);
                let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
                let h10 = s3 - 2.0 * s2 + s;
                let h01 = -2.0 * s3 + 3.0 * s2;
                let h11 = s3 - s2;
                let herm = |p0: f64, p1: f64, m0: f64, m1: f64| {
                    h00 * p0 + h10 * h * m0 + h01 * p1 + h11 * h * m1
                };
                Ok(Geodetic {
                    lat_deg: herm(a.p.lat_deg, b.p.lat_deg, ra[0], rb[0]),
                    lon_deg: herm(a.p.lon_deg, a.p.lon_deg + dlon, ra[1], rb[1]),
                    height_m: herm(a.p.height_m, b.p.height_m, ra[2], rb[2]),
                })
            }
            _ => Ok(Geodetic {
                lat_deg: lerp(a.p.lat_deg, b.p.lat_deg),
                lon_deg: a.p.lon_deg + dlon * s,
                height_m: lerp(a.p.height_m, b.p.height_m),
            }),
        }
    }

    /// Attitude (body → NED) at buffer time `t`.
    pub fn attitude_at(&self, t: f64) -> Result<UnitQuaternion<f64>, Miss> {
        let (i, s) = self.bracket(&self.att, |a| a.t, t)?;
        let a = &self.att[i];
        if s == 0.0 {
            return Ok(a.q);
        }
        let b = &self.att[i + 1];
        // The shorter way round (q and −q are the same rotation). Between INS samples the
        // rotation is small: normalised linear interpolation differs from SLERP by under
        // 3e-9 rad (0.6 mas) when the samples are less than 0.5° apart (the angle error grows with the
        // cube of the step), and costs no trigonometry; larger steps take the exact SLERP.
        let dot = a.q.coords.dot(&b.q.coords);
        if dot.abs() > NLERP_MIN_DOT {
            let bq = if dot < 0.0 {
                -b.q.into_inner()
            } else {
                b.q.into_inner()
            };
            let q = a.q.into_inner() * (1.0 - s) + bq * s;
            return Ok(UnitQuaternion::new_normalize(q));
        }
        Ok(a.q.slerp(&b.q, s))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nav::{NavKind, NavTime};

    fn pos(lat: f64, lon: f64, h: f64, v: Option<[f64; 3]>) -> NavSample {
        let mut s = NavSample::new(NavKind::Inspva, NavTime::None);
        s.lat = Some(lat);
        s.lon = Some(lon);
        s.height = Some(h);
        if let Some(v) = v {
            s.vel_north = Some(v[0]);
            s.vel_east = Some(v[1]);
            s.vel_up = Some(v[2]);
        }
        s
    }

    fn att(r: f64, p: f64, h: f64) -> NavSample {
        let mut s = NavSample::new(NavKind::Pashr, NavTime::None);
        s.roll = Some(r);
        s.pitch = Some(p);
        s.heading = Some(h);
        s
    }

    fn gt(sow: f64) -> GpsTime {
        GpsTime { week: 2000, sow }
    }

    #[test]
    fn heading_wraps_through_north() {
        let mut tr = Trajectory::new(TrajectoryConfig::default());
        tr.push(gt(100.0), &att(0.0, 0.0, 359.0));
        tr.push(gt(100.1), &att(0.0, 0.0, 1.0));
        let t = tr.time_of(gt(100.05)).unwrap();
        let [r, p, h] = attitude_angles(&tr.attitude_at(t).unwrap());
        assert!(r.abs() < 1e-9 && p.abs() < 1e-9);
        assert!(!(1e-6..=360.0 - 1e-6).contains(&h), "{h}");
        let t = tr.time_of(gt(100.075)).unwrap();
        let h = attitude_angles(&tr.attitude_at(t).unwrap())[2];
        assert!((h - 0.5).abs() < 1e-6, "{h}");
    }

    #[test]
    fn nlerp_between_close_samples_stays_within_3e9_rad_of_slerp() {
        let a = attitude_quaternion(1.0, 2.0, 30.0);
        let b = attitude_quaternion(1.1, 1.9, 30.3);
        assert!(a.angle_to(&b) < 0.5f64.to_radians());
        let mut tr = Trajectory::new(TrajectoryConfig::default());
        tr.push(gt(5.0), &att(1.0, 2.0, 30.0));
        tr.push(gt(5.01), &att(1.1, 1.9, 30.3));
        for k in 0..=20 {
            let s = k as f64 / 20.0;
            let got = tr
                .attitude_at(tr.time_of(gt(5.0 + 0.01 * s)).unwrap())
                .unwrap();
            assert!(got.angle_to(&a.slerp(&b, s)) < 3e-9, "{s}");
        }
    }

    #[test]
    fn euler_angles_round_trip_and_follow_ned() {
        let q = attitude_quaternion(2.0, -3.0, 250.0);
        let [r, p, h] = attitude_angles(&q);
        assert!((r - 2.0).abs() < 1e-9 && (p + 3.0).abs() < 1e-9 && (h - 250.0).abs() < 1e-9);
        // Heading 90°: the body's forward axis (x) points east (NED y).
        let fwd = attitude_quaternion(0.0, 0.0, 90.0) * nalgebra::Vector3::x();
        assert!((fwd - nalgebra::Vector3::y()).norm() < 1e-12);
        // Pitch up 10°: forward gains an upward (−z in NED) component.
        let fwd = attitude_quaternion(0.0, 10.0, 0.0) * nalgebra::Vector3::x();
        assert!(fwd.z < 0.0);
        // Roll right wing down 10°: the right wing (y) points down (+z).
        let right = attitude_quaternion(10.0, 0.0, 0.0) * nalgebra::Vector3::y();
        assert!(right.z > 0.0);
    }

    #[test]
    fn hermite_follows_a_constant_velocity_line_exactly_and_no_extrapolation() {
        // 60 m/s north at 45°: latitude rate from the meridian radius.
        let (m, _) = radii(45f64.to_radians());
        let rate = (60.0 / (m + 1000.0)).to_degrees();
        let mut tr = Trajectory::new(TrajectoryConfig::default());
        for k in 0..5 {
            tr.push(
                gt(10.0 + 0.1 * k as f64),
                &pos(
                    45.0 + rate * 0.1 * k as f64,
                    7.0,
                    1000.0,
                    Some([60.0, 0.0, 0.0]),
                ),
            );
        }
        let t = tr.time_of(gt(10.237)).unwrap();
        let p = tr.position_at(t).unwrap();
        assert!((p.lat_deg - (45.0 + rate * 0.237)).abs() < 1e-12);
        assert_eq!(
            tr.position_at(tr.time_of(gt(9.99)).unwrap()),
            Err(Miss::Before)
        );
        assert_eq!(
            tr.position_at(tr.time_of(gt(10.41)).unwrap()),
            Err(Miss::After)
        );
    }

    #[test]
    fn gaps_backwards_time_and_duplicates_are_refused() {
        let cfg = TrajectoryConfig {
            capacity: 3,
            max_gap_s: 0.5,
            interpolation: Interpolation::Linear,
        };
        let mut tr = Trajectory::new(cfg);
        tr.push(gt(1.0), &pos(10.0, 20.0, 0.0, None));
        tr.push(gt(2.0), &pos(10.0, 20.0, 0.0, None));
        tr.push(gt(1.5), &pos(10.0, 20.0, 0.0, None));
        tr.push(gt(2.0), &pos(10.0, 20.0, 0.0, None));
        assert_eq!(tr.stats().time_backwards, 1);
        assert_eq!(tr.stats().duplicate_epoch, 1);
        assert_eq!(tr.position_at(tr.time_of(gt(1.5)).unwrap()), Err(Miss::Gap));
        // Bounded: the oldest go first.
        for k in 0..10 {
            tr.push(gt(3.0 + k as f64 * 0.1), &pos(10.0, 20.0, 0.0, None));
        }
        assert_eq!(tr.pos.len(), 3);
        assert_eq!(
            tr.position_at(tr.time_of(gt(3.0)).unwrap()),
            Err(Miss::Before)
        );
    }

    #[test]
    fn week_crossing_interpolates() {
        let mut tr = Trajectory::new(TrajectoryConfig::default());
        tr.push(
            GpsTime {
                week: 2000,
                sow: WEEK_S - 0.05,
            },
            &pos(0.0, 179.99, 0.0, None),
        );
        tr.push(
            GpsTime {
                week: 2001,
                sow: 0.05,
            },
            &pos(0.0, -179.99, 0.0, None),
        );
        let t = tr
            .time_of(GpsTime {
                week: 2001,
                sow: 0.0,
            })
            .unwrap();
        let p = tr.position_at(t).unwrap();
        // Halfway, across the antimeridian: ±180, not 0.
        assert!((p.lon_deg.abs() - 180.0).abs() < 1e-9, "{p:?}");
    }
}
