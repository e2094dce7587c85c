//! Stems and first-order branches from waveform points (the seed's chapter 4): ground removed,
//! the optimal intensity threshold chosen from the curve of clusters against threshold (figs.
//! 4.6–4.7), foliage removed by local point geometry, trees found (or given), a stem per tree,
//! DBSCAN of the rest (fig. 4.8), a cylinder per branch cluster reconnected to the stem (figs.
//! 4.3–4.4). `docs/trees.md` explains each step and its defaults.

use std::collections::HashMap;

use crate::trees::TreesError;
use crate::trees::cluster::{NOISE, Neighbours, dbscan, members, pulse_spacing};
use crate::trees::cylinder::{Cylinder, CylinderKind, fit_line, principal_axes};
use crate::trees::points::TreePoint;

/// Share of the most branch-sized clusters at which the threshold curve's plateau starts.
pub const PLATEAU: f64 = 0.9;

/// How the intensity threshold is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Threshold {
    /// The lowest threshold of the scan with [`PLATEAU`] of the most branch-sized clusters.
    Auto,
    /// This signal, V.
    Fixed(f32),
}

/// Options of [`reconstruct`]; [`Default`] gives the documented defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct TreesOptions {
    /// Intensity threshold. Default [`Threshold::Auto`].
    pub threshold: Threshold,
    /// Thresholds scanned by [`Threshold::Auto`]: quantiles `k / steps` of the above-ground
    /// signals for k = 0 .. 0.95 · steps. Default 24.
    pub threshold_steps: usize,
    /// DBSCAN radius, m. Default: 1.5 × the beam spacing, at least 0.3 m.
    pub eps_m: Option<f64>,
    /// DBSCAN core size (points within `eps_m`, the point itself included). Default 5.
    pub min_points: Option<usize>,
    /// Side of the cells the ground is found in, m. Default 2.
    pub ground_cell_m: f64,
    /// Points less than this above the ground are the ground's, m. Default 0.5.
    pub ground_clearance_m: f64,
    /// Stem positions (x, y in the points' CRS) when the trees are known; default: found by
    /// clustering the points seen from above.
    pub stems: Option<Vec<[f64; 2]>>,
    /// Radius of the trees found from above: crowns closer than this are one tree, m.
    /// Default 1.
    pub tree_eps_m: f64,
    /// Points within this horizontal distance of the stem axis are the stem's, m. Default 0.45
    /// (half a 0.3 m footprint, a stem and half the beam spacing).
    pub stem_radius_m: f64,
    /// Least points of a branch cluster. Default 8.
    pub min_branch_points: usize,
    /// Least extent of a branch cluster along its axis, m. Default 0.8.
    pub min_branch_length_m: f64,
    /// Least linearity `(λ1 − λ2)/λ1` of a branch cluster. Default 0.5.
    pub min_linearity: f64,
    /// Foliage filter: a point whose neighbourhood of this radius (m) is a volume rather than a
    /// line or a sheet (scattering `λ3/λ1` above `foliage_max_scattering`) is foliage. 0 turns
    /// the filter off. Default 0.6.
    pub foliage_radius_m: f64,
    /// See `foliage_radius_m`. Default 0.25.
    pub foliage_max_scattering: f64,
}

impl Default for TreesOptions {
    fn default() -> Self {
        TreesOptions {
            threshold: Threshold::Auto,
            threshold_steps: 24,
            eps_m: None,
            min_points: None,
            ground_cell_m: 2.0,
            ground_clearance_m: 0.5,
            stems: None,
            tree_eps_m: 1.0,
            stem_radius_m: 0.45,
            min_branch_points: 8,
            min_branch_length_m: 0.8,
            min_linearity: 0.5,
            foliage_radius_m: 0.6,
            foliage_max_scattering: 0.25,
        }
    }
}

/// What a point became (`part` in `clustered_points.las`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize)]
pub enum Part {
    /// Below the intensity threshold (or unassigned).
    #[default]
    Unused = 0,
    /// Ground (within the clearance of the ground, or below it).
    Ground = 1,
    /// Stem.
    Stem = 2,
    /// A branch cluster that became a cylinder.
    Branch = 3,
    /// Removed as foliage by the local geometry.
    Foliage = 4,
    /// Above the threshold in a tree but in no cylinder (DBSCAN noise, clusters too small or
    /// not line-like).
    Crown = 5,
}

/// One row of the threshold curve.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ThresholdRow {
    /// Threshold, V.
    pub threshold_v: f32,
    /// Quantile of the above-ground signals it is.
    pub quantile: f64,
    /// Points at or above it.
    pub points: usize,
    /// DBSCAN clusters.
    pub clusters: usize,
    /// Clusters of at least `min_branch_points`.
    pub branch_clusters: usize,
    /// Largest cluster's share of the points.
    pub largest_fraction: f64,
}

/// The threshold used and how it was chosen.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ThresholdChoice {
    /// Threshold used, V.
    pub chosen_v: f32,
    /// Why.
    pub reason: String,
    /// The scan (empty for a fixed threshold).
    pub curve: Vec<ThresholdRow>,
}

/// A tree: its stem, branches and where its points went.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TreeModel {
    /// Number of the tree.
    pub id: usize,
    /// Stem base, x and y (CRS units).
    pub position: [f64; 2],
    /// Ground height at the stem, m.
    pub ground_z: f64,
    /// Height of the top above the ground, m.
    pub height_m: f64,
    /// Points of the tree above the threshold (after the foliage filter).
    pub points: usize,
    /// Stem first, then the branches.
    pub cylinders: Vec<Cylinder>,
}

/// Label of one input point.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct PointLabel {
    /// Tree, or −1.
    pub tree: i32,
    /// Cylinder id, or −1.
    pub cluster: i32,
    /// What it became.
    pub part: Part,
}

