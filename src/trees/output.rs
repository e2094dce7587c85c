//! What `fwlidar trees` writes: the cylinder table (`cylinders.csv`), a mesh of the cylinders
//! (`cylinders.ply`), the points with their cluster (`clustered_points.las`), the threshold
//! curve (`threshold.csv`, `threshold.svg`) and, with a truth, the scores (`scores.csv`).
//! Column by column in `docs/trees.md`.

use std::fmt::Write as _;
use std::path::Path;

use crate::format::las_points::{PointSix, write_point_cloud};
use crate::format::las_write::ExtraDim;
use crate::trees::TreesError;
use crate::trees::points::TreePoint;
use crate::trees::reconstruct::{Part, Reconstruction};
use crate::trees::score::Score;

/// Header of `cylinders.csv`.
pub const CYLINDERS_HEADER: &str = "tree_id,cylinder_id,parent_id,kind,start_x,start_y,start_z,\
axis_x,axis_y,axis_z,length_m,radius_m,azimuth_deg,zenith_deg,base_height_m,fit_rms_m,points,\
reconnect_m";

/// Sides of the prism a cylinder is drawn as in the PLY mesh.
pub const MESH_SIDES: usize = 12;

fn write(path: &Path, text: &str) -> Result<(), TreesError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".partial");
    let tmp = std::path::PathBuf::from(tmp);
    std::fs::write(&tmp, text)
        .and_then(|_| std::fs::rename(&tmp, path))
        .map_err(|e| TreesError::Write {
            path: path.display().to_string(),
            why: e.to_string(),
        })
}

fn num(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else {
        String::new()
    }
}

/// The cylinder table: one row per cylinder (stem first, then its branches, tree by tree).
pub fn cylinders_csv(r: &Reconstruction) -> String {
    let mut s = String::from(CYLINDERS_HEADER);
    s.push('\n');
    for t in &r.trees {
        for c in &t.cylinders {
            let _ = writeln!(
                s,
                "{},{},{},{},{:.3},{:.3},{:.3},{:.5},{:.5},{:.5},{:.3},{},{:.2},{:.2},{:.3},{},{},{:.3}",
                c.tree,
                c.id,
                c.parent.map_or(-1, |p| p as i64),
                c.kind.name(),
                c.start[0],
                c.start[1],
                c.start[2],
                c.axis[0],
                c.axis[1],
                c.axis[2],
                c.length_m,
                num(c.radius_m, 3),
                c.azimuth_deg(),
                c.zenith_deg(),
                c.start[2] - t.ground_z,
                num(c.fit_rms_m, 3),
                c.points,
                c.reconnect_m
            );
        }
    }
    s
}

