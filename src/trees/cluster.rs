//! Clustering and neighbour search for tree reconstruction: DBSCAN (Ester et al. 1996; the
//! seed's fig. 4.2) from `petal-clustering`, ball-tree neighbour queries from `petal-neighbors`,
//! and the point spacing DBSCAN's defaults are derived from.

use std::collections::HashMap;

use ndarray::Array2;
use petal_clustering::{Dbscan, Fit};
use petal_neighbors::BallTree;
use petal_neighbors::distance::Euclidean;

/// Label of a point DBSCAN left out of every cluster.
pub const NOISE: i32 = -1;

fn array(points: &[[f64; 3]]) -> Array2<f64> {
    let mut a = Array2::zeros((points.len(), 3));
    for (i, p) in points.iter().enumerate() {
        a[[i, 0]] = p[0];
        a[[i, 1]] = p[1];
        a[[i, 2]] = p[2];
    }
    a
}

/// DBSCAN of `points` (m): a point with at least `min_points` points (itself included) within
/// `eps_m` is a core point; clusters are the core points reachable from each other and their
/// neighbours. Returns one label per point: clusters numbered 0, 1, … in the order of their
/// first point, [`NOISE`] for the rest. Deterministic.
pub fn dbscan(points: &[[f64; 3]], eps_m: f64, min_points: usize) -> Vec<i32> {
    let mut labels = vec![NOISE; points.len()];
    if points.is_empty() {
        return labels;
    }
    let (clusters, _noise): (HashMap<usize, Vec<usize>>, Vec<usize>) =
        Dbscan::new(eps_m, min_points.max(1), Euclidean::default()).fit(&array(points), None);
    let mut members: Vec<Vec<usize>> = clusters.into_values().collect();
    for m in &mut members {
        m.sort_unstable();
    }
    members.sort_unstable_by_key(|m| m.first().copied().unwrap_or(usize::MAX));
    for (k, m) in members.iter().enumerate() {
        for &i in m {
            labels[i] = k as i32;
        }
    }
    labels
}

/// Number of clusters in DBSCAN labels.
pub fn cluster_count(labels: &[i32]) -> usize {
    labels
        .iter()
        .copied()
        .max()
        .map_or(0, |m| (m + 1).max(0) as usize)
}

/// Points of each cluster (indices), cluster by cluster.
pub fn members(labels: &[i32]) -> Vec<Vec<usize>> {
    let mut out = vec![Vec::new(); cluster_count(labels)];
    for (i, &l) in labels.iter().enumerate() {
        if l >= 0 {
            out[l as usize].push(i);
        }
    }
    out
}

/// A ball tree over points for radius queries.
pub struct Neighbours<'a> {
    tree: Option<BallTree<'a, f64, Euclidean>>,
}

impl Neighbours<'_> {
    /// Indexes `points` (m).
    pub fn new(points: &[[f64; 3]]) -> Neighbours<'static> {
        Neighbours {
            tree: BallTree::new(array(points), Euclidean::default()).ok(),
        }
    }

    /// Indices of the points within `r` m of `p`, `p` itself included when it is one of them.
    pub fn within(&self, p: [f64; 3], r: f64) -> Vec<usize> {
        match &self.tree {
            Some(t) => t.query_radius(&ndarray::arr1(&p), r),
            None => Vec::new(),
        }
    }

    /// Distance to the nearest other point (m), `None` without one.
    pub fn nearest_other(&self, p: [f64; 3]) -> Option<f64> {
        let t = self.tree.as_ref()?;
        let (_, d) = t.query(&ndarray::arr1(&p), 2);
        d.into_iter().find(|d| *d > 0.0)
    }
}

/// The spacing of the beams: the median horizontal distance (m) from each pulse (its points'
/// mean position, the pulses told apart by GPS time) to the nearest other pulse. `None` with
/// fewer than two pulses.
pub fn pulse_spacing(points: &[[f64; 3]], gps_time: &[f64]) -> Option<f64> {
    let mut by_pulse: HashMap<u64, ([f64; 3], usize)> = HashMap::new();
    for (p, t) in points.iter().zip(gps_time) {
        let e = by_pulse.entry(t.to_bits()).or_insert(([0.0; 3], 0));
        e.0[0] += p[0];
        e.0[1] += p[1];
        e.1 += 1;
    }
    let mut centres: Vec<[f64; 3]> = by_pulse
        .into_values()
        .map(|(s, n)| [s[0] / n as f64, s[1] / n as f64, 0.0])
        .collect();
    centres.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
    if centres.len() < 2 {
        return None;
    }
    let nb = Neighbours::new(&centres);
    let mut d: Vec<f64> = centres
        .iter()
        .filter_map(|c| nb.nearest_other(*c))
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f64::total_cmp);
    Some(d[d.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_lines_and_a_stray_point() {
        let mut pts = Vec::new();
        for i in 0..20 {
            pts.push([i as f64 * 0.1, 0.0, 0.0]);
            pts.push([i as f64 * 0.1, 5.0, 1.0]);
        }
        pts.push([50.0, 50.0, 50.0]);
        let l = dbscan(&pts, 0.15, 3);
        assert_eq!(cluster_count(&l), 2);
        assert_eq!(l[0], 0);
        assert_eq!(l[1], 1);
        assert_eq!(*l.last().unwrap(), NOISE);
        assert!(l.iter().step_by(2).take(20).all(|&x| x == 0));
        // Too small a radius: everything is noise.
        assert_eq!(cluster_count(&dbscan(&pts, 0.05, 3)), 0);
    }

    #[test]
    fn spacing_of_a_grid_of_pulses() {
        let mut pts = Vec::new();
        let mut t = Vec::new();
        for i in 0..10 {
            for j in 0..10 {
                for k in 0..3 {
                    pts.push([i as f64 * 0.5, j as f64 * 0.5, k as f64]);
                    t.push((i * 10 + j) as f64);
                }
            }
        }
        let s = pulse_spacing(&pts, &t).unwrap();
        assert!((s - 0.5).abs() < 1e-9, "{s}");
    }
}
