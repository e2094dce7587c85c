//! Direct georeferencing of one pulse: from the aircraft's pose (trajectory position and
//! attitude at the pulse's time), the scan angles, the lever arm and boresight of the sensor
//! profile and the speed of light in air, to the pulse's [`PulseGeometry`] in the output CRS —
//! the position of its reference time t0 and the displacement per nanosecond of the time axis,
//! so that every bin `t` ns after t0 lies at `anchor + t · direction`.
//!
//! Frames and conventions:
//! - **Scanner frame**: z along the beam at zero scan angles (down), x forward, y right. The
//!   primary (cross-track) angle θ turns the beam to the right for θ > 0, the secondary
//!   (along-track, Palmer and two-axis scanners) angle φ forward for φ > 0:
//!   `b = (cos θ · sin φ, sin θ, cos θ · cos φ)`.
//! - **Body frame**: x forward, y right, z down (NED-aligned when level, heading north). The
//!   scanner frame is rotated from it by the boresight angles (roll, pitch, yaw), same order and
//!   signs as the attitude; the scanner origin sits at the lever arm from the IMU reference
//!   point, in the body frame.
//! - **Local level (NED)** from the body by the INS attitude (`Rz(heading) · Ry(pitch) ·
//!   Rx(roll)`, see [`crate::nav::trajectory`]), then **ECEF** by the north/east/down axes at the
//!   IMU's latitude and longitude, then the **output CRS** by projection.
//! - **Range**: one nanosecond of two-way travel is `c / (2 n)` metres along the beam, `n` the
//!   air's group refractive index (configurable; 1.00027 is typical below 3 km at 1064-1550 nm).
//!
//! The beam is straight in ECEF; in the map (and in ellipsoidal height) it is slightly curved:
//! over a kilometre of horizontal travel a straight line through the ends misses the middle by
//! centimetres (the Earth's curvature, d²/8R). So the projected geometry is the chord through
//! the projections of the *recorded window's* first and last return samples (two projections per
//! pulse, every bin then one multiply-add), which is 0.1 mm over a 100 m window and about 1 mm
//! over 300 m at 30° off nadir; the anchor is that chord extended back to t0 (centimetres from the
//! scanner's true position: the chord serves the recorded bins, not the aircraft).
//! [`Georeferenced::chord_error_m`] measures the cost at any bin (tested).

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

use super::crs::{GeoError, OutputCrs, ecef_of, geodetic_of_ecef};
use super::local_projection::LocalProjection;
use crate::core::units::C_M_PER_S;
use crate::nav::trajectory::{Geodetic, radii};
use crate::pulse::PulseGeometry;

/// The sensor mounting and the air, as the georeference needs them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mounting {
    /// Scanner origin from the IMU reference point in the body frame (x fwd, y right, z down),
    /// metres.
    pub lever_arm_m: [f64; 3],
    /// Boresight (roll, pitch, yaw) of the scanner frame relative to the body, degrees.
    pub boresight_deg: [f64; 3],
    /// Group refractive index of the air along the path.
    pub refractive_index: f64,
}

impl Mounting {
    /// Metres along the beam per nanosecond of two-way travel time.
    pub fn metres_per_ns(&self) -> f64 {
        C_M_PER_S * 1e-9 / (2.0 * self.refractive_index)
    }
}

/// Footprint radius at a bin `t_ns` after t0, metres: the beam's full-angle (1/e²) divergence
/// `divergence_mrad` spread over the range `t · c / (2 n)` (small-angle: radius = range ·
/// divergence / 2), plus the beam's radius at the exit aperture `exit_radius_m`. What the
/// voxeliser spreads each bin over.
pub fn footprint_radius_m(
    mount: &Mounting,
    divergence_mrad: f64,
    exit_radius_m: f64,
    t_ns: f64,
) -> f64 {
    exit_radius_m + (t_ns.max(0.0) * mount.metres_per_ns()) * divergence_mrad * 1e-3 / 2.0
}