/// What [`reconstruct`] found.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Reconstruction {
    /// Threshold and its curve.
    pub threshold: ThresholdChoice,
    /// Beam spacing, m (`None` when it could not be measured).
    pub spacing_m: Option<f64>,
    /// DBSCAN radius used, m.
    pub eps_m: f64,
    /// DBSCAN core size used.
    pub min_points: usize,
    /// Input points.
    pub input_points: usize,
    /// Points of the ground.
    pub ground_points: usize,
    /// Points above the ground clearance.
    pub above_ground_points: usize,
    /// Noise level the threshold scan starts from, V (`None`: too few samples below the
    /// ground to measure it).
    pub noise_floor_v: Option<f32>,
    /// Above the threshold.
    pub selected_points: usize,
    /// Removed as foliage.
    pub foliage_points: usize,
    /// Trees.
    pub trees: Vec<TreeModel>,
    /// One label per input point.
    #[serde(skip)]
    pub labels: Vec<PointLabel>,
}

/// Ground height per cell: the lowest height above which at least 3 strong points lie within
/// 0.3 m (strong: at least a fifth of the 99th percentile signal) marks the ground echo's lower
/// edge; the ground is its strongest point within 1.5 m above that edge (the echo's peak, not
/// its edge, which a long pulse puts a metre low). Cells without one are filled from their
/// nearest cells that have one.
struct Ground {
    origin: [f64; 2],
    cell: f64,
    cols: usize,
    rows: usize,
    z: Vec<f64>,
}

impl Ground {
    fn find(points: &[TreePoint], cell: f64) -> Option<Ground> {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in points {
            x0 = x0.min(p.xyz[0]);
            y0 = y0.min(p.xyz[1]);
            x1 = x1.max(p.xyz[0]);
            y1 = y1.max(p.xyz[1]);
        }
        if points.is_empty() || cell.is_nan() || cell <= 0.0 {
            return None;
        }
        let cols = (((x1 - x0) / cell).floor() as usize + 1).min(1 << 14);
        let rows = (((y1 - y0) / cell).floor() as usize + 1).min(1 << 14);
        let mut s: Vec<f32> = points.iter().map(|p| p.signal).collect();
        s.sort_by(f32::total_cmp);
        let strong = 0.2 * s[(s.len() * 99 / 100).min(s.len() - 1)];
        let mut per: Vec<Vec<(f64, f32)>> = vec![Vec::new(); cols * rows];
        let g = Ground {
            origin: [x0, y0],
            cell,
            cols,
            rows,
            z: Vec::new(),
        };
        for p in points.iter().filter(|p| p.signal >= strong) {
            per[g.index(p.xyz[0], p.xyz[1])].push((p.xyz[2], p.signal));
        }
        let mut z: Vec<f64> = per
            .iter_mut()
            .map(|v| {
                v.sort_by(|a, b| a.0.total_cmp(&b.0));
                let Some(edge) = (0..v.len())
                    .find(|&i| v[i..].iter().take_while(|w| w.0 <= v[i].0 + 0.3).count() >= 3)
                else {
                    return f64::NAN;
                };
                v[edge..]
                    .iter()
                    .take_while(|w| w.0 <= v[edge].0 + 1.5)
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .map_or(f64::NAN, |w| w.0)
            })
            .collect();
        if z.iter().all(|v| v.is_nan()) {
            return None;
        }
        // Under a dense crown no ground echo is strong and the lowest strong echo is in the
        // crown: a cell more than 1.5 m above the lowest quarter of its 5 × 5 neighbourhood
        // is taken as having no ground.
        let prev = z.clone();
        for r in 0..rows {
            for c in 0..cols {
                let v = prev[r * cols + c];
                if v.is_nan() {
                    continue;
                }
                let mut near: Vec<f64> = Vec::with_capacity(25);
                for rr in r.saturating_sub(2)..(r + 3).min(rows) {
                    for cc in c.saturating_sub(2)..(c + 3).min(cols) {
                        let w = prev[rr * cols + cc];
                        if !w.is_nan() {
                            near.push(w);
                        }
                    }
                }
                near.sort_by(f64::total_cmp);
                if v > near[near.len() / 4] + 1.5 {
                    z[r * cols + c] = f64::NAN;
                }
            }
        }
        // Fill the gaps ring by ring from the cells that have a ground.
        while z.iter().any(|v| v.is_nan()) {
            let prev = z.clone();
            for r in 0..rows {
                for c in 0..cols {
                    if !prev[r * cols + c].is_nan() {
                        continue;
                    }
                    let mut acc = (0.0, 0);
                    for (dr, dc) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                        let (rr, cc) = (r as i64 + dr, c as i64 + dc);
                        if rr >= 0 && cc >= 0 && (rr as usize) < rows && (cc as usize) < cols {
                            let v = prev[rr as usize * cols + cc as usize];
                            if !v.is_nan() {
                                acc = (acc.0 + v, acc.1 + 1);
                            }
                        }
                    }
                    if acc.1 > 0 {
                        z[r * cols + c] = acc.0 / acc.1 as f64;
                    }
                }
            }
        }
        Some(Ground { z, ..g })
    }

    fn index(&self, x: f64, y: f64) -> usize {
        let c = (((x - self.origin[0]) / self.cell).floor().max(0.0) as usize).min(self.cols - 1);
        let r = (((y - self.origin[1]) / self.cell).floor().max(0.0) as usize).min(self.rows - 1);
        r * self.cols + c
    }

    fn at(&self, x: f64, y: f64) -> f64 {
        self.z[self.index(x, y)]
    }
}

/// Indices of the points of each pulse (told apart by GPS time), in order of first appearance.
fn by_pulse(points: &[TreePoint]) -> Vec<Vec<usize>> {
    let mut slot: HashMap<u64, usize> = HashMap::new();
    let mut out: Vec<Vec<usize>> = Vec::new();
    for (i, p) in points.iter().enumerate() {
        let k = *slot.entry(p.gps_time.to_bits()).or_insert_with(|| {
            out.push(Vec::new());
            out.len() - 1
        });
        out[k].push(i);
    }
    out
}

fn quantile(sorted: &[f32], q: f64) -> f32 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((q * (sorted.len() - 1) as f64).round() as usize).min(sorted.len() - 1)]
}

