//! Cylinders of a reconstructed tree (the seed's fig. 4.3: a first-order branch is a cylinder of
//! length L leaving the stem at zenith θ and an azimuth) and the line fit they come from.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

/// What a cylinder stands for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CylinderKind {
    /// The stem, from the ground to the top of the tree.
    Stem,
    /// A first-order branch, from the stem outward.
    Branch,
}

impl CylinderKind {
    /// Name in `cylinders.csv`.
    pub fn name(self) -> &'static str {
        match self {
            CylinderKind::Stem => "stem",
            CylinderKind::Branch => "branch",
        }
    }
}

/// One cylinder of a tree model.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Cylinder {
    /// Tree it belongs to.
    pub tree: usize,
    /// Number across the whole output (the `cluster` of its points in `clustered_points.las`).
    pub id: usize,
    /// The cylinder it grows from (`None` for a stem).
    pub parent: Option<usize>,
    /// Stem or branch.
    pub kind: CylinderKind,
    /// Centre of its base, CRS units (m).
    pub start: [f64; 3],
    /// Unit vector along its axis, from the base.
    pub axis: [f64; 3],
    /// Length along the axis, m.
    pub length_m: f64,
    /// Median distance of its points from the axis, m: an upper bound of the radius, since an
    /// airborne footprint (~0.5 m) is wider than a stem or branch.
    pub radius_m: f64,
    /// Root mean square distance of its points from the axis, m.
    pub fit_rms_m: f64,
    /// Points it was fitted to.
    pub points: usize,
    /// Gap bridged to reach its parent (fig. 4.4), m: from the base to its innermost point.
    pub reconnect_m: f64,
}

impl Cylinder {
    /// Centre of its far end.
    pub fn end(&self) -> [f64; 3] {
        [0, 1, 2].map(|k| self.start[k] + self.length_m * self.axis[k])
    }
    /// Azimuth of the axis, degrees clockwise from grid north, 0..360.
    pub fn azimuth_deg(&self) -> f64 {
        self.axis[0]
            .atan2(self.axis[1])
            .to_degrees()
            .rem_euclid(360.0)
    }
    /// Zenith of the axis, degrees from vertical (0: straight up).
    pub fn zenith_deg(&self) -> f64 {
        self.axis[2].clamp(-1.0, 1.0).acos().to_degrees()
    }
}

/// A straight line fitted to points by principal components.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineFit {
    /// Mean of the points.
    pub centroid: [f64; 3],
    /// Unit direction of largest spread (sign arbitrary).
    pub axis: [f64; 3],
    /// Smallest and largest position of a point along the axis from the centroid, m.
    pub t_range: [f64; 2],
    /// Root mean square distance from the axis, m.
    pub rms_m: f64,
    /// Median distance from the axis, m.
    pub median_m: f64,
    /// Eigenvalues of the covariance, largest first, m².
    pub eigen: [f64; 3],
}

impl LineFit {
    /// Linearity `(λ1 − λ2) / λ1`: 1 for points on a line, 0 for a ball or a disc.
    pub fn linearity(&self) -> f64 {
        if self.eigen[0] > 0.0 {
            (self.eigen[0] - self.eigen[1]) / self.eigen[0]
        } else {
            0.0
        }
    }
    /// Point of the line at `t` m from the centroid.
    pub fn at(&self, t: f64) -> [f64; 3] {
        [0, 1, 2].map(|k| self.centroid[k] + t * self.axis[k])
    }
}

/// Mean, eigenvalues (largest first) and matching unit eigenvectors of a point set.
pub type PrincipalAxes = ([f64; 3], [f64; 3], [[f64; 3]; 3]);

/// Covariance eigen-decomposition of `points` (centred on their mean): mean, eigenvalues
/// largest first and the matching unit eigenvectors. `None` with fewer than 2 points.
pub fn principal_axes(points: &[[f64; 3]]) -> Option<PrincipalAxes> {
    if points.len() < 2 {
        return None;
    }
    let n = points.len() as f64;
    let mut c = [0.0; 3];
    for p in points {
        for k in 0..3 {
            c[k] += p[k] / n;
        }
    }
    let mut m = Matrix3::zeros();
    for p in points {
        let d = Vector3::new(p[0] - c[0], p[1] - c[1], p[2] - c[2]);
        m += d * d.transpose();
    }
    m /= n;
    let e = SymmetricEigen::new(m);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| e.eigenvalues[b].total_cmp(&e.eigenvalues[a]));
    let vals = order.map(|i| e.eigenvalues[i].max(0.0));
    let vecs = order.map(|i| {
        let v = e.eigenvectors.column(i);
        [v[0], v[1], v[2]]
    });
    Some((c, vals, vecs))
}

/// Fits a line to `points` (m). `None` with fewer than 2 points or all at one place.
pub fn fit_line(points: &[[f64; 3]]) -> Option<LineFit> {
    let (c, vals, vecs) = principal_axes(points)?;
    if vals[0] <= 0.0 {
        return None;
    }
    let a = vecs[0];
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut d2 = Vec::with_capacity(points.len());
    for p in points {
        let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
        let t = d[0] * a[0] + d[1] * a[1] + d[2] * a[2];
        lo = lo.min(t);
        hi = hi.max(t);
        d2.push((d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - t * t).max(0.0));
    }
    let rms = (d2.iter().sum::<f64>() / d2.len() as f64).sqrt();
    d2.sort_by(f64::total_cmp);
    Some(LineFit {
        centroid: c,
        axis: a,
        t_range: [lo, hi],
        rms_m: rms,
        median_m: d2[d2.len() / 2].sqrt(),
        eigen: vals,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tilted_line_is_found_with_its_extent() {
        // 3 m long, 60° from vertical, azimuth 120°, with a ±2 cm wobble.
        let (z, a) = (60f64.to_radians(), 120f64.to_radians());
        let dir = [z.sin() * a.sin(), z.sin() * a.cos(), z.cos()];
        let pts: Vec<[f64; 3]> = (0..=30)
            .map(|i| {
                let t = i as f64 * 0.1;
                let w = if i % 2 == 0 { 0.02 } else { -0.02 };
                [10.0 + t * dir[0] + w, 20.0 + t * dir[1], 5.0 + t * dir[2]]
            })
            .collect();
        let f = fit_line(&pts).unwrap();
        let cos = (f.axis[0] * dir[0] + f.axis[1] * dir[1] + f.axis[2] * dir[2]).abs();
        assert!(cos > 0.9995, "{cos}");
        assert!((f.t_range[1] - f.t_range[0] - 3.0).abs() < 0.02);
        assert!(f.rms_m < 0.03 && f.linearity() > 0.99);
        let c = Cylinder {
            tree: 0,
            id: 0,
            parent: None,
            kind: CylinderKind::Branch,
            start: [0.0; 3],
            axis: dir,
            length_m: 3.0,
            radius_m: 0.1,
            fit_rms_m: 0.0,
            points: 1,
            reconnect_m: 0.0,
        };
        assert!((c.azimuth_deg() - 120.0).abs() < 1e-9);
        assert!((c.zenith_deg() - 60.0).abs() < 1e-9);
        assert!((c.end()[2] - 1.5).abs() < 1e-9);
    }

    #[test]
    fn a_ball_is_not_a_line() {
        let mut pts = Vec::new();
        for i in -3..=3 {
            for j in -3..=3 {
                for k in -3..=3 {
                    pts.push([i as f64, j as f64, k as f64]);
                }
            }
        }
        assert!(fit_line(&pts).unwrap().linearity() < 0.01);
        assert!(fit_line(&[[1.0, 1.0, 1.0]; 4]).is_none());
    }
}