/// A georeferenced pulse.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Georeferenced {
    /// Anchor and direction in the output CRS.
    pub geometry: PulseGeometry,
    /// The scanner origin in ECEF, metres.
    pub origin_ecef: [f64; 3],
    /// Unit beam direction in ECEF.
    pub beam_ecef: [f64; 3],
    /// Unit beam direction in NED at the aircraft (for incidence and footprint models).
    pub beam_ned: [f64; 3],
}

/// The beam in the scanner frame for primary `theta` and secondary `phi` scan angles (degrees;
/// a NaN secondary angle means a one-axis scanner: 0).
pub fn beam_in_scanner(theta_deg: f64, phi_deg: f64) -> Vector3<f64> {
    let t = theta_deg.to_radians();
    let p = if phi_deg.is_finite() {
        phi_deg.to_radians()
    } else {
        0.0
    };
    Vector3::new(t.cos() * p.sin(), t.sin(), t.cos() * p.cos())
}

/// The rotation from NED to ECEF axes at (`lat`, `lon`) degrees: columns north, east, down.
pub fn ned_to_ecef(lat: f64, lon: f64) -> Matrix3<f64> {
    let (sp, cp) = lat.to_radians().sin_cos();
    let (sl, cl) = lon.to_radians().sin_cos();
    Matrix3::new(
        -sp * cl,
        -sl,
        -cp * cl, //
        -sp * sl,
        cl,
        -cp * sl, //
        cp,
        0.0,
        -sp,
    )
}

fn add(a: [f64; 3], s: f64, d: Vector3<f64>) -> [f64; 3] {
    [a[0] + s * d.x, a[1] + s * d.y, a[2] + s * d.z]
}

/// Georeferences one pulse whose recorded return samples span `window_ns.0 ..= window_ns.1`
/// nanoseconds after t0: the chord's ends projected exactly (WGS84 by the closed form, then
/// `crs`; `[georeference] projection = "per_pulse"`).
pub fn georeference(
    crs: &OutputCrs,
    imu: Geodetic,
    attitude: &UnitQuaternion<f64>,
    scan_angle_deg: [f32; 2],
    mount: &Mounting,
    window_ns: (f64, f64),
) -> Result<Georeferenced, GeoError> {
    georeference_by(
        |a, e| crs.project_pair(geodetic_of_ecef(a)?, geodetic_of_ecef(e)?),
        imu,
        attitude,
        scan_angle_deg,
        mount,
        window_ns,
    )
}

/// [`georeference`] with the chord's ends mapped by `local`, a quadratic model of the
/// projection rebuilt once per kilometre (`[georeference] projection = "per_span"`; its
/// difference from the exact path is in docs/navigation.md).
pub fn georeference_local(
    crs: &OutputCrs,
    local: &mut LocalProjection,
    imu: Geodetic,
    attitude: &UnitQuaternion<f64>,
    scan_angle_deg: [f32; 2],
    mount: &Mounting,
    window_ns: (f64, f64),
) -> Result<Georeferenced, GeoError> {
    georeference_by(
        |a, e| local.map_pair(crs, a, e),
        imu,
        attitude,
        scan_angle_deg,
        mount,
        window_ns,
    )
}