/// The cylinders as an ASCII PLY mesh: each a prism of [`MESH_SIDES`] sides with capped ends;
/// vertices in double precision (map coordinates need it), faces carry their `cylinder` id.
/// Radii that could not be measured are drawn at 5 cm.
pub fn cylinders_ply(r: &Reconstruction) -> String {
    let cyl: Vec<_> = r.trees.iter().flat_map(|t| t.cylinders.iter()).collect();
    let per_v = 2 * MESH_SIDES + 2;
    let per_f = 3 * MESH_SIDES;
    let mut s = String::new();
    let _ = write!(
        s,
        "ply\nformat ascii 1.0\ncomment fwlidar trees: stems and first-order branches as \
         cylinders\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\n\
         element face {}\nproperty list uchar int vertex_indices\nproperty int cylinder\n\
         end_header\n",
        cyl.len() * per_v,
        cyl.len() * per_f
    );
    for c in &cyl {
        let a = c.axis;
        let e = if a[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let cross = |u: [f64; 3], v: [f64; 3]| {
            [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ]
        };
        let u = cross(a, e);
        let un = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
        let u = u.map(|x| x / un);
        let v = cross(a, u);
        let rad = if c.radius_m.is_finite() && c.radius_m > 0.0 {
            c.radius_m
        } else {
            0.05
        };
        let end = c.end();
        for centre in [c.start, end] {
            for k in 0..MESH_SIDES {
                let ang = std::f64::consts::TAU * k as f64 / MESH_SIDES as f64;
                let (cs, sn) = (ang.cos() * rad, ang.sin() * rad);
                let _ = writeln!(
                    s,
                    "{:.4} {:.4} {:.4}",
                    centre[0] + cs * u[0] + sn * v[0],
                    centre[1] + cs * u[1] + sn * v[1],
                    centre[2] + cs * u[2] + sn * v[2]
                );
            }
        }
        for centre in [c.start, end] {
            let _ = writeln!(s, "{:.4} {:.4} {:.4}", centre[0], centre[1], centre[2]);
        }
    }
    for (i, c) in cyl.iter().enumerate() {
        let o = i * per_v;
        let (bc, tc) = (o + 2 * MESH_SIDES, o + 2 * MESH_SIDES + 1);
        for k in 0..MESH_SIDES {
            let k1 = (k + 1) % MESH_SIDES;
            let _ = writeln!(
                s,
                "4 {} {} {} {} {}",
                o + k,
                o + k1,
                o + MESH_SIDES + k1,
                o + MESH_SIDES + k,
                c.id
            );
            let _ = writeln!(s, "3 {} {} {} {}", bc, o + k1, o + k, c.id);
            let _ = writeln!(
                s,
                "3 {} {} {} {}",
                tc,
                o + MESH_SIDES + k,
                o + MESH_SIDES + k1,
                c.id
            );
        }
    }
    s
}

/// The threshold curve as CSV.
pub fn threshold_csv(r: &Reconstruction) -> String {
    let mut s = String::from(
        "threshold_v,quantile,points,clusters,branch_clusters,largest_fraction,chosen\n",
    );
    for row in &r.threshold.curve {
        let _ = writeln!(
            s,
            "{},{:.4},{},{},{},{:.4},{}",
            row.threshold_v,
            row.quantile,
            row.points,
            row.clusters,
            row.branch_clusters,
            row.largest_fraction,
            u8::from(row.threshold_v == r.threshold.chosen_v)
        );
    }
    s
}

/// The threshold curve as an SVG figure: clusters of branch size and all clusters against the
/// threshold, the chosen one marked.
pub fn threshold_svg(r: &Reconstruction) -> String {
    let c = &r.threshold.curve;
    let (w, h, ml, mr, mt, mb) = (640.0, 400.0, 64.0, 24.0, 48.0, 56.0);
    let tmax = c
        .iter()
        .map(|r| f64::from(r.threshold_v))
        .fold(1e-12, f64::max);
    let ymax = c.iter().map(|r| r.clusters).max().unwrap_or(1).max(1) as f64;
    let x = |t: f64| ml + (w - ml - mr) * t / tmax;
    let y = |v: f64| h - mb - (h - mt - mb) * v / ymax;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" \
         font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" \
         fill=\"white\"/>\n<text x=\"{ml}\" y=\"20\" font-size=\"14\">Intensity threshold \
         for clustering: {:.4} V chosen ({} points above it)</text>\n",
        r.threshold.chosen_v, r.selected_points
    );
    let _ = writeln!(
        s,
        "<line x1=\"{ml}\" y1=\"{0}\" x2=\"{1}\" y2=\"{0}\" stroke=\"black\"/><line x1=\"{ml}\" \
         y1=\"{mt}\" x2=\"{ml}\" y2=\"{0}\" stroke=\"black\"/>",
        h - mb,
        w - mr
    );
    for k in 0..=4 {
        let t = tmax * k as f64 / 4.0;
        let v = ymax * k as f64 / 4.0;
        let _ = writeln!(
            s,
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{t:.3}</text><text x=\"{:.1}\" \
             y=\"{:.1}\" text-anchor=\"end\">{v:.0}</text>",
            x(t),
            h - mb + 16.0,
            ml - 6.0,
            y(v) + 4.0
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">threshold (V, processed signal)\
         </text><text x=\"16\" y=\"{:.1}\" transform=\"rotate(-90 16 {:.1})\" \
         text-anchor=\"middle\">DBSCAN clusters</text>",
        (ml + w - mr) / 2.0,
        h - 16.0,
        (mt + h - mb) / 2.0,
        (mt + h - mb) / 2.0
    );
    for (name, colour, get) in [
        (
            "all clusters",
            "#999999",
            (|r: &crate::trees::reconstruct::ThresholdRow| r.clusters) as fn(&_) -> usize,
        ),
        (
            "clusters of branch size",
            "#1f77b4",
            |r: &crate::trees::reconstruct::ThresholdRow| r.branch_clusters,
        ),
    ] {
        let pts: Vec<String> = c
            .iter()
            .map(|r| format!("{:.1},{:.1}", x(f64::from(r.threshold_v)), y(get(r) as f64)))
            .collect();
        let _ = writeln!(
            s,
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-width=\"2\" points=\"{}\"><title>\
             {name}</title></polyline>",
            pts.join(" ")
        );
    }
    if let Some(f) = r.noise_floor_v {
        let xf = x(f64::from(f));
        let _ = writeln!(
            s,
            "<line x1=\"{xf:.1}\" y1=\"{mt}\" x2=\"{xf:.1}\" y2=\"{}\" stroke=\"#555555\" \
             stroke-dasharray=\"1 3\"/>\n<text x=\"{:.1}\" y=\"{:.1}\" fill=\"#555555\" \
             text-anchor=\"end\">noise floor</text>",
            h - mb,
            xf - 4.0,
            h - mb - 6.0
        );
    }
    let xc = x(f64::from(r.threshold.chosen_v));
    let _ = writeln!(
        s,
        "<line x1=\"{xc:.1}\" y1=\"{mt}\" x2=\"{xc:.1}\" y2=\"{}\" stroke=\"#d62728\" \
         stroke-dasharray=\"4 3\"/>\n<text x=\"{:.1}\" y=\"{:.1}\" fill=\"#d62728\" \
         text-anchor=\"{}\">chosen</text>",
        h - mb,
        if xc > w / 2.0 { xc - 4.0 } else { xc + 4.0 },
        mt + 12.0,
        if xc > w / 2.0 { "end" } else { "start" }
    );
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"38\" fill=\"#1f77b4\" text-anchor=\"end\">clusters of branch size\
         </text><text x=\"{:.1}\" y=\"38\" fill=\"#999999\" text-anchor=\"end\">all clusters\
         </text>\n</svg>",
        w - mr,
        w - mr - 160.0
    );
    s
}

