//! Scoring a reconstruction against the simulator's truth (`<stem>.trees.csv` and
//! `<stem>.branches.csv`, written by `fwlidar simulate`): per first-order branch found or not,
//! its azimuth and zenith (tilt) error and its length error normalised by the true length
//! (the seed's table 4.1 and fig. 4.17); per tree the stem position and height error.
//!
//! Matching: a truth tree takes the nearest reconstructed tree within 2 m (one to one). Within a
//! tree, truth and reconstructed branches are paired greedily by the angle between their axes
//! plus 10° per metre of base-height difference; a pair counts as found when the axes are within
//! 45° and the bases within 2 m of height. The errors are those of the found pairs, so a gross
//! miss shows as "not found", not as a large error.

use std::path::Path;

use crate::trees::TreesError;
use crate::trees::cylinder::CylinderKind;
use crate::trees::reconstruct::Reconstruction;

/// One tree of `<stem>.trees.csv`.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthTree {
    /// `tree_id`.
    pub id: usize,
    /// Stem x, y in the scene's UTM.
    pub xy: [f64; 2],
    /// Height above the terrain, m.
    pub height_m: f64,
}

/// One branch of `<stem>.branches.csv`.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthBranch {
    /// `tree_id`.
    pub tree: usize,
    /// `branch_id`.
    pub id: usize,
    /// Base x, y (UTM) and height above the terrain (m).
    pub base: [f64; 3],
    /// End x, y (UTM) and height above the terrain (m).
    pub end: [f64; 3],
    /// Length, m.
    pub length_m: f64,
}

impl TruthBranch {
    /// Unit axis from base to end (in the UTM grid, so comparable with the reconstruction).
    pub fn axis(&self) -> [f64; 3] {
        let v = [0, 1, 2].map(|k| self.end[k] - self.base[k]);
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
        v.map(|x| x / n)
    }
}

fn read_csv(path: &Path) -> Result<(Vec<String>, Vec<Vec<String>>), TreesError> {
    let text = std::fs::read_to_string(path).map_err(|e| TreesError::Truth {
        path: path.display().to_string(),
        why: e.to_string(),
    })?;
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let header: Vec<String> = lines
        .next()
        .unwrap_or("")
        .split(',')
        .map(|s| s.trim().to_string())
        .collect();
    let rows = lines
        .map(|l| l.split(',').map(|s| s.trim().to_string()).collect())
        .collect();
    Ok((header, rows))
}

fn column(path: &Path, header: &[String], name: &str) -> Result<usize, TreesError> {
    header
        .iter()
        .position(|h| h == name)
        .ok_or_else(|| TreesError::Truth {
            path: path.display().to_string(),
            why: format!("no column \"{name}\""),
        })
}

fn num(path: &Path, row: usize, name: &str, v: Option<&String>) -> Result<f64, TreesError> {
    v.and_then(|s| s.parse::<f64>().ok())
        .filter(|x| x.is_finite())
        .ok_or_else(|| TreesError::Truth {
            path: path.display().to_string(),
            why: format!("row {}: \"{name}\" is not a number", row + 2),
        })
}

/// Reads `<stem>.trees.csv`.
pub fn read_truth_trees(path: &Path) -> Result<Vec<TruthTree>, TreesError> {
    let (h, rows) = read_csv(path)?;
    let [id, x, y, hm] = ["tree_id", "x", "y", "height_m"].map(|c| column(path, &h, c));
    let (id, x, y, hm) = (id?, x?, y?, hm?);
    rows.iter()
        .enumerate()
        .map(|(r, row)| {
            Ok(TruthTree {
                id: num(path, r, "tree_id", row.get(id))? as usize,
                xy: [
                    num(path, r, "x", row.get(x))?,
                    num(path, r, "y", row.get(y))?,
                ],
                height_m: num(path, r, "height_m", row.get(hm))?,
            })
        })
        .collect()
}