fn threshold_row(
    xyz: &[[f64; 3]],
    signal: &[f32],
    t: f32,
    q: f64,
    eps: f64,
    min_points: usize,
    min_branch: usize,
) -> ThresholdRow {
    let sel: Vec<[f64; 3]> = xyz
        .iter()
        .zip(signal)
        .filter(|(_, s)| **s >= t)
        .map(|(p, _)| *p)
        .collect();
    let labels = dbscan(&sel, eps, min_points);
    let m = members(&labels);
    let largest = m.iter().map(Vec::len).max().unwrap_or(0);
    ThresholdRow {
        threshold_v: t,
        quantile: q,
        points: sel.len(),
        clusters: m.len(),
        branch_clusters: m.iter().filter(|c| c.len() >= min_branch).count(),
        largest_fraction: if sel.is_empty() {
            0.0
        } else {
            largest as f64 / sel.len() as f64
        },
    }
}

/// Horizontal distance from `p` to the stem line through `base` along `axis` at `p`'s height.
fn stem_distance(base: [f64; 3], axis: [f64; 3], p: [f64; 3]) -> f64 {
    let t = if axis[2].abs() > 1e-6 {
        (p[2] - base[2]) / axis[2]
    } else {
        0.0
    };
    let (sx, sy) = (base[0] + t * axis[0], base[1] + t * axis[1]);
    ((p[0] - sx).powi(2) + (p[1] - sy).powi(2)).sqrt()
}

fn stem_point_at(base: [f64; 3], axis: [f64; 3], z: f64) -> [f64; 3] {
    let t = if axis[2].abs() > 1e-6 {
        (z - base[2]) / axis[2]
    } else {
        0.0
    };
    [base[0] + t * axis[0], base[1] + t * axis[1], z]
}

/// A stem axis: its base on the ground and its unit direction (upward).
struct Stem {
    base: [f64; 3],
    axis: [f64; 3],
}

impl Stem {
    fn vertical(xy: [f64; 2], ground: &Ground) -> Stem {
        Stem {
            base: [xy[0], xy[1], ground.at(xy[0], xy[1])],
            axis: [0.0, 0.0, 1.0],
        }
    }

    /// Points of `idx` within `radius` of the axis. Where they span 2 m of height and come
    /// from 10 echoes or more (an off-nadir view sees the stem's side), the stem is moved to
    /// their median position, twice. The stem stays vertical: seen from above, branch bases
    /// near the stem would tilt a fitted line more than real stems lean.
    fn refine(
        &mut self,
        points: &[TreePoint],
        idx: &[usize],
        ground: &Ground,
        radius: f64,
    ) -> Vec<usize> {
        let mut stem_pts: Vec<usize> = Vec::new();
        for round in 0..3 {
            stem_pts = idx
                .iter()
                .copied()
                .filter(|&i| stem_distance(self.base, self.axis, points[i].xyz) <= radius)
                .collect();
            if round == 2 {
                break;
            }
            let e = echoes(points, &stem_pts);
            let (lo, hi) = e
                .iter()
                .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p[2]), b.max(p[2])));
            if e.len() < 10 || hi - lo < 2.0 {
                break;
            }
            let mut xs: Vec<f64> = e.iter().map(|p| p[0]).collect();
            let mut ys: Vec<f64> = e.iter().map(|p| p[1]).collect();
            xs.sort_by(f64::total_cmp);
            ys.sort_by(f64::total_cmp);
            let (x, y) = (xs[xs.len() / 2], ys[ys.len() / 2]);
            self.base = [x, y, ground.at(x, y)];
        }
        stem_pts
    }
}

/// A branch cluster and the line fitted to its echoes.
struct BranchFit {
    members: Vec<usize>,
    fit: crate::trees::cylinder::LineFit,
}

/// The echoes of a set of points: each pulse's contiguous runs of samples (gaps under 0.3 m)
/// as their signal-weighted centroids. Fitting echoes rather than samples keeps a long pulse's
/// spread along the beam out of a branch's direction.
fn echoes(points: &[TreePoint], members: &[usize]) -> Vec<[f64; 3]> {
    let mut m: Vec<usize> = members.to_vec();
    m.sort_by(|&a, &b| {
        points[a]
            .gps_time
            .total_cmp(&points[b].gps_time)
            .then(points[a].xyz[2].total_cmp(&points[b].xyz[2]))
    });
    let mut out = Vec::new();
    let mut acc = ([0.0f64; 3], 0.0f64);
    let mut prev: Option<&TreePoint> = None;
    for &i in &m {
        let p = &points[i];
        let new_run = prev.is_none_or(|q| q.gps_time != p.gps_time || p.xyz[2] - q.xyz[2] > 0.3);
        if new_run && acc.1 > 0.0 {
            out.push(acc.0.map(|v| v / acc.1));
            acc = ([0.0; 3], 0.0);
        }
        let w = f64::from(p.signal.max(1e-6));
        for k in 0..3 {
            acc.0[k] += w * p.xyz[k];
        }
        acc.1 += w;
        prev = Some(p);
    }
    if acc.1 > 0.0 {
        out.push(acc.0.map(|v| v / acc.1));
    }
    out
}

/// DBSCAN of the tree's points outside the stem, a line through each cluster's echoes; the
/// clusters too small, too short, not line-like, or seen by fewer than 4 echoes are left out.
fn branch_fits(
    points: &[TreePoint],
    idx: &[usize],
    stem: &Stem,
    eps: f64,
    min_points: usize,
    opts: &TreesOptions,
) -> Vec<BranchFit> {
    let rest: Vec<usize> = idx
        .iter()
        .copied()
        .filter(|&i| stem_distance(stem.base, stem.axis, points[i].xyz) > opts.stem_radius_m)
        .collect();
    let rxyz: Vec<[f64; 3]> = rest.iter().map(|&i| points[i].xyz).collect();
    let mut out = Vec::new();
    for m in members(&dbscan(&rxyz, eps, min_points)) {
        if m.len() < opts.min_branch_points {
            continue;
        }
        let members: Vec<usize> = m.iter().map(|&k| rest[k]).collect();
        let e = echoes(points, &members);
        if e.len() < 4 {
            continue;
        }
        let Some(fit) = fit_line(&e) else { continue };
        if fit.t_range[1] - fit.t_range[0] < opts.min_branch_length_m
            || fit.linearity() < opts.min_linearity
        {
            continue;
        }
        out.push(BranchFit { members, fit });
    }
    merge_collinear(points, out)
}