/// A picture of the reconstruction: a top view (x, y) and a side view looking north (x, z) of
/// the samples above the threshold (stem and branch samples coloured by cylinder, the rest
/// grey, at most 6 000 drawn), the cylinders as thick lines, and with a truth its branches as
/// thin black lines (heights above the reconstruction's mean ground).
pub fn trees_svg(
    points: &[TreePoint],
    r: &Reconstruction,
    truth: Option<&[crate::trees::score::TruthBranch]>,
) -> String {
    const PALETTE: [&str; 10] = [
        "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf",
        "#bcbd22", "#7f7f7f",
    ];
    let shown: Vec<usize> = (0..points.len())
        .filter(|&i| !matches!(r.labels[i].part, Part::Unused | Part::Ground))
        .collect();
    let ground = if r.trees.is_empty() {
        0.0
    } else {
        r.trees.iter().map(|t| t.ground_z).sum::<f64>() / r.trees.len() as f64
    };
    let mut segs: Vec<([f64; 3], [f64; 3], &str, f64)> = Vec::new();
    for t in &r.trees {
        for c in &t.cylinders {
            segs.push((c.start, c.end(), PALETTE[c.id % PALETTE.len()], 3.0));
        }
    }
    if let Some(tb) = truth {
        for b in tb {
            segs.push((
                [b.base[0], b.base[1], b.base[2] + ground],
                [b.end[0], b.end[1], b.end[2] + ground],
                "#000000",
                1.0,
            ));
        }
    }
    let mut lo = [f64::MAX; 3];
    let mut hi = [f64::MIN; 3];
    let mut grow = |p: [f64; 3]| {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    };
    for &i in &shown {
        grow(points[i].xyz);
    }
    for (a, b, _, _) in &segs {
        grow(*a);
        grow(*b);
    }
    if shown.is_empty() && segs.is_empty() {
        lo = [0.0; 3];
        hi = [1.0; 3];
    }
    let (pw, ph, m) = (440.0, 440.0, 40.0);
    let span_xy = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-6);
    let span_xz = (hi[0] - lo[0]).max(hi[2] - lo[2]).max(1e-6);
    let top = |p: [f64; 3]| {
        (
            m + (pw - 2.0 * m) * (p[0] - lo[0]) / span_xy,
            ph - m - (ph - 2.0 * m) * (p[1] - lo[1]) / span_xy,
        )
    };
    let side = |p: [f64; 3]| {
        (
            pw + m + (pw - 2.0 * m) * (p[0] - lo[0]) / span_xz,
            ph - m - (ph - 2.0 * m) * (p[2] - lo[2]) / span_xz,
        )
    };
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{}\" height=\"{}\" \
         font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" \
         fill=\"white\"/>\n<text x=\"{m}\" y=\"20\" font-size=\"14\">{} trees, {} cylinders; \
         top view (left, {:.1} m across) and side view looking north (right, {:.1} m)</text>\n",
        2.0 * pw,
        ph + 20.0,
        r.trees.len(),
        r.trees.iter().map(|t| t.cylinders.len()).sum::<usize>(),
        span_xy,
        span_xz
    );
    let stride = shown.len().div_ceil(6000).max(1);
    for &i in shown.iter().step_by(stride) {
        let l = r.labels[i];
        let colour = if matches!(l.part, Part::Stem | Part::Branch) && l.cluster >= 0 {
            PALETTE[l.cluster as usize % PALETTE.len()]
        } else {
            "#cccccc"
        };
        for (x, y) in [top(points[i].xyz), side(points[i].xyz)] {
            let _ = writeln!(
                s,
                "<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"1.2\" fill=\"{colour}\"/>"
            );
        }
    }
    for (a, b, colour, wdt) in &segs {
        for f in [&top as &dyn Fn([f64; 3]) -> (f64, f64), &side] {
            let ((x1, y1), (x2, y2)) = (f(*a), f(*b));
            let _ = writeln!(
                s,
                "<line x1=\"{x1:.1}\" y1=\"{y1:.1}\" x2=\"{x2:.1}\" y2=\"{y2:.1}\" \
                 stroke=\"{colour}\" stroke-width=\"{wdt}\" stroke-linecap=\"round\"/>"
            );
        }
    }
    let _ = writeln!(
        s,
        "<text x=\"{m}\" y=\"{}\">thick: reconstructed cylinders (colour = cylinder){}; \
         dots: samples above the threshold (grey: in no cylinder)</text>\n</svg>",
        ph + 10.0,
        if truth.is_some() {
            "; thin black: the scene's branches"
        } else {
            ""
        }
    );
    s
}