/// [`georeference`] with `map_pair` turning the chord's two ends (ECEF, metres) into the output
/// CRS (easting, northing, ellipsoidal height, metres).
fn georeference_by(
    map_pair: impl FnOnce([f64; 3], [f64; 3]) -> Result<[[f64; 3]; 2], GeoError>,
    imu: Geodetic,
    attitude: &UnitQuaternion<f64>,
    scan_angle_deg: [f32; 2],
    mount: &Mounting,
    window_ns: (f64, f64),
) -> Result<Georeferenced, GeoError> {
    let boresight = crate::nav::trajectory::attitude_quaternion(
        mount.boresight_deg[0],
        mount.boresight_deg[1],
        mount.boresight_deg[2],
    );
    let beam_body = boresight * beam_in_scanner(scan_angle_deg[0] as f64, scan_angle_deg[1] as f64);
    let beam_ned = attitude * beam_body;
    let lever_ned = attitude * Vector3::from(mount.lever_arm_m);
    // The scanner origin: the IMU position moved by the lever arm. The offset is a metre or
    // two, so the radii of curvature turn it into degrees exactly enough (error ~ offset² / R,
    // 1e-7 m) without a round trip through ECEF.
    let (m_r, n_r) = radii(imu.lat_deg.to_radians());
    let origin = Geodetic {
        lat_deg: imu.lat_deg + (lever_ned.x / (m_r + imu.height_m)).to_degrees(),
        lon_deg: imu.lon_deg
            + (lever_ned.y / ((n_r + imu.height_m) * imu.lat_deg.to_radians().cos())).to_degrees(),
        height_m: imu.height_m - lever_ned.z,
    };
    let beam_ecef = ned_to_ecef(origin.lat_deg, origin.lon_deg) * beam_ned;
    let origin_ecef = ecef_of(origin.lat_deg, origin.lon_deg, origin.height_m)?;
    let (t0, t1) = (window_ns.0, window_ns.1.max(window_ns.0 + 1.0));
    let step = mount.metres_per_ns();
    let [a, e] = map_pair(
        add(origin_ecef, t0 * step, beam_ecef),
        add(origin_ecef, t1 * step, beam_ecef),
    )?;
    let direction = [
        (e[0] - a[0]) / (t1 - t0),
        (e[1] - a[1]) / (t1 - t0),
        (e[2] - a[2]) / (t1 - t0),
    ];
    Ok(Georeferenced {
        geometry: PulseGeometry {
            anchor: [
                a[0] - t0 * direction[0],
                a[1] - t0 * direction[1],
                a[2] - t0 * direction[2],
            ],
            direction,
        },
        origin_ecef,
        beam_ecef: [beam_ecef.x, beam_ecef.y, beam_ecef.z],
        beam_ned: [beam_ned.x, beam_ned.y, beam_ned.z],
    })
}

fn map_of_ecef(crs: &OutputCrs, x: [f64; 3]) -> Result<[f64; 3], GeoError> {
    let g = geodetic_of_ecef(x)?;
    crs.project(g[0], g[1], g[2])
}

