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

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
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

/// An 8 ns FWHM Gaussian pulse at 1 ns samples: its shape (peak 1 at 0, argument in ns) and
/// its 29 taps (±14 ns, peak 1).
fn gaussian_8ns() -> (impl Fn(f64) -> f64, Vec<f32>) {
    let sigma = 8.0 / 2.354_82f64;
    let pulse = move |x: f64| (-0.5 * (x / sigma).powi(2)).exp();
    let taps = (-14..=14).map(|j| pulse(j as f64) as f32).collect();
    (pulse, taps)
}

/// [`gaussian_8ns`] with its taps scaled to unit sum: the shape, the taps and the factor.
fn unit_gaussian_8ns() -> (impl Fn(f64) -> f64, Vec<f32>, f32) {
    let (pulse, taps) = gaussian_8ns();
    let sum: f32 = taps.iter().sum();
    (pulse, taps.iter().map(|t| t / sum).collect(), sum)
}

/// A deterministic uniform noise in [−0.5, 0.5) (xorshift64 from `seed`, non-zero).
fn uniform_noise(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }
}

/// `fwlidar process --input IN --kernel K --method M --no-progress --out OUT EXTRA…`.
fn process_rows(input: &Path, kernel: &Path, method: &str, extra: &[&str], out: &Path) -> Output {
    let mut args = vec![
        "process",
        "--input",
        s(input),
        "--kernel",
        s(kernel),
        "--method",
        method,
        "--no-progress",
        "--out",
        s(out),
    ];
    args.extend_from_slice(extra);
    fwlidar(&args)
}