/// The scores, one row per truth branch.
pub fn scores_csv(score: &Score) -> String {
    let mut s = String::from(
        "tree_id,branch_id,length_m,found,cylinder_id,azimuth_err_deg,zenith_err_deg,\
         length_err_rel,base_err_m\n",
    );
    for b in &score.branches {
        let _ = writeln!(
            s,
            "{},{},{:.3},{},{},{},{},{},{}",
            b.tree,
            b.branch,
            b.length_m,
            u8::from(b.cylinder.is_some()),
            b.cylinder.map_or(String::new(), |c| c.to_string()),
            num(b.azimuth_err_deg, 2),
            num(b.zenith_err_deg, 2),
            num(b.length_err_rel, 4),
            num(b.base_err_m, 3)
        );
    }
    s
}

/// Writes every product into `dir`.
pub fn write_all(
    dir: &Path,
    points: &[TreePoint],
    crs_wkt: Option<&str>,
    r: &Reconstruction,
    score: Option<&Score>,
    truth: Option<&[crate::trees::score::TruthBranch]>,
) -> Result<(), TreesError> {
    write(&dir.join("cylinders.csv"), &cylinders_csv(r))?;
    write(&dir.join("trees.svg"), &trees_svg(points, r, truth))?;
    write(&dir.join("cylinders.ply"), &cylinders_ply(r))?;
    write(&dir.join("threshold.csv"), &threshold_csv(r))?;
    if !r.threshold.curve.is_empty() {
        write(&dir.join("threshold.svg"), &threshold_svg(r))?;
    }
    if let Some(sc) = score {
        write(&dir.join("scores.csv"), &scores_csv(sc))?;
    }
    let extra = [
        ExtraDim::f32("signal", "processed signal (V)"),
        ExtraDim::i32("cluster", "cylinder id, -1 none"),
        ExtraDim::i32("tree", "tree id, -1 none"),
        ExtraDim::i32("part", "1 grnd 2 stem 3 branch 4 foliage"),
    ];
    let las = dir.join("clustered_points.las");
    write_point_cloud(
        &las,
        crs_wkt,
        &extra,
        points.iter().zip(&r.labels).map(|(p, l)| {
            (
                PointSix {
                    xyz: p.xyz,
                    gps_time: p.gps_time,
                    intensity: (f64::from(p.signal).max(0.0) * 10_000.0).min(65_535.0) as u16,
                    classification: match l.part {
                        Part::Ground => 2,
                        Part::Unused => 1,
                        _ => 5,
                    },
                    ..Default::default()
                },
                [
                    f64::from(p.signal),
                    f64::from(l.cluster),
                    f64::from(l.tree),
                    l.part as i32 as f64,
                ],
            )
        }),
    )
    .map_err(|e| TreesError::Write {
        path: las.display().to_string(),
        why: e.to_string(),
    })?;
    Ok(())
}
