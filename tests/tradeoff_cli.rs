//! `fwlidar tradeoff --quick` through the real binary: the three files exist, the CSV has the
//! expected columns and one row per (setting, pulse width, family), the SVG is well-formed XML,
//! the accuracy figures are sane, and bad arguments fail cleanly without writing anything.

use std::collections::HashMap;
use std::path::Path;
use std::process::{Command, Output};

fn fwlidar(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .args(args)
        .output()
        .expect("run fwlidar")
}

const COLUMNS: [&str; 17] = [
    "method",
    "parameter",
    "family",
    "width_ns",
    "pulses",
    "rmse",
    "rmse_2ns",
    "true_detections",
    "false_detections",
    "truth_peaks",
    "detection_rate",
    "false_per_pulse",
    "sam_deg",
    "time_mean_us",
    "time_median_us",
    "time_p99_us",
    "max_rate_hz",
];

/// Checks that `doc` is well-formed XML as far as this generator can produce it: one root
/// element, every start tag closed in order, quoted attributes, no stray `<` or `&` in text.
/// Returns the element names in document order.
fn check_xml(doc: &str) -> Result<Vec<String>, String> {
    let mut stack: Vec<String> = Vec::new();
    let mut names = Vec::new();
    let mut roots = 0;
    let mut rest = doc;
    while let Some(lt) = rest.find('<') {
        check_text(&rest[..lt])?;
        rest = &rest[lt..];
        let gt = rest.find('>').ok_or("unterminated tag")?;
        let tag = &rest[1..gt];
        rest = &rest[gt + 1..];
        if tag.starts_with('?') || tag.starts_with('!') {
            continue;
        }
        if let Some(name) = tag.strip_prefix('/') {
            let open = stack.pop().ok_or(format!("</{name}> closes nothing"))?;
            if open != name.trim() {
                return Err(format!("<{open}> closed by </{name}>"));
            }
            continue;
        }
        let self_closing = tag.ends_with('/');
        let body = tag.trim_end_matches('/');
        let name: String = body.chars().take_while(|c| !c.is_whitespace()).collect();
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
            return Err(format!("bad element name in <{tag}>"));
        }
        // Attributes: name="value" pairs, quotes balanced, no '<' inside.
        let attrs = &body[name.len()..];
        if !attrs.matches('"').count().is_multiple_of(2) || attrs.contains('<') {
            return Err(format!("bad attributes in <{tag}>"));
        }
        check_text(attrs)?;
        if stack.is_empty() {
            roots += 1;
        }
        names.push(name.clone());
        if !self_closing {
            stack.push(name);
        }
    }
    check_text(rest)?;
    if !stack.is_empty() {
        return Err(format!("unclosed elements {stack:?}"));
    }
    if roots != 1 {
        return Err(format!("{roots} root elements"));
    }
    Ok(names)
}

/// Text and attribute values: every `&` starts a known entity.
fn check_text(t: &str) -> Result<(), String> {
    for (i, _) in t.match_indices('&') {
        let ent = &t[i..];
        if !["&amp;", "&lt;", "&gt;", "&quot;", "&apos;"]
            .iter()
            .any(|e| ent.starts_with(e))
        {
            return Err(format!("bare & in {:?}", &t[i..(i + 10).min(t.len())]));
        }
    }
    Ok(())
}

#[test]
fn the_xml_check_can_fail() {
    assert!(check_xml("<svg><g></svg>").is_err());
    assert!(check_xml("<svg><g/></svg><svg/>").is_err());
    assert!(check_xml("<svg><text>a & b</text></svg>").is_err());
    assert!(check_xml("<svg x=\"1></svg>").is_err());
    assert!(check_xml("<svg><g><circle/></g></svg>").is_ok());
}