/// Joins branch clusters that are pieces of one branch (a gap in the points broke it): axes
/// within 20° and each centroid within 0.4 m of the other's line. Refits the joined echoes.
fn merge_collinear(points: &[TreePoint], mut fits: Vec<BranchFit>) -> Vec<BranchFit> {
    let off_line = |f: &crate::trees::cylinder::LineFit, p: [f64; 3]| {
        let d = [0, 1, 2].map(|k| p[k] - f.centroid[k]);
        let t = d[0] * f.axis[0] + d[1] * f.axis[1] + d[2] * f.axis[2];
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] - t * t)
            .max(0.0)
            .sqrt()
    };
    'again: loop {
        for i in 0..fits.len() {
            for j in i + 1..fits.len() {
                let (a, b) = (&fits[i].fit, &fits[j].fit);
                let cos =
                    (a.axis[0] * b.axis[0] + a.axis[1] * b.axis[1] + a.axis[2] * b.axis[2]).abs();
                if cos < 20f64.to_radians().cos()
                    || off_line(a, b.centroid) > 0.4
                    || off_line(b, a.centroid) > 0.4
                {
                    continue;
                }
                let mut members = fits[i].members.clone();
                members.extend_from_slice(&fits[j].members);
                let Some(fit) = fit_line(&echoes(points, &members)) else {
                    continue;
                };
                fits[i] = BranchFit { members, fit };
                fits.remove(j);
                continue 'again;
            }
        }
        return fits;
    }
}

/// The point (x, y) nearest, in the least-squares sense, to the horizontal projections of the
/// branch axes: where they meet the stem. `None` with fewer than two branches or nearly
/// parallel ones.
fn meeting_point(fits: &[BranchFit]) -> Option<[f64; 2]> {
    let (mut a11, mut a12, mut a22, mut b1, mut b2, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0, 0);
    for f in fits {
        let (dx, dy) = (f.fit.axis[0], f.fit.axis[1]);
        let h = (dx * dx + dy * dy).sqrt();
        if h < 0.3 {
            continue; // too steep to point anywhere from above
        }
        let (ux, uy) = (dx / h, dy / h);
        // (I − u uᵀ), weighted by the horizontal share of the axis.
        let (m11, m12, m22) = (1.0 - ux * ux, -ux * uy, 1.0 - uy * uy);
        let (cx, cy) = (f.fit.centroid[0], f.fit.centroid[1]);
        a11 += h * m11;
        a12 += h * m12;
        a22 += h * m22;
        b1 += h * (m11 * cx + m12 * cy);
        b2 += h * (m12 * cx + m22 * cy);
        n += 1;
    }
    let det = a11 * a22 - a12 * a12;
    if n < 2 || det.abs() < 1e-3 * (a11 + a22).powi(2) {
        return None;
    }
    Some([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det])
}

impl BranchFit {
    /// The cylinder: outward from the stem, based on the stem at the height where the axis
    /// passes closest to it (fig. 4.4), out to the farthest echo.
    fn cylinder(
        &self,
        stem: &Stem,
        top: f64,
        tree: usize,
        id: usize,
        parent: usize,
    ) -> Option<Cylinder> {
        let f = &self.fit;
        let c = f.centroid;
        let st = stem_point_at(stem.base, stem.axis, c[2]);
        let out = [c[0] - st[0], c[1] - st[1]];
        let flip = f.axis[0] * out[0] + f.axis[1] * out[1] < 0.0;
        let a = if flip { f.axis.map(|v| -v) } else { f.axis };
        let (lo, hi) = if flip {
            (-f.t_range[1], -f.t_range[0])
        } else {
            (f.t_range[0], f.t_range[1])
        };
        let line = |t: f64| [0, 1, 2].map(|k| c[k] + t * a[k]);
        let hxy = a[0] * a[0] + a[1] * a[1];
        let t_star = if hxy > 1e-6 {
            -((c[0] - st[0]) * a[0] + (c[1] - st[1]) * a[1]) / hxy
        } else {
            lo
        };
        let inner = line(t_star.min(lo));
        let start = stem_point_at(stem.base, stem.axis, inner[2].min(top).max(stem.base[2]));
        let end = line(hi);
        let v = [0, 1, 2].map(|k| end[k] - start[k]);
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if len <= 0.0 {
            return None;
        }
        let innermost = line(lo);
        Some(Cylinder {
            tree,
            id,
            parent: Some(parent),
            kind: CylinderKind::Branch,
            start,
            axis: v.map(|x| x / len),
            length_m: len,
            radius_m: f.median_m,
            fit_rms_m: f.rms_m,
            points: self.members.len(),
            reconnect_m: (0..3)
                .map(|k| (innermost[k] - start[k]).powi(2))
                .sum::<f64>()
                .sqrt(),
        })
    }
}

