//! Returns that agree with the instrument's own processor (issue 55): the system response is
//! learned from each input's own echoes and echoes are found against it, with the embedded
//! configuration and no per-file setting; checked against RiPROCESS's points of the same RIEGL
//! LMS-Q680i pulses with `fwlidar compare`, on every real waveform file of `tests/data`, against
//! the truth where it is known (the simulator's pulses, NEON's hard-target response), and
//! through `fwlidar response learn` and a configuration that names its file.

mod common;

use std::path::{Path, PathBuf};

use common::{fixture, fwlidar, text};

const RIEGL_PLS: &str = "waveform/riegl_q680i/100429_152240_2535pt_UTM.pls";

/// `fwlidar replay FILE --out DIR` with the embedded configuration; the summary as JSON.
fn replay(input: &Path, out: &Path, sets: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "replay".to_string(),
        input.display().to_string(),
        "--out".into(),
        out.display().to_string(),
        "--no-progress".into(),
    ];
    for s in sets {
        args.push("--set".into());
        args.push(s.to_string());
    }
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = fwlidar(&args);
    assert!(o.status.success(), "{}", text(&o.stderr));
    serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap()
}

/// `fwlidar compare OURS REF --json`.
fn compare(ours: &Path, reference: &Path) -> serde_json::Value {
    let o = fwlidar(&[
        "compare",
        ours.to_str().unwrap(),
        reference.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// The targets on the RIEGL fixture, replayed with the embedded configuration: ≥ 98 %
/// of RiPROCESS's echoes within 0.15 m, ≥ 85 % of ours are RiPROCESS echoes, ≤ 1.2 × its
/// returns per pulse, no intensity clipped and its rank correlation with RiPROCESS's
/// `Amplitude` ≥ 0.9.
#[test]
fn riegl_returns_agree_with_riprocess() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let summary = replay(&fixture(RIEGL_PLS), &out, &[]);
    assert_eq!(
        summary["response"]["model"], "response",
        "{}",
        summary["response"]
    );
    assert!(
        summary["response"]["source"]
            .as_str()
            .unwrap()
            .starts_with("learned from the first 2368 pulses"),
        "{}",
        summary["response"]
    );
    assert_eq!(summary["sinks"]["las"]["intensity_at_full_scale"], 0);
    let c = compare(&out.join("returns.las"), &fixture(common::RIEGL_LAS));
    eprintln!("RIEGL Q680i against RiPROCESS: {c:#}");
    let f = |k: &str| c[k].as_f64().unwrap();
    assert_eq!(c["pulses_in_both"], 2368, "{c}");
    assert!(f("reference_found") >= 0.98, "{c}");
    assert!(f("ours_are_reference") >= 0.85, "{c}");
    assert!(f("returns_ratio") <= 1.2, "{c}");
    assert!(f("intensity_rank_correlation") >= 0.9, "{c}");
    assert_eq!(c["our_intensity_clipped"], 0, "{c}");
    assert_eq!(c["reference_amplitude"], "Amplitude extra byte");
    assert!(f("median_distance_m") < 0.01, "{c}");
    // The figure, on request.
    let fig = dir.path().join("cmp.svg");
    let o = fwlidar(&[
        "compare",
        out.join("returns.las").to_str().unwrap(),
        fixture(common::RIEGL_LAS).to_str().unwrap(),
        "--figure",
        fig.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    assert!(text(&o.stdout).contains("% found"), "{}", text(&o.stdout));
    assert!(std::fs::read_to_string(&fig).unwrap().starts_with("<svg"));
}

/// Every real waveform file replays with a response learned from it (none of them is Gaussian),
/// and none gives many returns per pulse that are not echoes: these are single-surface files
/// (a flat field, an ice sheet, a LAS 1.3 line of weak ground echoes), where the Gaussian model
/// gave 2.9-5.5 returns per pulse.
#[test]
fn every_real_file_replays_against_its_own_response() {
    let dir = tempfile::tempdir().unwrap();
    for (rel, most) in [
        (common::RIEGL_LAS, 1.2),
        ("waveform/pulsewaves/lvis_example1.pls", 1.2),
        ("waveform/pulsewaves/las13fwf_example1.pls", 1.2),
    ] {
        let out = dir.path().join(Path::new(rel).file_stem().unwrap());
        let s = replay(&fixture(rel), &out, &[]);
        assert_eq!(
            s["response"]["model"], "response",
            "{rel}: {}",
            s["response"]
        );
        let ch = &s["response"]["channels"][0];
        assert_eq!(ch["gaussian"], false, "{rel}: {ch}");
        let per_pulse =
            s["sinks"]["las"]["points"].as_f64().unwrap() / s["pulses_out"].as_f64().unwrap();
        eprintln!("{rel}: {per_pulse:.3} returns per pulse; {ch}");
        assert!(per_pulse >= 0.95 && per_pulse <= most, "{rel}: {per_pulse}");
        assert_eq!(s["sinks"]["las"]["intensity_at_full_scale"], 0, "{rel}");
    }
}

/// The simulator's pulses are Gaussian, and the learned response says so: the decomposition
/// stays Gaussian (the returns are those of `model = "gaussian"`, bit for bit), and the learned
/// width is the scene's pulse within 8 % (measured: −6.4 % for `two_layer`, whose echoes stand
/// only ~23 σ high, so that the narrower half of their noisy widths is narrower than the pulse;
/// −4.3 % for `tree_plot`, +0.6 % for the survey line).
#[test]
fn the_simulator_keeps_its_gaussians_and_its_pulse_width_is_learned() {
    let dir = tempfile::tempdir().unwrap();
    let root = Path::new(common::ROOT);
    for (capture, fwhm_ns) in [
        ("replay/two_layer.fwcap", 16.0),
        ("replay/tree_plot.fwcap", 16.0),
        ("replay/survey_line.fwcap", 8.0),
    ] {
        let stem = Path::new(capture).file_stem().unwrap().to_str().unwrap();
        let auto = dir.path().join(format!("{stem}_auto"));
        let s = replay(&root.join(capture), &auto, &["output.returns=true"]);
        assert_eq!(
            s["response"]["model"], "gaussian",
            "{capture}: {}",
            s["response"]
        );
        let learned = s["response"]["channels"][0]["fwhm_ns"].as_f64().unwrap();
        eprintln!("{capture}: learned FWHM {learned:.2} ns, scene {fwhm_ns} ns");
        assert!(
            (learned / fwhm_ns - 1.0).abs() < 0.08,
            "{capture}: {learned}"
        );
        let plain = dir.path().join(format!("{stem}_gauss"));
        replay(
            &root.join(capture),
            &plain,
            &[
                "output.returns=true",
                "pipeline.stages[2].model=\"gaussian\"",
            ],
        );
        assert_eq!(
            std::fs::read(auto.join("returns.csv")).unwrap(),
            std::fs::read(plain.join("returns.csv")).unwrap(),
            "{capture}"
        );
    }
}

/// NEON's `imp.csv` is a hard-target return of the system whose forest waveforms `return.csv`
/// holds: the response learned from the forest rows alone is compared with it. The forest
/// holds few hard targets (its narrowest strong echoes are 17-19 ns wide against the target's
/// 16 ns), so the learned response is broader on its trailing side; its leading edge and peak
/// agree.
#[test]
fn neon_learned_response_against_its_hard_target() {
    use fwlidar::signal::learned_response::ResponseLearner;
    let rows = read_rows(&fixture("waveform/neon_harv/return.csv"));
    let mut learner = ResponseLearner::new();
    for r in &rows {
        learner.add_segment(0, 1.0, r, 4095.0);
    }
    let file = learner.finish("NEON return.csv").unwrap();
    let r = &file.responses[0];
    let imp = read_rows(&fixture("waveform/neon_harv/imp.csv"))
        .into_iter()
        .flatten()
        .collect::<Vec<f32>>();
    let (base, _) = fwlidar::signal::learned_response::pretrigger_floor(&imp, 1.0);
    let (i, top) = imp
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(i, v)| (i, *v))
        .unwrap();
    let (a, c, d) = (imp[i - 1], imp[i], imp[i + 1]);
    let t0 = i as f32 + 0.5 * (a - d) / (a - 2.0 * c + d);
    let truth = |x: f32| {
        let t = t0 + x;
        let k = t.floor() as usize;
        let w = t - k as f32;
        ((imp[k] * (1.0 - w) + imp[k + 1] * w) - base) / (top - base)
    };
    let (mut lead, mut trail, mut n_lead, mut n_trail) = (0.0f32, 0.0f32, 0, 0);
    let mut x = -10.0f32;
    while x <= 30.0 {
        let d = (r.value_at(x) - truth(x)).powi(2);
        if x <= 2.0 {
            lead += d;
            n_lead += 1;
        } else {
            trail += d;
            n_trail += 1;
        }
        x += 0.25;
    }
    let lead = (lead / n_lead as f32).sqrt();
    let trail = (trail / n_trail as f32).sqrt();
    eprintln!(
        "NEON: learned from {} of {} candidate echoes, FWHM {:.1} ns (hard target {:.1}); RMS \
         difference from the hard target {lead:.3} of the peak before +2 ns, {trail:.3} after",
        r.echoes,
        r.candidates,
        r.fwhm_samples,
        fwhm(&imp, base, i)
    );
    // Measured: 0.059 and 0.106 of the peak, FWHM 18.3 ns against 15.1 (docs/accuracy.md).
    assert!(lead < 0.08, "leading edge {lead}");
    assert!(trail < 0.15, "trailing side {trail}");
    let ratio = r.fwhm_samples / fwhm(&imp, base, i);
    assert!((1.0..1.35).contains(&ratio), "FWHM ratio {ratio}");
    assert!(!r.is_gaussian());
}

/// FWHM of the peak at `i` above `base`, samples.
fn fwhm(y: &[f32], base: f32, i: usize) -> f32 {
    let h = base + 0.5 * (y[i] - base);
    let (mut l, mut r) = (i, i);
    while l > 0 && y[l] > h {
        l -= 1;
    }
    while r + 1 < y.len() && y[r] > h {
        r += 1;
    }
    let lf = l as f32 + (h - y[l]) / (y[l + 1] - y[l]);
    let rf = (r - 1) as f32 + (y[r - 1] - h) / (y[r - 1] - y[r]);
    rf - lf
}

/// The rows of a CSV of numbers with a header, trailing zero padding cut.
fn read_rows(path: &Path) -> Vec<Vec<f32>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let mut v: Vec<f32> = l
                .split(',')
                .filter_map(|x| x.trim().parse::<f32>().ok())
                .collect();
            while v.last() == Some(&0.0) {
                v.pop();
            }
            v
        })
        .filter(|v| !v.is_empty())
        .collect()
}