/// Reads `<stem>.branches.csv`.
pub fn read_truth_branches(path: &Path) -> Result<Vec<TruthBranch>, TreesError> {
    let (h, rows) = read_csv(path)?;
    let names = [
        "tree_id",
        "branch_id",
        "x",
        "y",
        "base_height_m",
        "end_x",
        "end_y",
        "end_height_m",
        "length_m",
    ];
    let mut c = [0usize; 9];
    for (k, n) in names.iter().enumerate() {
        c[k] = column(path, &h, n)?;
    }
    rows.iter()
        .enumerate()
        .map(|(r, row)| {
            let v = |k: usize| num(path, r, names[k], row.get(c[k]));
            Ok(TruthBranch {
                tree: v(0)? as usize,
                id: v(1)? as usize,
                base: [v(2)?, v(3)?, v(4)?],
                end: [v(5)?, v(6)?, v(7)?],
                length_m: v(8)?,
            })
        })
        .collect()
}

/// How one truth branch fared.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BranchScore {
    /// Truth tree.
    pub tree: usize,
    /// Truth branch.
    pub branch: usize,
    /// True length, m.
    pub length_m: f64,
    /// The cylinder that matched it.
    pub cylinder: Option<usize>,
    /// Reconstructed − true azimuth, degrees in (−180, 180].
    pub azimuth_err_deg: f64,
    /// Reconstructed − true zenith, degrees.
    pub zenith_err_deg: f64,
    /// (Reconstructed − true length) / true length.
    pub length_err_rel: f64,
    /// Reconstructed − true base height above the ground, m.
    pub base_err_m: f64,
}

/// How one truth tree fared.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TreeScore {
    /// Truth tree.
    pub tree: usize,
    /// Reconstructed tree matched to it.
    pub found: Option<usize>,
    /// Horizontal distance of the stem bases, m.
    pub position_err_m: f64,
    /// Reconstructed − true height, m.
    pub height_err_m: f64,
}

/// Medians and counts over the branches longer than 1 m (the aim).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ScoreSummary {
    /// Truth trees, and those matched.
    pub trees: usize,
    /// Truth trees matched to a reconstructed one.
    pub trees_found: usize,
    /// Truth branches longer than 1 m (of all trees).
    pub branches: usize,
    /// Of those, found.
    pub branches_found: usize,
    /// `branches_found / branches`.
    pub found_fraction: f64,
    /// Reconstructed branches that matched no truth branch.
    pub extra_branches: usize,
    /// Median |azimuth error| of the found ones, degrees.
    pub azimuth_err_deg: f64,
    /// Median |zenith error|, degrees.
    pub zenith_err_deg: f64,
    /// Median |length error| / true length.
    pub length_err_rel: f64,
    /// Median |base height error|, m.
    pub base_err_m: f64,
    /// Median stem position error of the found trees, m.
    pub stem_position_err_m: f64,
    /// Median |height error| of the found trees, m.
    pub height_err_m: f64,
}

/// The whole score.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Score {
    /// Summary.
    pub summary: ScoreSummary,
    /// Per truth tree.
    pub trees: Vec<TreeScore>,
    /// Per truth branch.
    pub branches: Vec<BranchScore>,
}