/// Reconstructs every tree in `points` (one CRS, metres).
pub fn reconstruct(
    points: &[TreePoint],
    opts: &TreesOptions,
) -> Result<Reconstruction, TreesError> {
    let n = points.len();
    let mut labels = vec![
        PointLabel {
            tree: -1,
            cluster: -1,
            part: Part::Unused,
        };
        n
    ];
    let ground = Ground::find(points, opts.ground_cell_m).ok_or_else(|| {
        TreesError::Input("no ground found: no cell holds three strong points within 0.3 m".into())
    })?;
    // The noise: samples more than 1 m (at least twice the clearance) below the ground can only
    // be noise (and the ground echo's far tail); the threshold scan starts above the 99.9th
    // percentile of their signal.
    let below = (2.0 * opts.ground_clearance_m).max(1.0);
    let first_floor = noise_floor_of(&noise_below(points, &ground, below, None));
    // 1. Ground off.
    let in_echo = label_ground(
        points,
        &ground,
        opts,
        first_floor.unwrap_or(0.0),
        &mut labels,
    );
    let above: Vec<usize> = (0..n).filter(|&i| labels[i].part != Part::Ground).collect();
    // The noise again, without the ground echoes' lower tails (a long pulse's reaches more
    // than 1 m below the ground).
    let noise_samples = noise_below(points, &ground, below, Some(&in_echo));
    let noise = NoiseFloor {
        floor_v: noise_floor_of(&noise_samples).or(first_floor),
        samples: noise_samples.len(),
        below_m: below,
    };
    let ground_points = n - above.len();
    let xyz: Vec<[f64; 3]> = above.iter().map(|&i| points[i].xyz).collect();
    let signal: Vec<f32> = above.iter().map(|&i| points[i].signal).collect();
    let times: Vec<f64> = above.iter().map(|&i| points[i].gps_time).collect();
    let spacing = pulse_spacing(&xyz, &times);
    let eps = opts
        .eps_m
        .unwrap_or_else(|| (1.5 * spacing.unwrap_or(0.5)).max(0.3));
    let min_points = opts.min_points.unwrap_or(5);
    // 2. The threshold.
    let cluster = Clustering { eps, min_points };
    let threshold = choose_threshold(opts, &xyz, &signal, &noise, cluster)?;
    // 3. Above the threshold, then the foliage filter.
    let sel: Vec<usize> = above
        .iter()
        .copied()
        .filter(|&i| points[i].signal >= threshold.chosen_v)
        .collect();
    let (sel, foliage_points) = foliage_filter(points, sel, opts, &mut labels);
    let selected_points = sel.len();
    // 4. Trees.
    let (positions, per_tree) = find_trees(points, &sel, opts, cluster);
    // 5. Per tree: stem, then branches.
    let fit = TreeFit {
        points,
        opts,
        ground: &ground,
        cluster,
    };
    let mut trees = Vec::new();
    let mut next_id = 0usize;
    for (t, idx) in per_tree.iter().enumerate() {
        if idx.is_empty() {
            continue;
        }
        trees.push(fit.model(t, idx, positions[t], &mut labels, &mut next_id));
    }
    Ok(Reconstruction {
        threshold,
        spacing_m: spacing,
        eps_m: eps,
        min_points,
        input_points: n,
        ground_points,
        above_ground_points: above.len(),
        noise_floor_v: noise.floor_v,
        selected_points,
        foliage_points,
        trees,
        labels,
    })
}

/// The DBSCAN parameters of the clustering steps.
#[derive(Clone, Copy, Debug)]
struct Clustering {
    /// Radius, m.
    eps: f64,
    /// Core size, points.
    min_points: usize,
}

/// The noise below the ground the threshold scan starts from.
struct NoiseFloor {
    /// The 99.9th percentile of its signal, V (`None`: too few samples).
    floor_v: Option<f32>,
    /// Samples it was measured on.
    samples: usize,
    /// How far below the ground they are, at least, m.
    below_m: f64,
}

/// The signals (V, sorted) of the samples more than `below` m under the ground, those in a
/// ground echo (`in_echo`, when given) left out.
fn noise_below(
    points: &[TreePoint],
    ground: &Ground,
    below: f64,
    in_echo: Option<&[bool]>,
) -> Vec<f32> {
    let mut noise: Vec<f32> = points
        .iter()
        .enumerate()
        .filter(|(i, p)| {
            !in_echo.is_some_and(|e| e[*i]) && p.xyz[2] < ground.at(p.xyz[0], p.xyz[1]) - below
        })
        .map(|(_, p)| p.signal)
        .collect();
    noise.sort_by(f32::total_cmp);
    noise
}

/// The 99.9th percentile of `sorted` noise signals (V); `None` with fewer than 100.
fn noise_floor_of(sorted: &[f32]) -> Option<f32> {
    (sorted.len() >= 100).then(|| quantile(sorted, 0.999))
}

/// Step 1, ground off: labels as ground the points below the clearance, and each pulse's ground
/// echo whole — from its peak (the strongest sample within 1 m of the ground) up and down while
/// the signal falls (by more than the noise `tol` (V) it does not rise above the lowest so
/// far), so that a long pulse's tail does not join the stems and branches into one cluster.
/// Returns which points are in a ground echo.
fn label_ground(
    points: &[TreePoint],
    ground: &Ground,
    opts: &TreesOptions,
    tol: f32,
    labels: &mut [PointLabel],
) -> Vec<bool> {
    let mut in_echo = vec![false; points.len()];
    for (i, p) in points.iter().enumerate() {
        if p.xyz[2] - ground.at(p.xyz[0], p.xyz[1]) < opts.ground_clearance_m {
            labels[i].part = Part::Ground;
        }
    }
    for mut idx in by_pulse(points) {
        idx.sort_by(|&a, &b| points[a].xyz[2].total_cmp(&points[b].xyz[2]));
        ground_echo(points, &idx, ground, tol, labels, &mut in_echo);
    }
    in_echo
}

/// One pulse's ground echo (its samples `idx`, sorted by height): from its peak up and down
/// while the signal does not rise by more than `tol` (V) above the lowest so far and the
/// samples are under 0.5 m apart; labelled ground and marked `in_echo`.
fn ground_echo(
    points: &[TreePoint],
    idx: &[usize],
    ground: &Ground,
    tol: f32,
    labels: &mut [PointLabel],
    in_echo: &mut [bool],
) {
    let near = |i: usize| {
        let p = points[i].xyz;
        (p[2] - ground.at(p[0], p[1])).abs() <= 1.0
    };
    let Some(peak) = (0..idx.len())
        .filter(|&k| near(idx[k]))
        .max_by(|&a, &b| points[idx[a]].signal.total_cmp(&points[idx[b]].signal))
    else {
        return;
    };
    let step = |low: f32, k: usize, j: usize| {
        let (a, b) = (&points[idx[k]], &points[idx[j]]);
        b.signal <= low + tol && (b.xyz[2] - a.xyz[2]).abs() < 0.5
    };
    labels[idx[peak]].part = Part::Ground;
    in_echo[idx[peak]] = true;
    for dir in [1i64, -1] {
        let (mut k, mut low) = (peak, points[idx[peak]].signal);
        loop {
            let j = k as i64 + dir;
            if j < 0 || j as usize >= idx.len() || !step(low, k, j as usize) {
                break;
            }
            k = j as usize;
            low = low.min(points[idx[k]].signal);
            labels[idx[k]].part = Part::Ground;
            in_echo[idx[k]] = true;
        }
    }
}