/// `fwlidar response learn` writes the response and its figure, never over a file; a
/// configuration that names the file finds the same returns as the replay that learned it.
#[test]
fn a_learned_response_file_is_used_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("q680i.toml");
    let pls = fixture(RIEGL_PLS);
    let o = learn_response(&pls, &file);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let said = text(&o.stdout);
    assert!(
        said.contains("channel 1:") && said.contains("not Gaussian"),
        "{said}"
    );
    let svg = std::fs::read_to_string(file.with_extension("svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("FWHM"), "{svg}");
    let again = learn_response(&pls, &file);
    assert_eq!(again.status.code(), Some(2));
    assert!(text(&again.stderr).contains("never written over"));

    let learned = dir.path().join("learned");
    replay(&pls, &learned, &["output.returns=true"]);
    let named = dir.path().join("named");
    let set = format!("pipeline.stages[2].response=\"{}\"", file.display());
    let s = replay(&pls, &named, &["output.returns=true", &set]);
    assert!(
        s["response"]["source"]
            .as_str()
            .unwrap()
            .starts_with("file "),
        "{}",
        s["response"]
    );
    same_returns(&learned, &named);

    // A missing file is refused naming the key.
    let e = refused(
        &pls,
        dir.path(),
        "pipeline.stages[2].response=\"nowhere.toml\"",
    );
    assert!(e.contains("pipeline.stages[2].response"), "{e}");
}

/// `compare` refuses what it cannot compare, naming the file.
#[test]
fn compare_names_what_it_cannot_read() {
    let dir = tempfile::tempdir().unwrap();
    let missing: PathBuf = dir.path().join("missing.las");
    let las = fixture(common::RIEGL_LAS);
    let o = fwlidar(&["compare", missing.to_str().unwrap(), las.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o.stderr).contains("missing.las"),
        "{}",
        text(&o.stderr)
    );
    // The simulated sample's returns share no pulse with the RIEGL line.
    let out = dir.path().join("sample");
    replay(
        &Path::new(common::ROOT).join("replay/two_layer.fwcap"),
        &out,
        &[],
    );
    let o = fwlidar(&[
        "compare",
        out.join("returns.las").to_str().unwrap(),
        las.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o.stderr).contains("share no pulse"),
        "{}",
        text(&o.stderr)
    );
}

/// The deconvolve stage by the learned response: a LAS 1.3 waveform file records no outgoing
/// pulse, so `kernel = "outgoing"` has nothing to deconvolve by; `kernel = "learned"` (learned
/// from the input before the run) and `kernel = { response = FILE }` (the same response learned
/// by `fwlidar response learn`) deconvolve every pulse, alike; a missing file is refused
/// naming the key.
#[test]
fn the_deconvolve_stage_uses_the_learned_response() {
    let dir = tempfile::tempdir().unwrap();
    let pls = fixture("waveform/pulsewaves/las13fwf_example1.pls");
    let learned = dir.path().join("learned");
    let s = replay(
        &pls,
        &learned,
        &[
            "output.returns=true",
            "pipeline.stages[1].kernel=\"learned\"",
        ],
    );
    let deconvolve = &s["stages"][1];
    assert_eq!(deconvolve["name"], "deconvolve");
    assert_eq!(deconvolve["received"], 1000, "{deconvolve}");
    assert_eq!(deconvolve["sent"], 1000, "{deconvolve}");
    assert_eq!(s["pulses_out"], 1000);

    let file = dir.path().join("r.toml");
    let o = learn_response(&pls, &file);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let named = dir.path().join("named");
    let set = format!(
        "pipeline.stages[1].kernel={{ response = \"{}\" }}",
        file.display()
    );
    let s = replay(&pls, &named, &["output.returns=true", &set]);
    assert_eq!(s["stages"][1]["sent"], 1000);
    same_returns(&learned, &named);

    let e = refused(
        &pls,
        dir.path(),
        "pipeline.stages[1].kernel={ response = \"nowhere.toml\" }",
    );
    assert!(
        e.contains("kernel.response") && e.contains("nowhere.toml"),
        "{e}"
    );
}

/// The two replays' `returns.csv` are byte for byte the same.
fn same_returns(a: &Path, b: &Path) {
    assert_eq!(
        std::fs::read(a.join("returns.csv")).unwrap(),
        std::fs::read(b.join("returns.csv")).unwrap()
    );
}

/// A replay of `input` with `set` is refused as a usage error (exit 2); its stderr.
fn refused(input: &Path, dir: &Path, set: &str) -> String {
    let o = fwlidar(&[
        "replay",
        input.to_str().unwrap(),
        "--out",
        dir.join("x").to_str().unwrap(),
        "--set",
        set,
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o.stderr));
    text(&o.stderr)
}

/// `fwlidar response learn INPUT --out FILE`.
fn learn_response(input: &Path, file: &Path) -> std::process::Output {
    fwlidar(&[
        "response",
        "learn",
        input.to_str().unwrap(),
        "--out",
        file.to_str().unwrap(),
    ])
}