impl Georeferenced {
    /// Distance between the map chord and the true (ECEF-straight) beam `t_ns` after t0,
    /// metres: what the linear geometry costs at that bin (one more projection; for QA and
    /// tests, not per pulse).
    pub fn chord_error_m(
        &self,
        crs: &OutputCrs,
        mount: &Mounting,
        t_ns: f64,
    ) -> Result<f64, GeoError> {
        let b = Vector3::from(self.beam_ecef);
        let truth = map_of_ecef(crs, add(self.origin_ecef, t_ns * mount.metres_per_ns(), b))?;
        let g = &self.geometry;
        Ok((0..3)
            .map(|k| (g.anchor[k] + t_ns * g.direction[k] - truth[k]).powi(2))
            .sum::<f64>()
            .sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nav::trajectory::attitude_quaternion;

    fn mount() -> Mounting {
        Mounting {
            lever_arm_m: [0.0; 3],
            boresight_deg: [0.0; 3],
            refractive_index: 1.0,
        }
    }

    fn crs() -> OutputCrs {
        OutputCrs::from_epsg(32633).unwrap()
    }

    const IMU: Geodetic = Geodetic {
        lat_deg: 47.8,
        lon_deg: 15.0, // the central meridian of zone 33: grid north is true north
        height_m: 1000.0,
    };

    /// The local model of the projection places a swath of pulses (±30° across a 3 km track
    /// from 1000 m, turning) where the exact path does, within a hundredth of a millimetre at
    /// every bin of their windows.
    #[test]
    fn a_local_projection_places_pulses_as_the_exact_path_does() {
        let crs = crs();
        let mount = Mounting {
            lever_arm_m: [0.3, -0.2, 0.5],
            boresight_deg: [0.1, -0.05, 0.2],
            refractive_index: 1.00027,
        };
        let mut local = LocalProjection::new();
        let mut worst = 0.0f64;
        for i in 0..600 {
            let imu = Geodetic {
                lat_deg: IMU.lat_deg + i as f64 * 5e-5,
                lon_deg: IMU.lon_deg - 1.5 + i as f64 * 2e-5,
                height_m: 1000.0 + (i % 7) as f64,
            };
            let q = attitude_quaternion(2.0, -1.0, 30.0 + i as f64 * 0.1);
            let scan = [(i % 61) as f32 - 30.0, f32::NAN];
            let window = (6000.0 + (i % 13) as f64 * 10.0, 6600.0);
            let exact = georeference(&crs, imu, &q, scan, &mount, window).unwrap();
            let got = georeference_local(&crs, &mut local, imu, &q, scan, &mount, window).unwrap();
            for t in [window.0, (window.0 + window.1) / 2.0, window.1] {
                let (a, b) = (exact.geometry, got.geometry);
                for k in 0..3 {
                    let d = (a.anchor[k] + t * a.direction[k]) - (b.anchor[k] + t * b.direction[k]);
                    worst = worst.max(d.abs());
                }
            }
        }
        assert!(worst < 1e-5, "{worst} m");
        assert!(local.rebuilds >= 2, "{}", local.rebuilds);
    }

    #[test]
    fn level_nadir_beam_goes_straight_down() {
        let g = georeference(
            &crs(),
            IMU,
            &attitude_quaternion(0.0, 0.0, 0.0),
            [0.0, f32::NAN],
            &mount(),
            (6000.0, 7000.0),
        )
        .unwrap();
        let d = g.geometry.direction;
        let per_ns = C_M_PER_S * 1e-9 / 2.0;
        assert!(d[0].abs() < 1e-9 && d[1].abs() < 1e-9, "{d:?}");
        // Down, by c/2 per ns (heights are ellipsoidal: straight down is −h).
        assert!((d[2] + per_ns).abs() < 1e-6, "{d:?}");
        // 1000 m below the aircraft after 1000 m / (c/2 per ns): the ellipsoid.
        let t = 1000.0 / per_ns;
        let z = g.geometry.anchor[2] + t * d[2];
        assert!(z.abs() < 1e-3, "{z}");
        assert!(g.chord_error_m(&crs(), &mount(), 6500.0).unwrap() < 1e-4);
        // The chord extended to t0 is within centimetres of the aircraft (1000 m up).
        assert!(
            (g.geometry.anchor[2] - 1000.0).abs() < 0.05,
            "{:?}",
            g.geometry.anchor
        );
    }

    #[test]
    fn scan_angle_heading_and_roll_turn_the_beam_the_right_way() {
        // Flying north, scanning 20° right: the ground point is east of the track.
        let q = attitude_quaternion(0.0, 0.0, 0.0);
        let g = georeference(
            &crs(),
            IMU,
            &q,
            [20.0, f32::NAN],
            &mount(),
            (6000.0, 8000.0),
        )
        .unwrap();
        assert!(g.geometry.direction[0] > 0.0, "east");
        let ratio = g.geometry.direction[0] / -g.geometry.direction[2];
        assert!((ratio - 20f64.to_radians().tan()).abs() < 1e-3, "{ratio}");
        // Flying east (heading 90), the same scan goes south.
        let q = attitude_quaternion(0.0, 0.0, 90.0);
        let g = georeference(
            &crs(),
            IMU,
            &q,
            [20.0, f32::NAN],
            &mount(),
            (6000.0, 8000.0),
        )
        .unwrap();
        assert!(g.geometry.direction[1] < 0.0, "south");
        // Rolling right wing down by 20° turns the scanner's right side down: a beam scanned
        // 20° right then points at nadir.
        let q = attitude_quaternion(20.0, 0.0, 0.0);
        let g = georeference(
            &crs(),
            IMU,
            &q,
            [20.0, f32::NAN],
            &mount(),
            (6000.0, 8000.0),
        )
        .unwrap();
        let d = g.geometry.direction;
        assert!(d[0].abs() < 1e-6 && d[1].abs() < 1e-6, "{d:?}");
        // A boresight roll acts like an attitude roll.
        let m = Mounting {
            boresight_deg: [20.0, 0.0, 0.0],
            ..mount()
        };
        let g = georeference(
            &crs(),
            IMU,
            &attitude_quaternion(0.0, 0.0, 0.0),
            [20.0, f32::NAN],
            &m,
            (6000.0, 8000.0),
        )
        .unwrap();
        let d = g.geometry.direction;
        assert!(d[0].abs() < 1e-6 && d[1].abs() < 1e-6, "{d:?}");
    }

    #[test]
    fn lever_arm_is_turned_by_the_attitude() {
        // Scanner 2 m forward of the IMU, heading east: the anchor is 2 m east.
        let m = Mounting {
            lever_arm_m: [2.0, 0.0, 0.0],
            ..mount()
        };
        let q = attitude_quaternion(0.0, 0.0, 90.0);
        let with = georeference(&crs(), IMU, &q, [0.0, f32::NAN], &m, (6000.0, 7000.0)).unwrap();
        let without =
            georeference(&crs(), IMU, &q, [0.0, f32::NAN], &mount(), (6000.0, 7000.0)).unwrap();
        let de = with.geometry.anchor[0] - without.geometry.anchor[0];
        let dn = with.geometry.anchor[1] - without.geometry.anchor[1];
        // Grid distance = 2 m × the UTM scale factor on the central meridian (0.9996).
        assert!(
            (de - 2.0 * 0.9996).abs() < 1e-3 && dn.abs() < 1e-3,
            "{de} {dn}"
        );
    }

    #[test]
    fn the_map_chord_stays_within_millimetres_of_the_beam() {
        // 30° off nadir, banked 10°, 1 km up, a 2 µs window (300 m of beam, far more than a
        // canopy needs) ending near the ground: the chord's worst point is mid-window.
        let q = attitude_quaternion(10.0, 3.0, 47.0);
        let g = georeference(
            &crs(),
            IMU,
            &q,
            [30.0, f32::NAN],
            &mount(),
            (6000.0, 8000.0),
        )
        .unwrap();
        let mid = g.chord_error_m(&crs(), &mount(), 7000.0).unwrap();
        assert!(mid < 0.0015, "{mid} m");
        // A 100 m window (670 ns): a tenth of that (the error goes with the square).
        let g = georeference(
            &crs(),
            IMU,
            &q,
            [30.0, f32::NAN],
            &mount(),
            (7330.0, 8000.0),
        )
        .unwrap();
        let mid = g.chord_error_m(&crs(), &mount(), 7665.0).unwrap();
        assert!(mid < 0.0002, "{mid} m");
        for t in [7330.0, 8000.0] {
            assert!(g.chord_error_m(&crs(), &mount(), t).unwrap() < 1e-6);
        }
    }

    #[test]
    fn footprint_grows_with_range_by_half_the_divergence() {
        // 0.5 mrad at 1000 m (6671 ns two-way in vacuum): a 0.25 m radius, the RIEGL Q680i's
        // nominal 0.5 m footprint.
        let t = 1000.0 / mount().metres_per_ns();
        let r = footprint_radius_m(&mount(), 0.5, 0.0, t);
        assert!((r - 0.25).abs() < 1e-9, "{r}");
        assert_eq!(footprint_radius_m(&mount(), 0.5, 0.01, -5.0), 0.01);
    }

    #[test]
    fn refractive_index_shortens_the_range() {
        let m = Mounting {
            refractive_index: 1.00027,
            ..mount()
        };
        assert!((m.metres_per_ns() - crate::core::units::HALF_C_M_PER_NS / 1.00027).abs() < 1e-9);
    }
}