/// A drifting baseline and a clipped echo through `--method nnls` with no other option: the
/// summary names the clipped row, the drift is gone from the output (the line removed, not a
/// level), and the clipped echo comes back at its area where `--baseline level` and a plain
/// fit would not (a kernel of 8 ns, 1 ns samples).
#[test]
fn nnls_removes_a_drifting_baseline_and_leaves_clipped_samples_out() {
    let dir = tempfile::tempdir().unwrap();
    let (input, kernel) = (dir.path().join("in.npy"), dir.path().join("k.npy"));
    let (pulse, taps, sum) = unit_gaussian_8ns();
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
        let o = process_rows(&input, &kernel, "nnls", extra, out);
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

/// `--peaks` at its default 5 σ: the noise-aware detector on RL 200's output keeps the echoes and drops most of
/// the peaks late iterations sharpen out of the noise; with `--peak-snr 0` those come back.
/// 40 rows of two echoes (8 ns pulse, 1 ns bins, echoes 20–60 bins apart, amplitudes 0.3–1)
/// and uniform noise of ±3 % of the strongest echo's peak.
#[test]
fn peaks_keeps_the_echoes_the_data_show_and_drops_sharpened_noise() {
    let dir = tempfile::tempdir().unwrap();
    let (input, kernel) = (dir.path().join("in.npy"), dir.path().join("k.npy"));
    let (pulse, taps) = gaussian_8ns();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut truth = Vec::new();
    let rows: Vec<Vec<f32>> = (0..40)
        .map(|_| {
            let a = 40.0 + 60.0 * uniform();
            let b = a + 20.0 + 40.0 * uniform();
            let (ha, hb) = (1.0, 0.3 + 0.7 * uniform());
            truth.push([a, b]);
            (0..200)
                .map(|i| {
                    let x = i as f64;
                    let e = ha * pulse(x - a) + hb * pulse(x - b);
                    (0.1 + e + 0.03 * (2.0 * uniform() - 1.0)) as f32
                })
                .collect()
        })
        .collect();
    std::fs::write(&input, encode_npy(&rows)).unwrap();
    std::fs::write(&kernel, encode_npy(&[taps])).unwrap();
    let run = |extra: &[&str], peaks: &Path| {
        let out = dir.path().join("out.npy");
        let mut args = vec![
            "process",
            "--input",
            s(&input),
            "--kernel",
            s(&kernel),
            "--method",
            "rl",
            "--iterations",
            "200",
            "--no-progress",
            "--out",
            s(&out),
            "--peaks",
            s(peaks),
        ];
        args.extend_from_slice(extra);
        let o = fwlidar(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        let summary = String::from_utf8_lossy(&o.stdout).into_owned();
        let csv = std::fs::read_to_string(peaks).unwrap();
        let mut lines = csv.lines();
        assert_eq!(lines.next(), Some("waveform,position_bins,amplitude,snr"));
        let echoes: Vec<(usize, f64, f64)> = lines
            .map(|l| {
                let c: Vec<&str> = l.split(',').collect();
                (
                    c[0].parse().unwrap(),
                    c[1].parse().unwrap(),
                    c[3].parse().unwrap(),
                )
            })
            .collect();
        (summary, echoes)
    };
    // (found, false) against the truth: an echo is found when a peak lies within 2 bins.
    let score = |echoes: &[(usize, f64, f64)]| {
        let (mut found, mut stray) = (0, 0);
        for (r, t) in truth.iter().enumerate() {
            let here: Vec<f64> = echoes.iter().filter(|e| e.0 == r).map(|e| e.1).collect();
            found += t
                .iter()
                .filter(|&&x| here.iter().any(|p| (p - x).abs() <= 2.0))
                .count();
            stray += here
                .iter()
                .filter(|p| t.iter().all(|x| (*p - x).abs() > 2.0))
                .count();
        }
        (found, stray)
    };
    let (summary, kept) = run(&[], &dir.path().join("p5.csv"));
    assert!(summary.contains("echoes at >= 5 sigma"), "{summary}");
    assert!(
        kept.iter().all(|e| e.2 >= 5.0),
        "every kept echo at 5 σ or more"
    );
    let (found, stray) = score(&kept);
    let (_, all) = run(&["--peak-snr", "0"], &dir.path().join("p0.csv"));
    let (found0, stray0) = score(&all);
    println!("5 σ: {found}/80 found, {stray} stray; no test: {found0}/80, {stray0} stray");
    assert!(
        found >= 76,
        "{found} of 80 echoes found at 5 σ ({stray} stray)"
    );
    assert!(stray <= 20, "{stray} stray peaks in 40 rows at 5 σ");
    assert!(found0 >= found, "{found0} vs {found}");
    assert!(
        stray0 > 2 * stray.max(1),
        "{stray0} stray peaks without the test, {stray} with"
    );
    // A negative ratio is a usage error.
    let o = fwlidar(&[
        "process",
        "--input",
        s(&input),
        "--out",
        s(&dir.path().join("x.npy")),
        "--method",
        "none",
        "--peak-snr=-1",
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("--peak-snr"), "{}", stderr(&o));
}

/// `--peaks` on the real NEON Harvard Forest waveforms (RL by each row's outgoing pulse): every
/// waveform has an echo the data show, the strongest one sits where the raw waveform peaks,
/// and the 5 σ test keeps a plausible number per waveform (forest: canopy and ground) where
/// every local maximum of the output would be many more.
#[test]
fn neon_peaks_find_the_main_return_of_every_waveform() {
    let Some(fx) = fixtures() else { return };
    let neon = fx.join("waveform/neon_harv");
    let dir = tempfile::tempdir().unwrap();
    let outg = neon.join("outg.csv");
    let read = |p: &Path| -> Vec<(usize, f64, f64, f64)> {
        let csv = std::fs::read_to_string(p).unwrap();
        csv.lines()
            .skip(1)
            .map(|l| {
                let c: Vec<f64> = l.split(',').map(|v| v.parse().unwrap()).collect();
                (c[0] as usize, c[1], c[2], c[3])
            })
            .collect()
    };
    let mut counts = Vec::new();
    for (name, snr) in [("p5.csv", "5"), ("p0.csv", "0")] {
        let p = dir.path().join(name);
        let args = [
            "--method",
            "rl",
            "--kernel",
            s(&outg),
            "--kernel-per-row",
            "--peaks",
            s(&p),
            "--peak-snr",
            snr,
        ];
        neon_process(&neon, dir.path(), "rl.csv", &args);
        counts.push(read(&p));
    }
    let raw = read_table(&neon.join("return.csv")).unwrap().rows;
    let kept = &counts[0];
    let mut near = 0;
    for (r, row) in raw.iter().enumerate() {
        let here: Vec<_> = kept.iter().filter(|e| e.0 == r).collect();
        assert!(!here.is_empty(), "row {r}: no echo at 5 σ");
        let top = here.iter().max_by(|a, b| a.2.total_cmp(&b.2)).unwrap();
        assert!(top.3 >= 5.0);
        near += usize::from((top.1 - argmax(row) as f64).abs() <= 3.0);
    }
    let (n3, n0) = (kept.len() as f64 / 500.0, counts[1].len() as f64 / 500.0);
    println!(
        "NEON: {n3:.2} echoes per waveform at 5 σ, {n0:.2} maxima; strongest at the raw peak in {near}/500"
    );
    assert!(near >= 425, "{near}/500");
    assert!((1.0..=8.0).contains(&n3), "{n3} echoes per waveform");
    assert!(n0 > 1.5 * n3, "{n0} maxima vs {n3} echoes");
}

/// `--method nnls` puts spikes only near echoes by default (`--support-at-noise 4`): on rows of
/// two echoes in uniform noise, `--support-at-noise 0` (anywhere) fits the empty range with
/// spikes, the default leaves it at zero and keeps each echo's area; the option is refused for
/// another method and for a negative or non-finite value (exit 2, nothing written).
#[test]
fn nnls_spikes_only_near_echoes_by_default() {
    let dir = tempfile::tempdir().unwrap();
    let (input, kernel) = (dir.path().join("in.npy"), dir.path().join("k.npy"));
    let (pulse, taps, sum) = unit_gaussian_8ns();
    let mut uniform = uniform_noise(0x2545_f491_4f6c_dd1d);
    // Echo areas 3 (at 90) and 2 (at 150); peak about 0.35; noise ±0.01 (3 % of the peak).
    let rows: Vec<Vec<f32>> = (0..20)
        .map(|_| {
            (0..256)
                .map(|i| {
                    let x = i as f64;
                    let echo = (3.0 * pulse(x - 90.0) + 2.0 * pulse(x - 150.0)) / sum as f64;
                    (echo + 0.02 * uniform()) as f32
                })
                .collect()
        })
        .collect();
    std::fs::write(&input, encode_npy(&rows)).unwrap();
    std::fs::write(&kernel, encode_npy(&[taps])).unwrap();
    let run_method = |method: &str, extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let o = process_rows(&input, &kernel, method, extra, &out);
        (o.status.code(), stderr(&o), out)
    };
    let run = |extra: &[&str], name: &str| run_method("nnls", extra, name);
    let (code, err, out) = run(&[], "near.npy");
    assert_eq!(code, Some(0), "{err}");
    let near = read_table(&out).unwrap().rows;
    let (code, err, out) = run(&["--support-at-noise", "0"], "anywhere.npy");
    assert_eq!(code, Some(0), "{err}");
    let anywhere = read_table(&out).unwrap().rows;
    // Empty range: more than two kernels (29 taps) from either echo.
    let empty = |y: &[f32]| -> usize {
        (0..y.len())
            .filter(|&i| !(45..=195).contains(&i) && y[i] > 0.0)
            .count()
    };
    let in_noise: usize = anywhere.iter().map(|y| empty(y)).sum();
    let kept: usize = near.iter().map(|y| empty(y)).sum();
    assert!(
        in_noise >= 20,
        "spikes in the empty range without the mask: {in_noise}"
    );
    assert_eq!(kept, 0, "spikes in the empty range with the default");
    for (a, b) in near.iter().zip(&anywhere) {
        for (r, want) in [(70..110, 3.0f32), (130..170, 2.0)] {
            let (x, y) = (a[r.clone()].iter().sum::<f32>(), b[r].iter().sum::<f32>());
            assert!(
                (x - want).abs() < 0.2 && (x - y).abs() < 0.05,
                "{x} {y} {want}"
            );
        }
    }
    // Refused: another method, a negative or non-finite value; nothing written.
    for (method, value, words) in [
        ("rl", "4", "nnls only"),
        ("nnls", "-1", "positive number"),
        ("nnls", "NaN", "positive number"),
    ] {
        let extra = format!("--support-at-noise={value}");
        let (code, err, out) = run_method(method, &[extra.as_str()], "refused.npy");
        assert_eq!(code, Some(2), "{method} {value}: {err}");
        assert!(
            err.contains("--support-at-noise") && err.contains(words),
            "{err}"
        );
        assert!(!out.exists());
    }
}

/// The NEON Harvard Forest rows are zero-padded to 208 samples (68 to 196 recorded). Processed
/// as samples, the padding makes more than half of a row's first differences 0, so no noise
/// level is measured in most rows and `--support-at-noise` has nothing to apply there: the run
/// says so (summary and a warning) and names the padded rows with the option that removes the
/// padding. With `--zero-padding` every row has a noise level, and the mask changes nothing:
/// NEON's records are cut around the returns, so every recorded sample lies within a kernel
/// of an echo (the output equals `--support-at-noise 0`'s, spike for spike).
#[test]
fn neon_rows_without_a_noise_level_are_named_in_the_summary() {
    let neon = fixtures().unwrap().join("waveform/neon_harv");
    let dir = tempfile::tempdir().unwrap();
    let (input, kernel) = (neon.join("return.csv"), neon.join("imp.csv"));
    let o = process_rows(&input, &kernel, "nnls", &[], &dir.path().join("a.csv"));
    assert!(o.status.success(), "{}", stderr(&o));
    let summary = String::from_utf8_lossy(&o.stdout);
    let count_before = |summary: &str, text: &str| -> usize {
        summary
            .split(text)
            .next()
            .and_then(|t| t.rsplit(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no count before {text:?}: {summary}"))
    };
    let rows: usize = summary
        .split("spikes anywhere in ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no count of rows without a noise level: {summary}"));
    assert!((400..=500).contains(&rows), "{rows}: {summary}");
    assert_eq!(count_before(&summary, " rows end in 8 or more zeros"), 500);
    assert!(summary.contains("pass --zero-padding"), "{summary}");
    let err = stderr(&o);
    assert!(err.contains("no noise level measured"), "{err}");
    assert!(err.contains("--zero-padding processes only"), "{err}");

    let off = ["--support-at-noise", "0"];
    let o = process_rows(&input, &kernel, "nnls", &off, &dir.path().join("b.csv"));
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!String::from_utf8_lossy(&o.stdout).contains("spikes anywhere"));

    let padded = ["--zero-padding"];
    let (on, off) = (dir.path().join("c.csv"), dir.path().join("d.csv"));
    let o = process_rows(&input, &kernel, "nnls", &padded, &on);
    assert!(o.status.success(), "{}", stderr(&o));
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(!summary.contains("spikes anywhere"), "{summary}");
    assert!(!summary.contains("zeros"), "{summary}");
    let o = process_rows(
        &input,
        &kernel,
        "nnls",
        &["--zero-padding", "--support-at-noise", "0"],
        &off,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let (on, off) = (read_table(&on).unwrap(), read_table(&off).unwrap());
    assert_eq!(on.rows, off.rows);
    assert!(on.rows.iter().flatten().filter(|&&v| v > 0.0).count() > 1000);
}

/// `--method nnls_or_rl --target-fwhm-ns 2` keeps NNLS on rows of two hard surfaces (1 % noise)
/// and RL on rows of an extended canopy (3 % noise; 8 ns pulse, 1 ns samples): on each kind of
/// row its error against the 2 ns truth is well below the worse method's on hard surfaces (a
/// third of RL's, 0.017 against 0.047) and within 15 % of the better one's on canopy. (At 3 %
/// noise on 256 samples the residual rule keeps RL on these hard rows: RL's misfit is then
/// within the noise of the whole row; docs/accuracy.md.)
/// `--iterations` and `--support-at-noise` are refused for it (the two methods keep their own
/// settings), with exit 2 and nothing written.
#[test]
fn nnls_or_rl_keeps_the_better_method_per_row() {
    let dir = tempfile::tempdir().unwrap();
    let (input, kernel) = (dir.path().join("in.npy"), dir.path().join("k.npy"));
    let (pulse, taps, sum) = unit_gaussian_8ns();
    let sigma2 = 2.0 / 2.354_820_045; // 2 ns truth pulse, samples
    let truth_pulse = |x: f64| (-0.5 * (x / sigma2).powi(2)).exp() / (sigma2 * 2.506_628_275);
    let mut uniform = uniform_noise(0x9e37_79b9_7f4a_7c15);
    // Surfaces: (position, area); canopy: 30 scatterers over 40 samples, then ground.
    let hard: Vec<(f64, f64)> = vec![(100.0, 3.0), (140.0, 2.0)];
    let canopy: Vec<(f64, f64)> = (0..30)
        .map(|j| (70.0 + 40.0 * j as f64 / 30.0, 0.1 + 0.05 * (j % 3) as f64))
        .chain([(150.0, 2.0)])
        .collect();
    let draw = |scatter: &[(f64, f64)], p: &dyn Fn(f64) -> f64, x: f64| -> f64 {
        scatter.iter().map(|&(at, a)| a * p(x - at)).sum()
    };
    let system = |x: f64| pulse(x) / sum as f64;
    let mut rows = Vec::new();
    for r in 0..20 {
        let (scatter, noise) = if r % 2 == 0 {
            (&hard, 0.007)
        } else {
            (&canopy, 0.02)
        };
        let row: Vec<f32> = (0..256)
            .map(|i| (draw(scatter, &system, i as f64) + noise * uniform()) as f32)
            .collect();
        rows.push(row);
    }
    std::fs::write(&input, encode_npy(&rows)).unwrap();
    std::fs::write(&kernel, encode_npy(&[taps])).unwrap();
    let target = ["--target-fwhm-ns", "2"];
    let out_choice = dir.path().join("choice.npy");
    let error = |method: &str, extra: &[&str], kind: usize| -> f64 {
        let out = dir.path().join(format!("{method}.npy"));
        let mut args = target.to_vec();
        args.extend_from_slice(extra);
        let o = process_rows(&input, &kernel, method, &args, &out);
        assert!(o.status.success(), "{method}: {}", stderr(&o));
        let t = read_table(&out).unwrap().rows;
        let mut sq = 0.0;
        for (r, row) in t.iter().enumerate().filter(|(r, _)| r % 2 == kind) {
            let scatter = if r % 2 == 0 { &hard } else { &canopy };
            for (i, &v) in row.iter().enumerate() {
                sq += (v as f64 - draw(scatter, &truth_pulse, i as f64)).powi(2);
            }
        }
        (sq / (10.0 * 256.0)).sqrt()
    };
    // The summary line says how the choice went: NNLS kept on most of the 10 hard rows and on
    // few canopy rows (measured: ran on 17 rows, kept on 9).
    let o = process_rows(&input, &kernel, "nnls_or_rl", &target, &out_choice);
    let said = stdout(&o);
    let counts: Vec<u64> = said
        .split("NNLS ran on ")
        .nth(1)
        .and_then(|t| t.split(')').next())
        .map(|t| t.split(' ').filter_map(|w| w.parse().ok()).collect())
        .unwrap_or_default();
    let [ran, rows_run, kept] = counts[..] else {
        panic!("no choice counts in {said}")
    };
    assert_eq!(rows_run, 20, "{said}");
    assert!((8..=12).contains(&kept) && ran >= kept, "{said}");
    let rl = ["--iterations", "46"];
    for (kind, name) in [(0, "hard surfaces"), (1, "canopy")] {
        let (nnls, rl, both) = (
            error("nnls", &[], kind),
            error("rl", &rl, kind),
            error("nnls_or_rl", &[], kind),
        );
        // NNLS inside the choice runs on the low-passed row (`--method nnls` on the raw row), so
        // on hard surfaces it is compared with the worse method only.
        let (better, worse) = (nnls.min(rl), nnls.max(rl));
        let (close, below) = if kind == 0 { (4.0, 0.5) } else { (1.15, 0.9) };
        assert!(
            both < better * close && both < below * worse,
            "{name}: nnls {nnls:.4}, rl {rl:.4}, nnls_or_rl {both:.4}"
        );
    }
    for extra in [["--iterations", "20"], ["--support-at-noise", "4"]] {
        let out = dir.path().join("refused.npy");
        let o = process_rows(&input, &kernel, "nnls_or_rl", &extra, &out);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {}", stderr(&o));
        assert!(!out.exists());
    }
}

/// `fwlidar process --input INPUT --no-progress --learn-kernel --out OUT` with `extra`.
fn learn(input: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "process",
        "--input",
        s(input),
        "--no-progress",
        "--learn-kernel",
        "--out",
        s(out),
    ];
    args.extend_from_slice(extra);
    fwlidar(&args)
}

/// `--learn-kernel`: the kernel learned from the rows (NEON's returns: no kernel needed), the
/// given kernel kept and said so when the rows hold too few clean echoes, and the errors.
#[test]
fn learn_kernel_learns_from_the_rows_or_says_why_not() {
    let neon = fixtures().unwrap().join("waveform/neon_harv");
    let dir = tempfile::tempdir().unwrap();
    let input = neon.join("return.csv");
    let imp = neon.join("imp.csv");
    let out = dir.path().join("out.npy");
    // NEON's 500 returns, no kernel: learned from their single echoes.
    let o = learn(&input, &out, &["--zero-padding", "--method", "rl"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let line = stdout(&o);
    assert!(line.contains("kernel learned from"), "{line}");
    assert_eq!(read_table(&out).unwrap().rows.len(), 500);
    // Starting from NEON's calibrated response: stretched to the returns, the factor stated.
    let o = learn(
        &input,
        &out,
        &["--zero-padding", "--method", "rl", "--kernel", s(&imp)],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let line = stdout(&o);
    assert!(line.contains("--kernel stretched"), "{line}");
    // Three rows: too few echoes. With --kernel it is kept and said so; without, an error that
    // names the input and the way out, nothing written.
    let few = dir.path().join("few.csv");
    let row: Vec<String> = (0..64)
        .map(|i| {
            let x = (i as f32 - 30.0) / 3.0;
            format!("{}", 10.0 + 100.0 * (-0.5 * x * x).exp())
        })
        .collect();
    std::fs::write(&few, format!("{}\n", vec![row.join(","); 3].join("\n"))).unwrap();
    let o = learn(&few, &out, &["--method", "rl", "--kernel", s(&imp)]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("--kernel kept"), "{}", stdout(&o));
    assert!(stderr(&o).contains("learned nothing"), "{}", stderr(&o));
    let none = dir.path().join("none.npy");
    let o = learn(&few, &none, &["--method", "rl"]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(
        e.contains("few.csv") && e.contains("--learn-kernel") && e.contains("--kernel"),
        "{e}"
    );
    assert!(!none.exists());
    // Usage errors: nothing to learn for, or combined with what it replaces.
    for extra in [
        &["--method", "none"][..],
        &["--method", "rl", "--response", s(&imp)][..],
    ] {
        let o = learn(&few, &none, extra);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {}", stderr(&o));
        assert!(stderr(&o).contains("--learn-kernel"), "{}", stderr(&o));
    }
}
