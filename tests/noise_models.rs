//! The noise-model benchmark of issue 37 (`tests/python/noise_models.py`): held-out waveforms
//! (8 ns system pulse, 1 ns samples, a canopy of 2–4 scatterers, a ground echo and one close
//! pair at 0.75 FWHM per row, truth drawn with a 2 ns pulse) under six noise models — white
//! Gaussian, uniform with a non-zero mean, Poisson shot noise, baseline drift, 8-bit
//! quantisation, saturation — scored as RMSE / raw and close pairs resolved, with
//! scikit-image's RL-200 and scipy's NNLS in the same run. The full grid (4, 8, 16 ns pulses ×
//! 0.5, 1, 2 ns samples) is `benches/noise_models.sh`; figures in docs/accuracy.md.
//!
//! Asserted is what holds on every model today, so that a change that loses it fails: the
//! deconvolution settings of `fwlidar process` and both references beat the raw rows, and
//! RL-200 to a 2 ns target — also asked for without an iteration count — resolves at least
//! half of the close pairs; the noise-aware stop never ends worse than RL 20 (by a stated
//! margin); and `--method nnls --target-fwhm-ns 2` meets issue 37's first target on every
//! model (RMSE / raw ≤ 0.45, ≥ 60 % of the pairs, ahead of both references). What does not
//! hold yet (the tradeoff targets, the 4 ns pulse at 2 ns samples) is in docs/accuracy.md.

mod common;

fn noise_models(dir: &std::path::Path, args: &[&str]) -> (i32, String, String) {
    common::python_bench("noise_models.py", dir, args)
}

/// Every score of a run of the benchmark with `args` (its tables printed), in `dir`.
fn scores(dir: &std::path::Path, args: &[&str]) -> Vec<serde_json::Value> {
    let json = dir.join("scores.json");
    let mut all = args.to_vec();
    all.extend(["--json", json.to_str().unwrap()]);
    let (code, out, err) = noise_models(dir, &all);
    println!("{out}");
    assert_eq!(code, 0, "{out}\n{err}");
    serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap()
}

#[test]
fn every_noise_model_is_scored_beside_scikit_image_and_scipy_and_deconvolution_beats_raw() {
    let dir = tempfile::tempdir().unwrap();
    let scores = scores(dir.path(), &["--waveforms", "80", "--model", "all"]);
    let get = |model: &str, row: &str, what: &str| -> f64 {
        scores
            .iter()
            .find(|s| s["model"] == model && s["row"] == row)
            .and_then(|s| s[what].as_f64())
            .unwrap_or_else(|| panic!("{model} {row} {what} missing"))
    };
    let models = [
        "gaussian",
        "uniform_offset",
        "poisson",
        "drift",
        "quantised",
        "saturated",
        "shot_8bit",
    ];
    for m in models {
        assert_eq!(get(m, "raw", "rmse_ratio"), 1.0);
        for row in [
            "skimage-rl200",
            "scipy-nnls+2ns",
            "nnls-2ns",
            "rl200-2ns",
            "rl200",
        ] {
            let r = get(m, row, "rmse_ratio");
            assert!(r < 1.0, "{m}: {row} RMSE / raw {r} not below the raw rows'");
            assert!(
                get(m, row, "pairs") > get(m, "raw", "pairs"),
                "{m}: {row} resolves no more pairs than the raw rows"
            );
        }
        let p = get(m, "rl200-2ns", "pairs");
        assert!(p >= 0.5, "{m}: RL-200 to 2 ns resolved {p} of the pairs");
        // One command, no iteration count: the count follows from the kernel and the target
        // (200 here; the method's default of 20 resolved none).
        let p = get(m, "rl-2ns", "pairs");
        assert!(
            p >= 0.5,
            "{m}: `--method rl --target-fwhm-ns 2` resolved {p} of the pairs"
        );
        // The noise-aware stop never ends worse than a fixed small count (RL 20) by more
        // than 0.01 of RMSE / raw or 2 points of pairs (docs/accuracy.md, "The noise-aware
        // stop over the noise models").
        let (stop, fixed) = ("rl200-2ns-stop1", "rl20-2ns");
        let (rs, rf) = (get(m, stop, "rmse_ratio"), get(m, fixed, "rmse_ratio"));
        assert!(
            rs <= rf + 0.01,
            "{m}: the stop's RMSE / raw {rs} against RL 20's {rf}"
        );
        let (ps, pf) = (get(m, stop, "pairs"), get(m, fixed, "pairs"));
        assert!(
            ps >= pf - 0.02,
            "{m}: the stop resolved {ps} of the pairs, RL 20 {pf}"
        );
        // Issue 37's target, one command (`--method nnls --target-fwhm-ns 2`: the drifting
        // baseline removed, clipped samples left out, the noise-weighted refit, adjacent spikes
        // drawn at their centroid): RMSE / raw ≤ 0.45 with ≥ 60 % of the pairs, a lower RMSE
        // than both references, and no fewer pairs than the better of them but 2 points.
        let (r, p) = (
            get(m, "nnls-2ns", "rmse_ratio"),
            get(m, "nnls-2ns", "pairs"),
        );
        assert!(r <= 0.45 && p >= 0.6, "{m}: nnls-2ns {r} / {p}");
        for reference in ["skimage-rl200", "scipy-nnls+2ns"] {
            let rr = get(m, reference, "rmse_ratio");
            assert!(r < rr, "{m}: nnls-2ns RMSE / raw {r}, {reference} {rr}");
            let pr = get(m, reference, "pairs");
            assert!(p >= pr - 0.02, "{m}: nnls-2ns pairs {p}, {reference} {pr}");
        }
    }
    assert_eq!(scores.len(), models.len() * 9, "{scores:?}");
    // The inputs of the last configuration are left for a reader to rerun.
    for f in ["rows.npy", "kernel.npy"] {
        assert!(dir.path().join(f).exists(), "{f}");
    }
}