fn median_abs(v: impl Iterator<Item = f64>) -> f64 {
    crate::forest::metrics_plot::median(v.filter(|x| x.is_finite()).map(f64::abs).collect())
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Scores `r` against the truth.
pub fn score(r: &Reconstruction, trees: &[TruthTree], branches: &[TruthBranch]) -> Score {
    // Trees: nearest first, one to one, within 2 m.
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (ti, t) in trees.iter().enumerate() {
        for (ri, m) in r.trees.iter().enumerate() {
            let d = ((t.xy[0] - m.position[0]).powi(2) + (t.xy[1] - m.position[1]).powi(2)).sqrt();
            if d <= 2.0 {
                pairs.push((d, ti, ri));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut tree_match: Vec<Option<usize>> = vec![None; trees.len()];
    let mut taken = vec![false; r.trees.len()];
    for (_, ti, ri) in pairs {
        if tree_match[ti].is_none() && !taken[ri] {
            tree_match[ti] = Some(ri);
            taken[ri] = true;
        }
    }
    let tree_scores: Vec<TreeScore> = trees
        .iter()
        .zip(&tree_match)
        .map(|(t, m)| match m {
            Some(ri) => {
                let mt = &r.trees[*ri];
                TreeScore {
                    tree: t.id,
                    found: Some(mt.id),
                    position_err_m: ((t.xy[0] - mt.position[0]).powi(2)
                        + (t.xy[1] - mt.position[1]).powi(2))
                    .sqrt(),
                    height_err_m: mt.height_m - t.height_m,
                }
            }
            None => TreeScore {
                tree: t.id,
                found: None,
                position_err_m: f64::NAN,
                height_err_m: f64::NAN,
            },
        })
        .collect();
    // Branches, tree by tree.
    let mut scores: Vec<BranchScore> = branches
        .iter()
        .map(|b| BranchScore {
            tree: b.tree,
            branch: b.id,
            length_m: b.length_m,
            cylinder: None,
            azimuth_err_deg: f64::NAN,
            zenith_err_deg: f64::NAN,
            length_err_rel: f64::NAN,
            base_err_m: f64::NAN,
        })
        .collect();
    let mut extra = 0;
    for (ti, t) in trees.iter().enumerate() {
        let Some(ri) = tree_match[ti] else { continue };
        let model = &r.trees[ri];
        let found: Vec<_> = model
            .cylinders
            .iter()
            .filter(|c| c.kind == CylinderKind::Branch)
            .collect();
        let truth: Vec<usize> = (0..branches.len())
            .filter(|&k| branches[k].tree == t.id)
            .collect();
        let mut cand: Vec<(f64, usize, usize)> = Vec::new();
        for &k in &truth {
            let b = &branches[k];
            for (j, c) in found.iter().enumerate() {
                let ang = angle_deg(b.axis(), c.axis);
                let dh = (c.start[2] - model.ground_z) - b.base[2];
                if ang <= 45.0 && dh.abs() <= 2.0 {
                    cand.push((ang + 10.0 * dh.abs(), k, j));
                }
            }
        }
        cand.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut used = vec![false; found.len()];
        for (_, k, j) in cand {
            if scores[k].cylinder.is_some() || used[j] {
                continue;
            }
            used[j] = true;
            let (b, c) = (&branches[k], found[j]);
            let a = b.axis();
            let true_az = a[0].atan2(a[1]).to_degrees();
            let true_zen = a[2].clamp(-1.0, 1.0).acos().to_degrees();
            let s = &mut scores[k];
            s.cylinder = Some(c.id);
            s.azimuth_err_deg = (c.azimuth_deg() - true_az + 540.0).rem_euclid(360.0) - 180.0;
            s.zenith_err_deg = c.zenith_deg() - true_zen;
            s.length_err_rel = (c.length_m - b.length_m) / b.length_m;
            s.base_err_m = (c.start[2] - model.ground_z) - b.base[2];
        }
        extra += used.iter().filter(|u| !**u).count();
    }
    let long: Vec<&BranchScore> = scores.iter().filter(|s| s.length_m > 1.0).collect();
    let found: Vec<&&BranchScore> = long.iter().filter(|s| s.cylinder.is_some()).collect();
    let summary = ScoreSummary {
        trees: trees.len(),
        trees_found: tree_match.iter().filter(|m| m.is_some()).count(),
        branches: long.len(),
        branches_found: found.len(),
        found_fraction: if long.is_empty() {
            f64::NAN
        } else {
            found.len() as f64 / long.len() as f64
        },
        extra_branches: extra,
        azimuth_err_deg: median_abs(found.iter().map(|s| s.azimuth_err_deg)),
        zenith_err_deg: median_abs(found.iter().map(|s| s.zenith_err_deg)),
        length_err_rel: median_abs(found.iter().map(|s| s.length_err_rel)),
        base_err_m: median_abs(found.iter().map(|s| s.base_err_m)),
        stem_position_err_m: median_abs(tree_scores.iter().map(|t| t.position_err_m)),
        height_err_m: median_abs(tree_scores.iter().map(|t| t.height_err_m)),
    };
    Score {
        summary,
        trees: tree_scores,
        branches: scores,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truth_files_with_a_bad_number_name_the_row_and_column() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.branches.csv");
        std::fs::write(
            &p,
            "tree_id,branch_id,x,y,base_height_m,end_x,end_y,end_height_m,azimuth_deg,\
             zenith_deg,length_m,radius_m\n0,0,1,2,3,4,5,6,7,8,oops,0.1\n",
        )
        .unwrap();
        let e = read_truth_branches(&p).unwrap_err().to_string();
        assert!(e.contains("x.branches.csv") && e.contains("row 2") && e.contains("length_m"));
        std::fs::write(&p, "tree_id,x\n").unwrap();
        let e = read_truth_trees(&p).unwrap_err().to_string();
        assert!(e.contains("\"y\""), "{e}");
    }
}
