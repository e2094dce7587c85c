//! `fwlidar process` through the real binary: exact round trips with `--method none
//! --no-denoise` (CSV and NPY, ragged rows), a run on the NEON Harvard Forest waveforms from the
//! shared fixtures, and the errors (exit codes, messages, nothing written).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use fwlidar::format::table::{encode_npy, parse_csv, read_table};

fn fwlidar(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .args(args)
        .output()
        .expect("run fwlidar")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The real-data fixtures folder (`tests/data`, or `$FWLIDAR_FIXTURES`); always present, the
/// `Option` keeps the callers' shape.
fn fixtures() -> Option<PathBuf> {
    Some(fwlidar::fixtures::dir())
}

fn ragged_rows() -> Vec<Vec<f32>> {
    vec![
        vec![1.5, -2.25, 3.0e-7, 0.0, 0.0],
        vec![208.0],
        vec![0.1, 0.2, 0.3, 1e30, -1e-30, 7.0, 0.0],
    ]
}

#[test]
fn csv_round_trip_without_processing_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.csv");
    let out = dir.path().join("out.csv");
    std::fs::write(
        &input,
        "V1,V2,V3,V4,V5,V6,V7\n1.5,-2.25,3e-7,0,0,,\n\n 208 ,,\n0.1,0.2,0.3,1e30,-1e-30,7,0\n",
    )
    .unwrap();
    let o = fwlidar(&[
        "process",
        "--input",
        s(&input),
        "--method",
        "none",
        "--no-denoise",
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("3 waveforms"));
    assert_eq!(read_table(&out).unwrap().rows, ragged_rows());
}

#[test]
fn npy_round_trip_without_processing_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.npy");
    let out = dir.path().join("out.npy");
    std::fs::write(&input, encode_npy(&ragged_rows())).unwrap();
    let o = fwlidar(&[
        "process",
        "--input",
        s(&input),
        "--method",
        "none",
        "--no-denoise",
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(read_table(&out).unwrap().rows, ragged_rows());
    // And across formats: NPY in, CSV out.
    let csv_out = dir.path().join("out.csv");
    let o = fwlidar(&[
        "process",
        "--input",
        s(&input),
        "--method",
        "none",
        "--no-denoise",
        "--out",
        s(&csv_out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(read_table(&csv_out).unwrap().rows, ragged_rows());
}

#[test]
fn neon_harvard_forest_waveforms() {
    let Some(fx) = fixtures() else { return };
    let neon = fx.join("waveform/neon_harv");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.csv");
    let returns = dir.path().join("returns.csv");
    // imp.csv is one column with a header ("imp"): the column is the kernel.
    let o = fwlidar(&[
        "process",
        "--input",
        s(&neon.join("return.csv")),
        "--kernel",
        s(&neon.join("imp.csv")),
        "--method",
        "none",
        "--out",
        s(&out),
        "--returns",
        s(&returns),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let t = read_table(&out).unwrap();
    assert_eq!(t.rows.len(), 500);
    assert!(t.rows.iter().all(|r| r.len() == 208));
    assert!(t.rows.iter().flatten().all(|v| v.is_finite()));
    // Denoised: the baseline (~200-220 DN) is removed, the peaks stay.
    let first = &t.rows[0];
    assert!(
        first[..8].iter().all(|v| v.abs() < 20.0),
        "{:?}",
        &first[..8]
    );
    let peak = first.iter().copied().fold(f32::MIN, f32::max);
    assert!(peak > 250.0 && peak < 450.0, "peak {peak}");
    let header = std::fs::read_to_string(&returns).unwrap();
    assert!(header.starts_with("waveform,position_bins,amplitude,sigma_bins\n"));

    // --zero-padding: only the recorded samples are processed; the padding stays zeros.
    let o = fwlidar(&[
        "process",
        "--input",
        s(&neon.join("return.csv")),
        "--kernel",
        s(&neon.join("imp.csv")),
        "--method",
        "none",
        "--zero-padding",
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let padded = read_table(&out).unwrap();
    let raw = read_table(&neon.join("return.csv")).unwrap();
    assert_eq!(padded.rows.len(), 500);
    for (p, r) in padded.rows.iter().zip(&raw.rows) {
        assert_eq!(p.len(), 208);
        let valid = r.iter().rposition(|&v| v != 0.0).unwrap() + 1;
        assert!((68..=196).contains(&valid), "recorded length {valid}");
        assert!(p[valid..].iter().all(|&v| v == 0.0));
        // No step down to the padding (about -220 without --zero-padding). A few NEON rows hold
        // interior runs of zeros (gaps in the recording), which stay steps: skip those.
        if r[..valid].contains(&0.0) {
            continue;
        }
        let low = p[..valid].iter().copied().fold(f32::MAX, f32::min);
        assert!(low > -100.0, "minimum {low}");
    }

    // One outgoing pulse per row (outg.csv, 500 x 100, zero-padded) and a deconvolution method.
    let npy_out = dir.path().join("out.npy");
    let o = fwlidar(&[
        "process",
        "--input",
        s(&neon.join("return.csv")),
        "--kernel",
        s(&neon.join("outg.csv")),
        "--kernel-per-row",
        "--method",
        "wiener",
        "--out",
        s(&npy_out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let t = read_table(&npy_out).unwrap();
    assert_eq!(t.rows.len(), 500);
    assert!(t.rows.iter().all(|r| r.len() == 208));
}

#[test]
fn bad_input_fails_clearly_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    std::fs::write(p("in.csv"), "1,2,3,4\n5,6,7,8\n").unwrap();
    std::fs::write(p("k2.csv"), "0,1,3,1\n0,1,3,1\n").unwrap();
    std::fs::write(p("k1.csv"), "0,0,1,3,1,0\n").unwrap();
    std::fs::write(p("k3.csv"), "0,1,3,1\n0,1,3,1\n0,1,3,1\n").unwrap();
    std::fs::write(p("empty.csv"), "V1,V2\n\n").unwrap();
    std::fs::write(p("text.csv"), "1,2,3\n4,oops,6\n").unwrap();
    std::fs::write(p("nan.csv"), "1,2,3\n4,5,6\n7,NaN,9\n").unwrap();
    let mut nan_npy = encode_npy(&[vec![1.0, 2.0], vec![3.0, 4.0]]);
    let n = nan_npy.len();
    nan_npy[n - 8..n - 4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(p("nan.npy"), nan_npy).unwrap();
    std::fs::write(p("trunc.npy"), &encode_npy(&[vec![1.0, 2.0]])[..70]).unwrap();
    let out = p("out.csv");
    std::fs::write(&out, "previous").unwrap();

    // Paths as &'static str for the table below (a test process; the leak is harmless).
    let q = |n: &str| -> &'static str {
        Box::leak(
            dir.path()
                .join(n)
                .to_str()
                .unwrap()
                .to_string()
                .into_boxed_str(),
        )
    };
    let cases: Vec<(Vec<&str>, i32, &str)> = vec![
        (
            vec!["--input", q("missing.csv"), "--method", "none"],
            1,
            "does not exist",
        ),
        (
            vec![
                "--input",
                q("in.csv"),
                "--kernel",
                q("missing.csv"),
                "--method",
                "rl",
            ],
            1,
            "does not exist",
        ),
        (
            vec![
                "--input",
                q("in.csv"),
                "--kernel",
                q("k2.csv"),
                "--method",
                "wiener",
            ],
            2,
            "--kernel-per-row",
        ),
        (
            vec![
                "--input",
                q("in.csv"),
                "--kernel",
                q("k3.csv"),
                "--kernel-per-row",
                "--method",
                "wiener",
            ],
            1,
            "3 rows",
        ),
        (
            vec!["--input", q("empty.csv"), "--method", "none"],
            1,
            "no waveforms",
        ),
        (
            vec!["--input", q("text.csv"), "--method", "none"],
            1,
            "text.csv:2: cell 2",
        ),
        (
            vec!["--input", q("nan.csv"), "--method", "none"],
            1,
            "nan.csv:3: cell 2",
        ),
        (
            vec!["--input", q("nan.npy"), "--method", "none"],
            1,
            "nan.npy: row 1",
        ),
        (
            vec!["--input", q("trunc.npy"), "--method", "none"],
            1,
            "truncated",
        ),
        (
            vec!["--input", q("in.csv"), "--method", "rl"],
            2,
            "needs --kernel",
        ),
        (
            vec![
                "--input",
                q("in.csv"),
                "--method",
                "none",
                "--cutoff-ghz",
                "0.5",
            ],
            2,
            "Nyquist",
        ),
        (
            vec!["--input", q("in.txt"), "--method", "none"],
            2,
            ".csv or .npy",
        ),
        (
            vec!["--input", q("in.csv"), "--method", "bogus"],
            2,
            "bogus",
        ),
    ];
    for (args, code, message) in cases {
        let mut all = vec!["process"];
        all.extend(&args);
        all.extend(["--out", s(&out), "--returns", q("ret.csv")]);
        let o = fwlidar(&all);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(code), "{args:?}: {err}");
        assert!(
            err.contains(message),
            "{args:?}: expected {message:?} in {err}"
        );
        assert_eq!(
            std::fs::read_to_string(&out).unwrap(),
            "previous",
            "{args:?}"
        );
        assert!(!p("ret.csv").exists(), "{args:?}");
        assert!(!p("out.csv.partial").exists(), "{args:?}");
    }

    // The good kernel works (and a plain run replaces the old output).
    let o = fwlidar(&[
        "process",
        "--input",
        s(&p("in.csv")),
        "--kernel",
        s(&p("k1.csv")),
        "--method",
        "none",
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let t = parse_csv(&std::fs::read(&out).unwrap(), "out.csv").unwrap();
    assert_eq!(t.rows.len(), 2);
    assert!(t.rows.iter().all(|r| r.len() == 4));
}

/// Runs `fwlidar process` on the NEON returns with `extra` options; the processed rows.
fn neon_process(neon: &Path, dir: &Path, name: &str, extra: &[&str]) -> Vec<Vec<f32>> {
    let out = dir.join(name);
    let input = neon.join("return.csv");
    let mut args = vec![
        "process",
        "--input",
        s(&input),
        "--zero-padding",
        "--no-progress",
        "--out",
        s(&out),
    ];
    args.extend_from_slice(extra);
    let o = fwlidar(&args);
    assert!(o.status.success(), "{extra:?}: {}", stderr(&o));
    let rows = read_table(&out).unwrap().rows;
    assert_eq!(rows.len(), 500);
    assert!(rows.iter().flatten().all(|v| v.is_finite()), "{extra:?}");
    rows
}

fn argmax(x: &[f32]) -> usize {
    x.iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map_or(0, |(i, _)| i)
}

#[test]
fn neon_two_stage_response_then_outgoing() {
    let Some(fx) = fixtures() else { return };
    let neon = fx.join("waveform/neon_harv");
    let dir = tempfile::tempdir().unwrap();
    let outg = neon.join("outg.csv");
    let outgoing = ["--method", "gold", "--kernel", s(&outg), "--kernel-per-row"];
    let one = neon_process(&neon, dir.path(), "one.csv", &outgoing);
    let mut two_args = outgoing.to_vec();
    let (imp, imp_out) = (neon.join("imp.csv"), neon.join("imp_out.csv"));
    two_args.extend_from_slice(&["--response", s(&imp), "--response-outgoing", s(&imp_out)]);
    let two = neon_process(&neon, dir.path(), "two.csv", &two_args);
    // Gold keeps everything non-negative; the response stage changes the result but moves no
    // return: the highest sample of most rows stays within a bin of the one-stage result's.
    assert!(two.iter().flatten().all(|v| *v >= 0.0));
    assert_ne!(one, two, "--response changed nothing");
    let near = one
        .iter()
        .zip(&two)
        .filter(|(a, b)| (argmax(a) as i64 - argmax(b) as i64).abs() <= 1)
        .count();
    assert!(
        near >= 450,
        "{near}/500 rows peak within a bin of the one-stage result"
    );

    // The response alone (no --kernel) is accepted; --response-outgoing needs --response.
    let imp_s = s(&imp);
    neon_process(
        &neon,
        dir.path(),
        "h.csv",
        &["--method", "rl", "--response", imp_s],
    );
    let o = fwlidar(&[
        "process",
        "--input",
        s(&neon.join("return.csv")),
        "--method",
        "rl",
        "--kernel",
        imp_s,
        "--response-outgoing",
        s(&imp_out),
        "--out",
        s(&dir.path().join("x.csv")),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("--response"), "{}", stderr(&o));
    assert!(!dir.path().join("x.csv").exists());
}

#[test]
fn iterations_change_the_result_of_iterative_methods() {
    let Some(fx) = fixtures() else { return };
    let neon = fx.join("waveform/neon_harv");
    let dir = tempfile::tempdir().unwrap();
    let imp = neon.join("imp.csv");
    for method in ["rl", "gold"] {
        let run = |n: &str| {
            neon_process(
                &neon,
                dir.path(),
                &format!("{method}{n}.csv"),
                &["--method", method, "--kernel", s(&imp), "--iterations", n],
            )
        };
        let (few, many) = (run("5"), run("50"));
        let changed = few.iter().zip(&many).filter(|(a, b)| a != b).count();
        assert!(changed >= 490, "{method}: only {changed}/500 rows changed");
        // More iterations sharpen: the highest sample grows in most rows.
        let taller = few
            .iter()
            .zip(&many)
            .filter(|(a, b)| b[argmax(b)] > a[argmax(a)])
            .count();
        assert!(
            taller >= 450,
            "{method}: {taller}/500 rows sharper at 50 iterations"
        );
    }
}

/// A drifting baseline and a clipped echo through `--method nnls` with no other option: the
/// summary names the clipped row, the drift is gone from the output (the line removed, not a
/// level), and the clipped echo comes back at its area where `--baseline level` and a plain
/// fit would not (a kernel of 8 ns, 1 ns samples).
#[test]
fn nnls_removes_a_drifting_baseline_and_leaves_clipped_samples_out() {
    let dir = tempfile::tempdir().unwrap();
    let (input, kernel) = (dir.path().join("in.npy"), dir.path().join("k.npy"));
    let sigma = 8.0 / 2.354_82f64;
    let pulse = |x: f64| (-0.5 * (x / sigma).powi(2)).exp();
    let taps: Vec<f32> = (-14..=14).map(|j| pulse(j as f64) as f32).collect();
    let sum: f32 = taps.iter().sum();
    let taps: Vec<f32> = taps.iter().map(|t| t / sum).collect();
    // Echo areas 2 (at 80) and 6 (at 170, its top clipped at 0.5); baseline 0.05 → 0.15.
    let row: Vec<f32> = (0..256)
        .map(|i| {
            let x = i as f64;
            let echo = 2.0 * pulse(x - 80.0) / sum as f64 + 6.0 * pulse(x - 170.0) / sum as f64;
            let wiggle = 0.002 * ((i * 7919 % 13) as f64 - 6.0) / 6.0;
            (0.05 + 0.1 * x / 255.0 + echo + wiggle).min(0.5) as f32
        })
        .collect();
    std::fs::write(&input, encode_npy(&[row])).unwrap();
    std::fs::write(&kernel, encode_npy(&[taps])).unwrap();
    let run = |extra: &[&str], out: &Path| {
        let mut args = vec![
            "process",
            "--input",
            s(&input),
            "--kernel",
            s(&kernel),
            "--method",
            "nnls",
            "--no-progress",
            "--out",
            s(out),
        ];
        args.extend_from_slice(extra);
        let o = fwlidar(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        let y = read_table(out).unwrap().rows.remove(0);
        (String::from_utf8_lossy(&o.stdout).into_owned(), y)
    };
    let (summary, y) = run(&[], &dir.path().join("line.npy"));
    assert!(summary.contains("1 rows with clipped samples"), "{summary}");
    assert!(
        summary.contains("baseline removed (no low-pass)"),
        "{summary}"
    );
    let area = |y: &[f32], r: std::ops::Range<usize>| y[r].iter().sum::<f32>();
    // Spikes: the echoes' areas, and along the drift only the small ones of the ±0.002
    // ripple.
    assert!((area(&y, 70..90) - 2.0).abs() < 0.1, "{}", area(&y, 70..90));
    assert!(
        (area(&y, 160..180) - 6.0).abs() < 0.3,
        "{}",
        area(&y, 160..180)
    );
    let stray = area(&y, 0..60) + area(&y, 100..150) + area(&y, 195..256);
    assert!(stray < 0.5, "{stray} {y:?}");
    // With a level baseline the drift stays in and is fitted with spikes.
    let (_, level) = run(&["--baseline", "level"], &dir.path().join("level.npy"));
    let drift = area(&level, 0..60) + area(&level, 100..150) + area(&level, 195..256);
    assert!(drift > 4.0 * stray, "level {drift}, line {stray}");
}