#[test]
fn quick_run_writes_sane_csv_markdown_and_svg() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t");
    let o = fwlidar(&["tradeoff", "--quick", "--out", out.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("[360/360]"), "progress on stderr: {err}");

    for f in ["tradeoff.csv", "tradeoff.md", "tradeoff.svg"] {
        assert!(out.join(f).is_file(), "{f} missing");
        assert!(!out.join(format!("{f}.partial")).exists());
    }

    // CSV: columns, one row per case, numbers where numbers belong.
    let csv = std::fs::read_to_string(out.join("tradeoff.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header, COLUMNS);
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    // 60 settings × 3 widths × 2 families.
    assert_eq!(rows.len(), 60 * 3 * 2);
    let col = |name: &str| COLUMNS.iter().position(|c| *c == name).unwrap();
    let mut rmse: HashMap<(String, String, String, String), f64> = HashMap::new();
    for r in &rows {
        assert_eq!(r.len(), COLUMNS.len(), "{r:?}");
        for name in &COLUMNS[3..] {
            let v: f64 = r[col(name)]
                .parse()
                .unwrap_or_else(|_| panic!("{name} = {:?}", r[col(name)]));
            assert!(v.is_finite() && v >= 0.0, "{name} = {v}");
        }
        assert_eq!(r[col("pulses")], "24");
        let rate: f64 = r[col("detection_rate")].parse().unwrap();
        assert!(rate <= 1.0);
        let sam: f64 = r[col("sam_deg")].parse().unwrap();
        assert!(sam <= 180.0);
        rmse.insert(
            (
                r[0].to_string(),
                r[1].to_string(),
                r[2].to_string(),
                r[3].to_string(),
            ),
            r[col("rmse")].parse().unwrap(),
        );
    }
    let methods: Vec<&str> = rows.iter().map(|r| r[0]).collect();
    for m in ["raw", "denoise", "rl", "rl_acc", "gold", "wiener", "nnls"] {
        assert!(methods.contains(&m), "{m} missing");
    }
    // Accuracy sanity on discrete surfaces: at 8 and 16 ns (the widths the seed deconvolved)
    // 200 RL iterations beat the raw waveform by a clear margin; at 4 ns, where 200 iterations
    // sharpen past the 2 ns truth, 20 iterations still do. NNLS finds at least as many truth
    // peaks as RL.
    let key = |m: &str, p: &str, w: &str| (m.into(), p.into(), "sparse".into(), w.into());
    for w in ["8", "16"] {
        let raw = rmse[&key("raw", "", w)];
        let rl = rmse[&key("rl", "iterations=200", w)];
        assert!(rl < 0.8 * raw, "{w} ns: RL 200 {rl} vs raw {raw}");
    }
    let (raw4, rl4) = (
        rmse[&key("raw", "", "4")],
        rmse[&key("rl", "iterations=20", "4")],
    );
    assert!(rl4 < 0.8 * raw4, "4 ns: RL 20 {rl4} vs raw {raw4}");
    // At the truth's 2 ns resolution (the output seen through the 2 ns pulse), the outputs are
    // scored as cross-section estimates: NNLS's spikes then beat the raw waveform by half at
    // 8 ns, and RL keeps improving with iterations.
    let rmse_2ns = |m: &str, p: &str, w: &str| -> f64 {
        rows.iter()
            .find(|r| r[0] == m && r[1] == p && r[2] == "sparse" && r[3] == w)
            .map(|r| r[col("rmse_2ns")].parse().unwrap())
            .unwrap()
    };
    let (raw8, nnls8) = (
        rmse_2ns("raw", "", "8"),
        rmse_2ns("nnls", "max_iterations=50", "8"),
    );
    assert!(
        nnls8 < 0.5 * raw8,
        "8 ns at 2 ns resolution: NNLS {nnls8} vs raw {raw8}"
    );
    let (rl20, rl200) = (
        rmse_2ns("rl", "iterations=20", "8"),
        rmse_2ns("rl", "iterations=200", "8"),
    );
    assert!(
        rl200 < rl20,
        "8 ns at 2 ns resolution: RL 200 {rl200} vs RL 20 {rl20}"
    );
    let detections = |m: &str, p: &str| -> u64 {
        rows.iter()
            .filter(|r| r[0] == m && r[1] == p && r[2] == "sparse")
            .map(|r| r[col("true_detections")].parse::<u64>().unwrap())
            .sum()
    };
    assert!(detections("nnls", "max_iterations=50") >= detections("rl", "iterations=20"));

    // Markdown: the summary and per-case tables, the plot linked.
    let md = std::fs::read_to_string(out.join("tradeoff.md")).unwrap();
    assert!(md.contains("| rl iterations=200 |"));
    assert!(md.contains("![error against time per pulse](tradeoff.svg)"));
    assert!(md.contains("●"), "a Pareto front is marked");

    // SVG: well-formed, an svg root, markers for every setting in both panels.
    let svg = std::fs::read_to_string(out.join("tradeoff.svg")).unwrap();
    let names = check_xml(&svg).unwrap_or_else(|e| panic!("SVG not well-formed: {e}"));
    assert_eq!(names[0], "svg");
    assert!(names.iter().filter(|n| *n == "circle").count() >= 2 * 23);
    assert!(names.iter().filter(|n| *n == "path").count() >= 2);
    assert!(svg.contains("time per pulse (µs"));
}

fn assert_usage_error(args: &[&str], dir: &Path, needle: &str) {
    let o = fwlidar(args);
    assert_eq!(o.status.code(), Some(2), "{args:?}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains(needle), "{args:?}: {err}");
    assert!(
        std::fs::read_dir(dir).unwrap().next().is_none(),
        "nothing written for {args:?}"
    );
}

#[test]
fn bad_arguments_fail_with_a_usage_error_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t");
    let o = out.to_str().unwrap();
    assert_usage_error(
        &["tradeoff", "--out", o, "--pulses", "0"],
        dir.path(),
        "--pulses",
    );
    assert_usage_error(
        &["tradeoff", "--out", o, "--widths-ns", "8,-4"],
        dir.path(),
        "pulse width",
    );
    assert_usage_error(
        &["tradeoff", "--out", o, "--noise", "nan"],
        dir.path(),
        "--noise",
    );
    assert_usage_error(
        &["tradeoff", "--out", o, "--peak-floor", "1.5"],
        dir.path(),
        "--peak-floor",
    );
    assert_usage_error(
        &["tradeoff", "--out", o, "--pulses", "many"],
        dir.path(),
        "invalid value",
    );
}

#[test]
fn a_chain_from_a_run_configuration_is_scored_beside_the_built_in_settings() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t");
    let onboard = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/onboard.toml");
    let o = fwlidar(&[
        "tradeoff",
        "--quick",
        "--pulses",
        "12",
        "--chain",
        onboard.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("[366/366]"),
        "60 settings and the chain: {err}"
    );
    assert!(
        err.contains("chain:onboard runs denoise, deconvolve"),
        "what the chain runs: {err}"
    );
    // The cases: one row per (pulse width, family), method `chain:onboard`.
    let csv = std::fs::read_to_string(out.join("tradeoff.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .filter(|r: &Vec<&str>| r[0] == "chain:onboard")
        .collect();
    assert_eq!(rows.len(), 6, "{csv}");
    for r in &rows {
        assert_eq!(r.len(), COLUMNS.len());
        assert_eq!(r[1], "", "no parameter");
        let rmse: f64 = r[5].parse().unwrap();
        assert!(rmse.is_finite() && rmse > 0.0 && rmse < 0.5, "{r:?}");
    }
    // The pulse-weighted summary: a row per setting, the chain's beside RL 20, comparable.
    let summary = std::fs::read_to_string(out.join("tradeoff_summary.csv")).unwrap();
    let mut lines = summary.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(&header[..4], ["method", "parameter", "pulses", "rmse"]);
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 61);
    let row = |m: &str, p: &str| {
        rows.iter()
            .find(|r| r[0] == m && r[1] == p)
            .unwrap_or_else(|| panic!("no {m} {p}"))
    };
    let (chain, rl20) = (row("chain:onboard", ""), row("rl", "iterations=20"));
    assert_eq!(chain[2], "72", "12 pulses × 6 cases");
    let col = |r: &Vec<&str>, name: &str| -> f64 {
        r[header.iter().position(|c| *c == name).unwrap()]
            .parse()
            .unwrap()
    };
    for name in ["rmse", "detection_rate", "false_per_pulse"] {
        let (c, b) = (col(chain, name), col(rl20, name));
        assert!(
            (c - b).abs() <= 0.2 * b.abs() + 0.05,
            "{name}: chain {c}, RL 20 {b}"
        );
    }
    let md = std::fs::read_to_string(out.join("tradeoff.md")).unwrap();
    assert!(md.contains("| chain:onboard |"), "{md}");
    assert!(md.contains("### Chains"));
    let svg = std::fs::read_to_string(out.join("tradeoff.svg")).unwrap();
    check_xml(&svg).unwrap();
    assert!(svg.contains("chain:onboard"));
}

#[test]
fn a_bad_chain_file_fails_naming_the_file_and_the_field_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let o = out.to_str().unwrap();
    let missing = dir.path().join("absent.toml");
    let o1 = fwlidar(&["tradeoff", "--out", o, "--chain", missing.to_str().unwrap()]);
    assert_eq!(o1.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o1.stderr);
    assert!(err.contains("absent.toml"), "{err}");

    let bad = dir.path().join("bad.toml");
    std::fs::write(
        &bad,
        "[[pipeline.stages]]\ntype = \"denoise\"\n[[pipeline.stages]]\ntype = \"deconvolve\"\n\
         method = { method = \"richardson_lucy\", iterations = 0 }\n",
    )
    .unwrap();
    let o2 = fwlidar(&["tradeoff", "--out", o, "--chain", bad.to_str().unwrap()]);
    assert_eq!(o2.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o2.stderr);
    assert!(
        err.contains("bad.toml") && err.contains("pipeline.stages[1].method"),
        "{err}"
    );

    let nothing = dir.path().join("nothing.toml");
    std::fs::write(&nothing, "[[pipeline.stages]]\ntype = \"passthrough\"\n").unwrap();
    let o3 = fwlidar(&["tradeoff", "--out", o, "--chain", nothing.to_str().unwrap()]);
    assert_eq!(o3.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o3.stderr);
    assert!(
        err.contains("nothing.toml: pipeline.stages: no stage changes the waveform"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written");
}

/// Rows of a `tradeoff.csv`, keyed by (method, parameter, family, width), as the named
/// column's numbers.
fn csv_column(path: &Path, name: &str) -> HashMap<(String, String, String, String), f64> {
    let csv = std::fs::read_to_string(path).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let c = header.iter().position(|h| *h == name).unwrap();
    lines
        .map(|l| {
            let r: Vec<&str> = l.split(',').collect();
            (
                (r[0].into(), r[1].into(), r[2].into(), r[3].into()),
                r[c].parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn the_noise_aware_detector_only_removes_peaks_and_drops_what_late_iterations_sharpen() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "tradeoff",
            "--pulses",
            "150",
            "--widths-ns",
            "8",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = fwlidar(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        out.join("tradeoff.csv")
    };
    let (floor, snr) = (run("floor", &[]), run("snr", &["--peak-snr", "5"]));
    let md = std::fs::read_to_string(dir.path().join("snr/tradeoff.md")).unwrap();
    assert!(
        md.contains("≥ 5 × the received noise σ"),
        "the header names the test"
    );
    let (t0, t1) = (
        csv_column(&floor, "true_detections"),
        csv_column(&snr, "true_detections"),
    );
    let (f0, f1) = (
        csv_column(&floor, "false_detections"),
        csv_column(&snr, "false_detections"),
    );
    let (r0, r1) = (csv_column(&floor, "rmse"), csv_column(&snr, "rmse"));
    for (k, v) in &t0 {
        assert!(
            t1[k] <= *v && f1[k] <= f0[k],
            "{k:?}: the test can only drop peaks"
        );
        assert_eq!(r1[k], r0[k], "{k:?}: the estimate itself is untouched");
    }
    // RL 200 on extended targets sharpens noise into peaks; the data do not show them.
    let k = (
        "rl".to_string(),
        "iterations=200".to_string(),
        "extended".to_string(),
        "8".to_string(),
    );
    assert!(f1[&k] < 0.5 * f0[&k], "false {} -> {}", f0[&k], f1[&k]);
    assert!(t1[&k] > 0.9 * t0[&k], "true {} -> {}", t0[&k], t1[&k]);
    // A negative multiple, or the test on a scene's steps, is refused.
    let bad = dir.path().join("bad");
    let o = fwlidar(&["tradeoff", "--out", bad.to_str().unwrap(), "--peak-snr=-1"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("non-negative multiple"));
    let o = fwlidar(&[
        "tradeoff",
        "--out",
        bad.to_str().unwrap(),
        "--peak-snr",
        "2",
        "--scene",
        "config/scenes/tree_plot.toml",
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--peak-floor alone"));
    assert!(!bad.exists(), "nothing written");
}
