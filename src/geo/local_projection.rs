//! The map position of an ECEF point from a local quadratic model of the projection instead of
//! an exact conversion per point (`[georeference] projection = "per_span"`).
//!
//! The exact path converts every point ECEF → WGS84 (Heikkinen's closed form: a cube root, five
//! square roots, two arctangents) and then projects it (`proj4rs`: the extended transverse
//! Mercator's series, with its own transcendental functions); a pulse needs two points (its
//! chord). The map (easting, northing, ellipsoidal height, metres) is a smooth function of the
//! ECEF position whose second derivatives are of the order of 1/R (the Earth's radius) and third
//! of 1/R², so within a kilometre of a centre a quadratic model is exact to well under a
//! millimetre (truncation ~ d³/R² ≈ 25 µm at d = 1 km). The model is built from 19 exact
//! conversions (the centre, ± a step along each ECEF axis, and the four diagonal corners of each
//! pair of axes: central differences for the gradient and the Hessian) and rebuilt around the
//! point that first falls beyond [`REACH_M`] of its centre: at 60 m/s and a 540 m swath, every
//! 10–20 s of flight (a few million pulses at 400 kHz), so a point costs a dozen multiply-adds
//! per coordinate. Measured on the survey line against the exact path: docs/navigation.md.

use super::crs::{GeoError, OutputCrs, geodetic_of_ecef};

/// Distance from the model's centre beyond which it is rebuilt, metres (3-D, ECEF).
pub const REACH_M: f64 = 1000.0;

/// Step of the central differences, metres: half the reach (the difference formulas' own error
/// is of the order of step² · third derivative, ~1e-8 m).
const STEP_M: f64 = REACH_M / 2.0;

/// The exact map position of an ECEF point (metres): WGS84 by the closed form, then the
/// projection; easting, northing and ellipsoidal height, metres.
pub fn exact_map_of_ecef(crs: &OutputCrs, x: [f64; 3]) -> Result<[f64; 3], GeoError> {
    let g = geodetic_of_ecef(x)?;
    crs.project(g[0], g[1], g[2])
}

/// A quadratic model of the map position around an ECEF centre (see the module documentation).
#[derive(Clone, Debug, Default)]
pub struct LocalProjection {
    /// The model: None until the first point.
    model: Option<Quadratic>,
    /// Models built (the centre moved on).
    pub rebuilds: u64,
}

/// `f(c + d) ≈ f0 + g·d + ½ dᵀ H d` for each of the three map coordinates.
#[derive(Clone, Debug)]
struct Quadratic {
    /// Centre, ECEF metres.
    centre: [f64; 3],
    /// Map position of the centre: easting, northing, height, metres.
    f0: [f64; 3],
    /// Gradient of each map coordinate along the ECEF axes (dimensionless).
    grad: [[f64; 3]; 3],
    /// Half the Hessian of each map coordinate, in the order xx, yy, zz, xy, xz, yz, per metre
    /// (the off-diagonal terms are whole: they appear twice in dᵀ H d).
    half_hess: [[f64; 6]; 3],
}

impl LocalProjection {
    /// An empty model (built at the first point).
    pub fn new() -> Self {
        Self::default()
    }

    /// The map positions (easting, northing, ellipsoidal height, metres) of two ECEF points
    /// (metres), from the model; rebuilt first around a point beyond [`REACH_M`].
    pub fn map_pair(
        &mut self,
        crs: &OutputCrs,
        a: [f64; 3],
        b: [f64; 3],
    ) -> Result<[[f64; 3]; 2], GeoError> {
        Ok([self.map(crs, a)?, self.map(crs, b)?])
    }

