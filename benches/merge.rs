//! Cost of merging voxel stores (`src/voxel/merge.rs`: `fwlidar merge`, a campaign's merge):
//!
//! - `merge/four_crossing_lines`: the line stores of four survey lines that cross at one point
//!   (`tests/campaign.rs`'s lines): 160 of 166 tiles held by one line, copied as they are;
//! - `merge/four_parallel_lines_40m`: four parallel lines 40 m apart, most tiles held by
//!   several lines: decoded, added and encoded.
//!
//! Each iteration merges the stores into a new folder (nothing is deleted while the bench
//! runs: on this VM a deletion slows every later write, `docs/performance.md`). The bench
//! prints mean, p50, p99 and max of the iterations and the megabytes of input per second. The
//! line stores are made in setup by the built binary (`fwlidar simulate`, `fwlidar campaign
//! run`).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use fwlidar::voxel::merge::{MergeMeta, merge_stores};

#[path = "../tests/common/mod.rs"]
mod common;

/// Simulates the lines along `tracks` into `dir/name/`, runs them as a campaign, returns their
/// stores and their size in bytes.
fn line_stores(dir: &Path, name: &str, tracks: &[(&str, &str)]) -> (Vec<PathBuf>, u64) {
    let root = std::path::absolute(dir.join(name)).unwrap();
    common::survey_lines(&root, tracks);
    let file = root.join("c.toml");
    std::fs::write(
        &file,
        "[campaign]\nname = \"bench\"\ncaptures = [\"lines/line?.fwcap\"]\n\
         set = [\"output.waveforms=false\", \"output.las=false\", \"output.rasters=false\"]\n\
         out = \"out\"\nepsg = 32736\nmetrics = false\n",
    )
    .unwrap();
    let o = common::fwlidar(&["campaign", "run", file.to_str().unwrap(), "--local", "2"]);
    assert!(o.status.success(), "{}", common::text(&o.stderr));
    let stores: Vec<PathBuf> = (0..tracks.len())
        .map(|i| root.join(format!("out/lines/line{i}/voxels.zarr")))
        .collect();
    let bytes = stores.iter().map(|s| tree_bytes(s)).sum();
    (stores, bytes)
}

fn tree_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| {
            let p = e.unwrap().path();
            if p.is_dir() {
                tree_bytes(&p)
            } else {
                std::fs::metadata(&p).unwrap().len()
            }
        })
        .sum()
}

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            "four_crossing_lines",
            line_stores(dir.path(), "crossing", &common::CROSSING_TRACKS),
        ),
        (
            "four_parallel_lines_40m",
            line_stores(
                dir.path(),
                "parallel",
                &[
                    ("[-150.0, 0.0]", "[150.0, 0.0]"),
                    ("[-150.0, 40.0]", "[150.0, 40.0]"),
                    ("[-150.0, 80.0]", "[150.0, 80.0]"),
                    ("[-150.0, 120.0]", "[150.0, 120.0]"),
                ],
            ),
        ),
    ];
    let mut g = c.benchmark_group("merge");
    g.sample_size(10).measurement_time(Duration::from_secs(15));
    for (name, (stores, bytes)) in &cases {
        let outs = dir.path().join(format!("{name}_out"));
        std::fs::create_dir_all(&outs).unwrap();
        let mut times: Vec<f64> = Vec::new();
        let mut n = 0usize;
        let mut last = None;
        g.bench_function(*name, |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for _ in 0..iters {
                    n += 1;
                    let out = outs.join(format!("m{n}.zarr"));
                    let t = Instant::now();
                    let s = merge_stores(stores, &out, &MergeMeta::FromInputs, |_, _| {}).unwrap();
                    let e = t.elapsed();
                    total += e;
                    times.push(e.as_secs_f64() * 1e3);
                    last = Some(s);
                }
                total
            })
        });
        times.sort_by(f64::total_cmp);
        let at = |q: f64| times[((times.len() - 1) as f64 * q).round() as usize];
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        let s = last.unwrap();
        println!(
            "merge/{name}: {} merges of {} stores ({:.1} MB): mean {mean:.0} ms ({:.0} MB/s), \
             p50 {:.0}, p99 {:.0}, max {:.0} ms; {} tiles, {} in several stores, {} copied",
            times.len(),
            stores.len(),
            *bytes as f64 / 1e6,
            *bytes as f64 / 1e3 / mean,
            at(0.5),
            at(0.99),
            times[times.len() - 1],
            s.tiles,
            s.tiles_from_several,
            s.tiles_copied
        );
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