/// Step 2, the threshold (V) on the above-ground points (`xyz`, `signal`): the given one, or the
/// plateau of the threshold curve ([`auto_threshold`]).
fn choose_threshold(
    opts: &TreesOptions,
    xyz: &[[f64; 3]],
    signal: &[f32],
    noise: &NoiseFloor,
    cluster: Clustering,
) -> Result<ThresholdChoice, TreesError> {
    Ok(match opts.threshold {
        Threshold::Fixed(t) => ThresholdChoice {
            chosen_v: t,
            reason: "given".into(),
            curve: Vec::new(),
        },
        Threshold::Auto => auto_threshold(opts, xyz, signal, noise, cluster)?,
    })
}

/// The threshold curve, from the noise floor (or the lowest signal) up to the 95th percentile
/// of the above-ground signal in `threshold_steps` quantile steps, and its plateau's start:
/// the lowest threshold with 90 % of the most branch-sized clusters.
fn auto_threshold(
    opts: &TreesOptions,
    xyz: &[[f64; 3]],
    signal: &[f32],
    noise: &NoiseFloor,
    cluster: Clustering,
) -> Result<ThresholdChoice, TreesError> {
    let noise_floor = noise.floor_v;
    let mut sorted = signal.to_vec();
    sorted.sort_by(f32::total_cmp);
    let steps = opts.threshold_steps.max(2);
    let mut curve: Vec<ThresholdRow> = Vec::new();
    let q0 = noise_floor.map_or(0.0, |f| {
        sorted.partition_point(|s| *s < f) as f64 / sorted.len().max(1) as f64
    });
    for k in 0..=(steps * 95 / 100) {
        let q = q0 + (1.0 - q0) * k as f64 / steps as f64;
        let t = quantile(&sorted, q).max(noise_floor.unwrap_or(f32::MIN));
        if curve.last().is_some_and(|r| r.threshold_v == t) {
            continue;
        }
        curve.push(threshold_row(
            xyz,
            signal,
            t,
            q,
            cluster.eps,
            cluster.min_points,
            opts.min_branch_points,
        ));
    }
    let most = curve
        .iter()
        .map(|r| r.branch_clusters)
        .max()
        .ok_or_else(|| TreesError::Input("no point above the ground".into()))?;
    // The plateau's start: the lowest threshold with 90 % of the most branch-sized
    // clusters. Above it the count creeps up as branches break into pieces while
    // samples are lost.
    let best = curve
        .iter()
        .position(|r| r.branch_clusters as f64 >= PLATEAU * most as f64)
        .unwrap_or(0);
    let r = &curve[best];
    Ok(ThresholdChoice {
        chosen_v: r.threshold_v,
        reason: threshold_reason(opts, r, most, &curve, noise),
        curve,
    })
}

/// Why the automatic threshold is `r` (`most`: the most branch-sized clusters on `curve`).
fn threshold_reason(
    opts: &TreesOptions,
    r: &ThresholdRow,
    most: usize,
    curve: &[ThresholdRow],
    noise: &NoiseFloor,
) -> String {
    let below = noise.below_m;
    format!(
        "the lowest threshold with 90 % of the most clusters of at least {} points \
         ({} of {}) over {} thresholds from {} to the {:.0}th percentile of the \
         above-ground signal: lower thresholds merge branches through foliage and \
         noise, higher ones break them and lose samples",
        opts.min_branch_points,
        r.branch_clusters,
        most,
        curve.len(),
        match noise.floor_v {
            Some(f) => format!(
                "the noise (99.9th percentile of the {} samples more than {below} m \
                 below the ground: {f:.4} V)",
                noise.samples
            ),
            None => "the lowest signal (too few samples below the ground to \
                     measure the noise)"
                .to_string(),
        },
        100.0 * curve.last().map_or(0.0, |r| r.quantile)
    )
}

/// Step 3, the foliage filter: of the selected points `sel`, those whose neighbourhood (within
/// `foliage_radius_m`, at least 6 points) scatters in volume rather than along a line or a
/// plane are labelled foliage and left out. Returns the points kept and the number left out.
fn foliage_filter(
    points: &[TreePoint],
    sel: Vec<usize>,
    opts: &TreesOptions,
    labels: &mut [PointLabel],
) -> (Vec<usize>, usize) {
    let mut foliage_points = 0;
    let active = opts.foliage_radius_m > 0.0 && !sel.is_empty();
    if !active {
        return (sel, foliage_points);
    }
    let sxyz: Vec<[f64; 3]> = sel.iter().map(|&i| points[i].xyz).collect();
    let nb = Neighbours::new(&sxyz);
    let mut keep = Vec::with_capacity(sel.len());
    let mut hood = Vec::new();
    for (k, &i) in sel.iter().enumerate() {
        let near = nb.within(sxyz[k], opts.foliage_radius_m);
        let volume = if near.len() >= 6 {
            hood.clear();
            hood.extend(near.iter().map(|&j| sxyz[j]));
            principal_axes(&hood)
                .is_some_and(|(_, l, _)| l[0] > 0.0 && l[2] / l[0] > opts.foliage_max_scattering)
        } else {
            false
        };
        if volume {
            labels[i].part = Part::Foliage;
            foliage_points += 1;
        } else {
            keep.push(i);
        }
    }
    (keep, foliage_points)
}