#[test]
fn an_unknown_noise_model_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let (code, _, err) = noise_models(dir.path(), &["--model", "pink"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("pink") && err.contains("gaussian"), "{err}");
}

/// Issue 55's kernel-mismatch target: rows drawn with a system pulse 10 % wider (then 10 %
/// narrower) than the kernel given, under white noise and under shot noise on an 8-bit
/// digitizer; with `--learn-kernel` (the given kernel stretched to the rows' echoes), NNLS and
/// RL to a 2 ns target end within 5 % of the RMSE they reach with the true kernel, and below
/// what the wrong kernel gives. The whole grid (seven models, three pulses, three sample
/// intervals) is `benches/kernel_mismatch.sh`; figures in docs/accuracy.md.
#[test]
fn a_kernel_known_to_ten_percent_is_learned_from_the_rows() {
    for mismatch in ["0.1", "-0.1"] {
        let dir = tempfile::tempdir().unwrap();
        let scores = scores(
            dir.path(),
            &[
                "--waveforms",
                "200",
                "--model",
                "gaussian",
                "--model",
                "shot_8bit",
                "--kernel-mismatch",
                mismatch,
                "--run",
                "nnls=--method nnls --target-fwhm-ns 2",
                "--run",
                "nnls-learn=--method nnls --target-fwhm-ns 2 --learn-kernel",
                "--run",
                "nnls@true=--method nnls --target-fwhm-ns 2",
                "--run",
                "rl=--method rl --target-fwhm-ns 2",
                "--run",
                "rl-learn=--method rl --target-fwhm-ns 2 --learn-kernel",
                "--run",
                "rl@true=--method rl --target-fwhm-ns 2",
            ],
        );
        let get = |model: &str, row: &str| -> f64 {
            scores
                .iter()
                .find(|s| s["model"] == model && s["row"] == row)
                .and_then(|s| s["rmse_ratio"].as_f64())
                .unwrap_or_else(|| panic!("{model} {row} missing"))
        };
        for m in ["gaussian", "shot_8bit"] {
            for method in ["nnls", "rl"] {
                let given = get(m, method);
                let learned = get(m, &format!("{method}-learn"));
                let truth = get(m, &format!("{method}@true"));
                assert!(
                    learned <= 1.05 * truth,
                    "{m}, true pulse {mismatch}: {method} with --learn-kernel {learned}, with \
                     the true kernel {truth}"
                );
                assert!(
                    learned < given,
                    "{m}, true pulse {mismatch}: {method} with --learn-kernel {learned}, with \
                     the kernel given {given}"
                );
            }
        }
    }
}
