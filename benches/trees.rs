//! Cost of 3D tree reconstruction (`src/trees/`, `fwlidar trees`) per tree, from the hyper
//! point cloud of a replay:
//!
//! - `trees/branch_trees_leaf_off_2ns`: `config/scenes/branch_trees.toml` as written (three
//!   leaf-off trees, 5 184 pulses, 2 ns), raw waveforms;
//! - `trees/branch_trees_leaf_on_2ns`: the same trees in leaf (leaf area density 0.8);
//! - `trees/tree_plot_2ns`: the seed's tree plot (six trees, 1 600 pulses), 2 ns.
//!
//! Each iteration is the whole reconstruction of the plot (ground, threshold scan, foliage
//! filter, trees, stems, branches); the figure per tree is the mean divided by the number of
//! trees. The bench also prints mean, p50, p99 and max of 20 timed runs per plot, and the
//! points each holds. The captures are simulated and replayed by the built binary in setup.

use std::hint::black_box;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::trees::cluster::dbscan;
use fwlidar::trees::points::{TreePoint, read_hyper_points};
use fwlidar::trees::reconstruct::Part;
use fwlidar::trees::{TreesOptions, reconstruct};

fn fwlidar(args: &[&str]) {
    let o = Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Simulates `scene` with `sets`, replays it into hyper points (raw waveforms), reads them.
fn points(dir: &Path, name: &str, scene: &str, sets: &[String]) -> Vec<TreePoint> {
    let cap = dir.join(format!("{name}.fwcap"));
    let scene = format!("config/scenes/{scene}.toml");
    let mut args = vec![
        "simulate",
        "--scene",
        &scene,
        "--no-truth-voxels",
        "--out",
        cap.to_str().unwrap(),
    ];
    for s in sets {
        args.extend(["--set", s]);
    }
    fwlidar(&args);
    let out = dir.join(name);
    fwlidar(&[
        "trees",
        cap.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--waveform",
        "raw",
    ]);
    read_hyper_points(&out.join("replay/hyper_points.las"))
        .unwrap()
        .points
}

/// Writes `points` as an n × 3 float64 `.npy`, with `eps` and `min_points` in a `.json` beside.
fn write_npy(path: &Path, points: &[[f64; 3]], eps: f64, min_points: usize) {
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 3), }}",
        points.len()
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(header.as_bytes());
    for p in points {
        for v in p {
            b.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, b).unwrap();
    std::fs::write(
        path.with_extension("json"),
        format!("{{\"eps\": {eps}, \"min_points\": {min_points}}}"),
    )
    .unwrap();
}

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let lad = |n: usize, v: f64| -> Vec<String> {
        (0..n)
            .map(|i| format!("tree[{i}].leaf_area_density={v}"))
            .collect()
    };
    let mut plot_sets = lad(6, 0.0);
    plot_sets.push("sensor.outgoing_fwhm_ns=2".into());
    let cases = [
        (
            "branch_trees_leaf_off_2ns",
            points(dir.path(), "off", "branch_trees", &[]),
        ),
        (
            "branch_trees_leaf_on_2ns",
            points(dir.path(), "on", "branch_trees", &lad(3, 0.8)),
        ),
        (
            "tree_plot_2ns",
            points(dir.path(), "plot", "tree_plot", &plot_sets),
        ),
    ];
    let opts = TreesOptions::default();
    let mut g = c.benchmark_group("trees");
    g.sample_size(10);
    for (name, pts) in &cases {
        let trees = reconstruct(pts, &opts).unwrap().trees.len().max(1);
        let mut times = Vec::new();
        for _ in 0..20 {
            let t = Instant::now();
            black_box(reconstruct(black_box(pts), &opts).unwrap());
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        let q = |f: f64| times[((times.len() - 1) as f64 * f).round() as usize];
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        println!(
            "{name}: {} points, {trees} trees; whole plot over 20 runs: mean {mean:.1} ms \
             (per tree {:.1} ms), p50 {:.1}, p99 {:.1}, max {:.1} ms",
            pts.len(),
            mean / trees as f64,
            q(0.5),
            q(0.99),
            q(1.0)
        );
        g.bench_function(*name, |b| {
            b.iter(|| black_box(reconstruct(black_box(pts), &opts).unwrap()))
        });
    }
    // One DBSCAN alone, on the largest set the threshold scan clusters (the above-ground
    // samples above the noise floor of the leaf-on plot), for the side-by-side with
    // scikit-learn's DBSCAN (`benches/compare/trees_dbscan.sh`: the same points, written to
    // `target/trees_dbscan_points.npy`, the same eps and min_samples).
    let (_, pts) = &cases[1];
    let r = reconstruct(pts, &opts).unwrap();
    let floor = r.noise_floor_v.unwrap_or(f32::MIN);
    let set: Vec<[f64; 3]> = pts
        .iter()
        .zip(&r.labels)
        .filter(|(p, l)| l.part != Part::Ground && p.signal >= floor)
        .map(|(p, _)| p.xyz)
        .collect();
    println!(
        "dbscan_scan_first: {} points, eps {:.4} m, min_points {}",
        set.len(),
        r.eps_m,
        r.min_points
    );
    write_npy(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("target/trees_dbscan_points.npy"),
        &set,
        r.eps_m,
        r.min_points,
    );
    g.bench_function("dbscan_scan_first", |b| {
        b.iter(|| black_box(dbscan(black_box(&set), r.eps_m, r.min_points)))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