/// Step 4, trees: their positions (x, y) and each one's points of `sel` — at the given stems, or
/// found by clustering the points seen from above.
fn find_trees(
    points: &[TreePoint],
    sel: &[usize],
    opts: &TreesOptions,
    cluster: Clustering,
) -> (Vec<[f64; 2]>, Vec<Vec<usize>>) {
    let (positions, tree_of) = match &opts.stems {
        Some(stems) => (stems.clone(), trees_at_stems(points, sel, stems)),
        None => trees_from_clusters(points, sel, opts, cluster),
    };
    let mut per_tree: Vec<Vec<usize>> = vec![Vec::new(); positions.len()];
    for &i in sel {
        if let Some(&t) = tree_of.get(&i) {
            per_tree[t].push(i);
        }
    }
    (positions, per_tree)
}

/// The tree of each point of `sel`: the nearest of the given `stems` (x, y), when within
/// 10 m.
fn trees_at_stems(
    points: &[TreePoint],
    sel: &[usize],
    stems: &[[f64; 2]],
) -> HashMap<usize, usize> {
    let mut tree_of: HashMap<usize, usize> = HashMap::new();
    for &i in sel {
        let p = points[i].xyz;
        let best = stems
            .iter()
            .enumerate()
            .map(|(t, s)| (t, (p[0] - s[0]).powi(2) + (p[1] - s[1]).powi(2)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((t, d2)) = best
            && d2 < 100.0
        {
            tree_of.insert(i, t);
        }
    }
    tree_of
}

/// Trees seen from above: the points of `sel` DBSCAN puts in a cluster (isolated noise left
/// out), flattened and clustered again with `tree_eps_m`; clusters of at least three
/// branches' worth of points are trees, at their centroids. Returns the positions and the
/// tree of each point.
fn trees_from_clusters(
    points: &[TreePoint],
    sel: &[usize],
    opts: &TreesOptions,
    cluster: Clustering,
) -> (Vec<[f64; 2]>, HashMap<usize, usize>) {
    let min_points = cluster.min_points;
    let mut tree_of: HashMap<usize, usize> = HashMap::new();
    let mut positions: Vec<[f64; 2]> = Vec::new();
    let sxyz: Vec<[f64; 3]> = sel.iter().map(|&i| points[i].xyz).collect();
    let l3 = dbscan(&sxyz, cluster.eps, min_points);
    let clustered: Vec<usize> = (0..sel.len()).filter(|&k| l3[k] != NOISE).collect();
    let flat: Vec<[f64; 3]> = clustered
        .iter()
        .map(|&k| [sxyz[k][0], sxyz[k][1], 0.0])
        .collect();
    let sel: Vec<usize> = clustered.iter().map(|&k| sel[k]).collect();
    let l = dbscan(&flat, opts.tree_eps_m, min_points);
    for (t, m) in members(&l)
        .into_iter()
        .filter(|m| m.len() >= 3 * opts.min_branch_points)
        .enumerate()
    {
        let mut c = [0.0, 0.0];
        for &k in &m {
            c[0] += flat[k][0] / m.len() as f64;
            c[1] += flat[k][1] / m.len() as f64;
            tree_of.insert(sel[k], t);
        }
        positions.push(c);
    }
    (positions, tree_of)
}

/// What the per-tree step shares.
struct TreeFit<'a> {
    points: &'a [TreePoint],
    opts: &'a TreesOptions,
    ground: &'a Ground,
    cluster: Clustering,
}

impl TreeFit<'_> {
    /// Step 5, tree `t` (its points `idx`, found at `position`): its stem, then its branches, as
    /// cylinders numbered from `next_id` on; labels its points.
    fn model(
        &self,
        t: usize,
        idx: &[usize],
        position: [f64; 2],
        labels: &mut [PointLabel],
        next_id: &mut usize,
    ) -> TreeModel {
        let points = self.points;
        for &i in idx {
            labels[i].tree = t as i32;
            labels[i].part = Part::Crown;
        }
        let top = idx
            .iter()
            .map(|&i| points[i].xyz[2])
            .fold(f64::MIN, f64::max);
        let (stem, stem_pts, fits) = self.stem_and_branches(idx, position);
        let base = stem.base;
        let height = top - base[2];
        let stem_id = *next_id;
        *next_id += 1;
        let mut cylinders = vec![self.stem_cylinder(t, stem_id, &stem, &stem_pts, height)];
        for &i in &stem_pts {
            labels[i].part = Part::Stem;
            labels[i].cluster = stem_id as i32;
        }
        for bf in fits {
            let Some(c) = bf.cylinder(&stem, top, t, *next_id, stem_id) else {
                continue;
            };
            *next_id += 1;
            for &i in &bf.members {
                labels[i].part = Part::Branch;
                labels[i].cluster = c.id as i32;
            }
            cylinders.push(c);
        }
        TreeModel {
            id: t,
            position: [base[0], base[1]],
            ground_z: base[2],
            height_m: height,
            points: idx.len(),
            cylinders,
        }
    }

    /// The stem of the tree of points `idx` found at `position`: first a vertical line
    /// through the tree's centre; then, where the branches point back to one place, through
    /// that place (the least-squares meeting point of their axes seen from above, within 4 m);
    /// then moved to its points ([`Stem::refine`]). Returns it, its points and the branch fits
    /// around it.
    fn stem_and_branches(
        &self,
        idx: &[usize],
        position: [f64; 2],
    ) -> (Stem, Vec<usize>, Vec<BranchFit>) {
        let (points, opts) = (self.points, self.opts);
        let (eps, min_points) = (self.cluster.eps, self.cluster.min_points);
        let mut stem = Stem::vertical(position, self.ground);
        let first = branch_fits(points, idx, &stem, eps, min_points, opts);
        if opts.stems.is_none()
            && let Some(p) = meeting_point(&first)
            && (p[0] - position[0]).hypot(p[1] - position[1]) < 4.0
        {
            stem = Stem::vertical(p, self.ground);
        }
        let stem_pts = stem.refine(points, idx, self.ground, opts.stem_radius_m);
        let fits = branch_fits(points, idx, &stem, eps, min_points, opts);
        (stem, stem_pts, fits)
    }

    /// The stem's cylinder (number `id` of tree `t`): from its base along its axis to the
    /// tree's `height` (m), its radius the median distance of its points `stem_pts` (m) and
    /// their RMS distance its fit error (m).
    fn stem_cylinder(
        &self,
        t: usize,
        id: usize,
        stem: &Stem,
        stem_pts: &[usize],
        height: f64,
    ) -> Cylinder {
        let (base, axis) = (stem.base, stem.axis);
        let mut radii: Vec<f64> = stem_pts
            .iter()
            .map(|&i| stem_distance(base, axis, self.points[i].xyz))
            .collect();
        radii.sort_by(f64::total_cmp);
        let rms = if radii.is_empty() {
            f64::NAN
        } else {
            (radii.iter().map(|r| r * r).sum::<f64>() / radii.len() as f64).sqrt()
        };
        Cylinder {
            tree: t,
            id,
            parent: None,
            kind: CylinderKind::Stem,
            start: base,
            axis,
            length_m: height / axis[2],
            radius_m: radii.get(radii.len() / 2).copied().unwrap_or(f64::NAN),
            fit_rms_m: rms,
            points: stem_pts.len(),
            reconnect_m: 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A synthetic leaf-off tree seen by vertical beams 0.25 m apart: ground, a stem and three
    /// branches, each beam's points where it crosses them.
    /// (base height, azimuth, zenith, length) of a branch.
    type Truth = (f64, f64, f64, f64);

    fn synthetic() -> (Vec<TreePoint>, Vec<Truth>) {
        let branches = vec![
            // (base height, azimuth, zenith, length)
            (5.0, 30.0, 60.0, 3.0),
            (6.5, 150.0, 55.0, 3.0),
            (8.0, 270.0, 65.0, 2.5),
        ];
        let mut pts = Vec::new();
        let mut t = 0.0;
        for i in -24..=24 {
            for j in -24..=24 {
                let (x, y) = (i as f64 * 0.25, j as f64 * 0.25);
                t += 1.0;
                for k in -1..=1 {
                    pts.push(TreePoint {
                        xyz: [x, y, 0.15 * k as f64],
                        signal: 1.0 - 0.3 * (k as f32).abs(),
                        gps_time: t,
                    });
                }
                for &(h, az, zen, len) in &branches {
                    let (a, z): (f64, f64) = (f64::to_radians(az), f64::to_radians(zen));
                    let d = [z.sin() * a.sin(), z.sin() * a.cos()];
                    // Distance along the branch's horizontal projection and across it.
                    let along = x * d[0] + y * d[1];
                    let across = (x * d[1] - y * d[0]).abs();
                    let reach = len * z.sin();
                    if across < 0.3 && along > 0.3 && along < reach {
                        let zz = h + along / z.tan();
                        for k in -1..=1 {
                            pts.push(TreePoint {
                                xyz: [x, y, zz + 0.15 * k as f64],
                                signal: 0.3 - 0.1 * (k as f32).abs(),
                                gps_time: t,
                            });
                        }
                    }
                }
            }
        }
        (pts, branches)
    }

    #[test]
    fn three_branches_of_a_synthetic_tree() {
        let (pts, truth) = synthetic();
        let r = reconstruct(&pts, &TreesOptions::default()).unwrap();
        assert_eq!(r.trees.len(), 1, "{:?}", r.trees);
        let tree = &r.trees[0];
        let branches: Vec<&Cylinder> = tree
            .cylinders
            .iter()
            .filter(|c| c.kind == CylinderKind::Branch)
            .collect();
        assert_eq!(branches.len(), 3, "{branches:?}");
        for &(h, az, zen, len) in &truth {
            let b = branches
                .iter()
                .min_by(|a, b| {
                    let d = |c: &&&Cylinder| ((c.azimuth_deg() - az + 540.0) % 360.0 - 180.0).abs();
                    d(a).total_cmp(&d(b))
                })
                .unwrap();
            let daz = ((b.azimuth_deg() - az + 540.0) % 360.0 - 180.0).abs();
            assert!(daz < 10.0, "azimuth {} vs {az}", b.azimuth_deg());
            assert!(
                (b.zenith_deg() - zen).abs() < 10.0,
                "zenith {} vs {zen}",
                b.zenith_deg()
            );
            assert!(
                (b.length_m - len).abs() / len < 0.25,
                "length {} vs {len}",
                b.length_m
            );
            assert!((b.start[2] - h).abs() < 0.8, "base {} vs {h}", b.start[2]);
        }
        // Stem near the origin; every branch point labelled with its cylinder.
        assert!(tree.position[0].abs() < 0.5 && tree.position[1].abs() < 0.5);
        assert!(r.labels.iter().filter(|l| l.part == Part::Ground).count() > 2000);
        assert_eq!(
            r.labels.iter().filter(|l| l.part == Part::Branch).count(),
            branches.iter().map(|b| b.points).sum::<usize>()
        );
    }

    #[test]
    fn the_threshold_is_where_the_curve_reaches_its_plateau() {
        let (pts, _) = synthetic();
        let r = reconstruct(&pts, &TreesOptions::default()).unwrap();
        let c = &r.threshold.curve;
        assert!(c.len() >= 2);
        let best = c.iter().map(|r| r.branch_clusters).max().unwrap() as f64;
        let k = c
            .iter()
            .position(|row| row.threshold_v == r.threshold.chosen_v)
            .unwrap();
        assert!(c[k].branch_clusters as f64 >= PLATEAU * best);
        assert!(
            c[..k]
                .iter()
                .all(|row| (row.branch_clusters as f64) < PLATEAU * best)
        );
    }

    #[test]
    fn no_ground_is_a_clear_error() {
        let e = reconstruct(&[], &TreesOptions::default()).unwrap_err();
        assert!(e.to_string().contains("ground"), "{e}");
    }
}