    /// The map position of one ECEF point (see [`LocalProjection::map_pair`]).
    pub fn map(&mut self, crs: &OutputCrs, x: [f64; 3]) -> Result<[f64; 3], GeoError> {
        if !x.iter().all(|v| v.is_finite()) {
            // The exact path says why.
            return exact_map_of_ecef(crs, x);
        }
        let near = self.model.as_ref().is_some_and(|m| {
            let d = sub(x, m.centre);
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= REACH_M * REACH_M
        });
        if !near {
            self.model = Some(Quadratic::around(crs, x)?);
            self.rebuilds += 1;
        }
        let m = self.model.as_ref().expect("built above");
        Ok(m.eval(sub(x, m.centre)))
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

impl Quadratic {
    /// The model around `c` (ECEF metres) from 19 exact conversions.
    fn around(crs: &OutputCrs, c: [f64; 3]) -> Result<Self, GeoError> {
        let s = STEP_M;
        let at = |d: [f64; 3]| exact_map_of_ecef(crs, [c[0] + d[0], c[1] + d[1], c[2] + d[2]]);
        let unit = |axis: usize, v: f64| {
            let mut d = [0.0; 3];
            d[axis] = v;
            d
        };
        let f0 = at([0.0; 3])?;
        let mut plus = [[0.0; 3]; 3];
        let mut minus = [[0.0; 3]; 3];
        for axis in 0..3 {
            plus[axis] = at(unit(axis, s))?;
            minus[axis] = at(unit(axis, -s))?;
        }
        let mut grad = [[0.0; 3]; 3];
        let mut half_hess = [[0.0; 6]; 3];
        for k in 0..3 {
            for axis in 0..3 {
                grad[k][axis] = (plus[axis][k] - minus[axis][k]) / (2.0 * s);
                half_hess[k][axis] = (plus[axis][k] - 2.0 * f0[k] + minus[axis][k]) / (2.0 * s * s);
            }
        }
        for (slot, (i, j)) in [(0usize, 1usize), (0, 2), (1, 2)].into_iter().enumerate() {
            let corner = |si: f64, sj: f64| {
                let mut d = unit(i, si * s);
                d[j] = sj * s;
                at(d)
            };
            let (pp, pm, mp, mm) = (
                corner(1.0, 1.0)?,
                corner(1.0, -1.0)?,
                corner(-1.0, 1.0)?,
                corner(-1.0, -1.0)?,
            );
            for k in 0..3 {
                half_hess[k][3 + slot] = (pp[k] - pm[k] - mp[k] + mm[k]) / (4.0 * s * s);
            }
        }
        Ok(Quadratic {
            centre: c,
            f0,
            grad,
            half_hess,
        })
    }

    /// The model at offset `d` from the centre (metres).
    #[inline]
    fn eval(&self, d: [f64; 3]) -> [f64; 3] {
        let sq = [
            d[0] * d[0],
            d[1] * d[1],
            d[2] * d[2],
            d[0] * d[1],
            d[0] * d[2],
            d[1] * d[2],
        ];
        let mut out = [0.0; 3];
        for (k, o) in out.iter_mut().enumerate() {
            let g = &self.grad[k];
            let h = &self.half_hess[k];
            let linear = g[0] * d[0] + g[1] * d[1] + g[2] * d[2];
            let quadratic = h[0] * sq[0]
                + h[1] * sq[1]
                + h[2] * sq[2]
                + h[3] * sq[3]
                + h[4] * sq[4]
                + h[5] * sq[5];
            *o = self.f0[k] + (linear + quadratic);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::crs::ecef_of;

    /// Points on and above the ground within the reach of a centre (a 2 km cube around a point
    /// 1000 m below an aircraft) map within a tenth of a millimetre of the exact path.
    #[test]
    fn the_model_agrees_with_the_exact_path_within_its_reach() {
        let crs = OutputCrs::from_epsg(32736).unwrap();
        let mut local = LocalProjection::new();
        let mut worst = 0.0f64;
        for (lat, lon) in [(-24.99, 31.587), (-60.0, 30.0), (0.01, 35.9)] {
            let c = ecef_of(lat, lon, 100.0).unwrap();
            local.map(&crs, c).unwrap();
            for i in 0..=8 {
                for j in 0..=8 {
                    for k in 0..=4 {
                        let d = [
                            (i as f64 - 4.0) * 140.0,
                            (j as f64 - 4.0) * 140.0,
                            (k as f64 - 2.0) * 140.0,
                        ];
                        let x = [c[0] + d[0], c[1] + d[1], c[2] + d[2]];
                        let exact = exact_map_of_ecef(&crs, x).unwrap();
                        let got = local.map(&crs, x).unwrap();
                        for a in 0..3 {
                            worst = worst.max((got[a] - exact[a]).abs());
                        }
                    }
                }
            }
        }
        assert!(worst < 1e-4, "{worst} m");
        assert_eq!(local.rebuilds, 3, "one model per centre");
    }

    #[test]
    fn a_point_beyond_the_reach_rebuilds_and_stays_exact_there() {
        let crs = OutputCrs::from_epsg(32736).unwrap();
        let mut local = LocalProjection::new();
        let a = ecef_of(-25.0, 31.5, 0.0).unwrap();
        let b = ecef_of(-25.1, 31.5, 0.0).unwrap();
        let [pa, pb] = local.map_pair(&crs, a, b).unwrap();
        assert_eq!(local.rebuilds, 2);
        // Each centre is an exact conversion.
        assert_eq!(pa, exact_map_of_ecef(&crs, a).unwrap());
        assert_eq!(pb, exact_map_of_ecef(&crs, b).unwrap());
        assert!(local.map(&crs, [f64::NAN, 0.0, 0.0]).is_err());
    }
}
