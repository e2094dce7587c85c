//! Gaussian decomposition of real NEON (Harvard Forest) return waveforms, compared with the
//! decomposition the waveformlidar R package ships for the same 500 waveforms
//! (`decom_result.csv`: 713 components in 482 waveforms).
//!
//! Fixtures: `return.csv` holds 500 waveforms × 208 columns (header `V1..V208`), 1 ns bins,
//! digitizer counts on a ~200-220 DN baseline, zero-padded at the end (real lengths 68-196).
//! Eight waveforms also contain an inner run of zeros: a gap between two recorded segments
//! (the R package turns zeros into NA and keeps the bin numbering). Each non-zero run becomes a
//! return segment of a pulse, starting at its bin, so positions stay in record bins.
//!
//! The chain is the crate's own: the `denoise` stage (median of the first 8 samples as the
//! baseline, 0.2 GHz low-pass, noise level) then the `decompose` stage with default settings.
//! That is closer to the real pipeline than a hand-made baseline removal, at the cost of a
//! different baseline convention from the R package (see the amplitude offset below).
//!
//! The R package's `decom` (read from its source, not copied): bins `x = 1, 2, …` (1-based,
//! so its `u − 1` is our 0-based bin), baseline `min(y) − 1`, a 3-bin running mean, local maxima
//! above 0.22 × the waveform's maximum as initial peaks, `nlsLM` without bounds, fits with a
//! negative amplitude discarded (the 18 waveforms without a result). Its peaks below 22 % of the
//! maximum are never fitted, so components we find there count as "extra" by construction.
//!
//! The asserted setting is the package's method in our terms: its selection rule
//! (`min_relative_amplitude = 0.22`), a converged fit (`max_iterations = 200`), no residual
//! refinement, and local maxima standing out of the noise (`min_prominence_snr = 2`: the
//! 0.2 GHz low-pass leaves flat spots on the long NEON tails that are maxima a few hundredths
//! of the noise high, which the package's 3-bin running mean does not have; each split an echo
//! the package fits with one Gaussian).
//!
//! A second asserted setting is the opt-in waveformlidar-compatible decomposition
//! (`docs/signal.md`): the package's baseline convention (raw counts − the record's minimum + 1),
//! its 3-bin running mean, its peak rule and its start values, each a decompose option; the
//! ablation rows put our choices back one at a time.

use fwlidar::pipeline::testing::run_stage;
use fwlidar::pulse::{Pulse, SegmentKind};
use fwlidar::signal::peaks::PeakRule;
use fwlidar::signal::{
    Decompose, DecomposeBaseline, DecomposeConfig, Denoise, DenoiseConfig, StartValues,
};

/// One component of the R package's result: waveform index (1-based), A, u (1-based bin), σ.
struct Reference {
    waveform: usize,
    amplitude: f64,
    center_bins: f64,
    sigma_bins: f64,
}

fn read_reference(text: &str) -> Vec<Reference> {
    let mut lines = text.lines();
    let header = lines.next().expect("header");
    assert!(header.starts_with("index,A,u,sigma"), "{header}");
    lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            Reference {
                waveform: v[0] as usize,
                amplitude: v[1],
                // 1-based bins to our 0-based ones.
                center_bins: v[2] - 1.0,
                sigma_bins: v[3],
            }
        })
        .collect()
}

/// Pulses built from `return.csv`: one return segment per run of non-zero counts.
fn read_waveforms(text: &str) -> Vec<Pulse> {
    let mut lines = text.lines();
    let header = lines.next().expect("header");
    assert!(
        header.starts_with("V1,"),
        "expected a V1.. header: {header}"
    );
    lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let counts: Vec<u16> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            let mut p = Pulse {
                sample_ns: 1.0,
                ..Pulse::default()
            };
            let mut i = 0;
            while i < counts.len() {
                if counts[i] == 0 {
                    i += 1;
                    continue;
                }
                let start = i;
                while i < counts.len() && counts[i] != 0 {
                    i += 1;
                }
                p.push_segment(
                    SegmentKind::Return,
                    0,
                    start as f64,
                    counts[start..i].iter().copied(),
                );
            }
            p
        })
        .collect()
}

/// What one comparison found (ours − reference for the matched components).
struct Comparison {
    matched: usize,
    ours_total: usize,
    ours_in_ref_waveforms: usize,
    extra_in_ref_waveforms: usize,
    d_mu: Vec<f64>,
    d_sigma: Vec<f64>,
    r_amp: Vec<f64>,
}

/// Decomposes the denoised pulses with `config` and matches the result with the reference:
/// per waveform, greedy one-to-one, each reference component taking the nearest of our unused
/// components within ±1 ns (1 bin).
fn compare(denoised: &[Pulse], reference: &[Reference], config: DecomposeConfig) -> Comparison {
    let run = run_stage(
        &mut Decompose::new(config),
        denoised.iter().map(|p| {
            let mut q = Pulse {
                sample_ns: p.sample_ns,
                noise: p.noise,
                ..Pulse::default()
            };
            q.segments.clone_from(&p.segments);
            q.raw.clone_from(&p.raw);
            q.signal.clone_from(&p.signal);
            q
        }),
    )
    .unwrap();
    assert_eq!(run.emitted.len(), 500, "dropped: {:?}", run.dropped);
    let mut c = Comparison {
        matched: 0,
        ours_total: 0,
        ours_in_ref_waveforms: 0,
        extra_in_ref_waveforms: 0,
        d_mu: Vec::new(),
        d_sigma: Vec::new(),
        r_amp: Vec::new(),
    };
    for (w, p) in run.emitted.iter().enumerate() {
        let ours = &p.returns;
        c.ours_total += ours.len();
        let refs: Vec<&Reference> = reference.iter().filter(|r| r.waveform == w + 1).collect();
        if refs.is_empty() {
            continue;
        }
        c.ours_in_ref_waveforms += ours.len();
        let mut used = vec![false; ours.len()];
        for r in &refs {
            let best = ours
                .iter()
                .enumerate()
                .filter(|(i, o)| !used[*i] && (o.time_ns - r.center_bins).abs() <= 1.0)
                .min_by(|a, b| {
                    (a.1.time_ns - r.center_bins)
                        .abs()
                        .total_cmp(&(b.1.time_ns - r.center_bins).abs())
                });
            if let Some((i, o)) = best {
                used[i] = true;
                c.matched += 1;
                c.d_mu.push(o.time_ns - r.center_bins);
                c.d_sigma.push(o.sigma_bins as f64 - r.sigma_bins);
                c.r_amp.push(o.amplitude as f64 / r.amplitude);
            }
        }
        c.extra_in_ref_waveforms += used.iter().filter(|u| !**u).count();
    }
    c
}

/// The `q` quantile (0..1, nearest rank) of `v`.
fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

fn report(name: &str, c: &Comparison, reference: usize) {
    let abs = |v: &[f64]| v.iter().map(|x| x.abs()).collect::<Vec<_>>();
    let amp_dev: Vec<f64> = c.r_amp.iter().map(|r| (r - 1.0).abs()).collect();
    println!(
        "NEON HARV [{name}]: matched {}/{reference} ({:.1} %); ours {} in 500 waveforms, {} in \
         the 482 with a reference, {} of those extra; μ diff median {:+.3} bin, |μ| p90 {:.3}; \
         σ diff median {:+.3} bin, |σ| p90 {:.3}; A ratio median {:.3}, |A ratio − 1| p90 {:.3}",
        c.matched,
        100.0 * c.matched as f64 / reference as f64,
        c.ours_total,
        c.ours_in_ref_waveforms,
        c.extra_in_ref_waveforms,
        quantile(&c.d_mu, 0.5),
        quantile(&abs(&c.d_mu), 0.9),
        quantile(&c.d_sigma, 0.5),
        quantile(&abs(&c.d_sigma), 0.9),
        quantile(&c.r_amp, 0.5),
        quantile(&amp_dev, 0.9),
    );
}

#[test]
fn neon_harv_decomposition_matches_the_reference() {
    let dir = fwlidar::fixtures::dir().join("waveform/neon_harv");
    let waveforms = std::fs::read_to_string(dir.join("return.csv")).expect("return.csv");
    let reference = std::fs::read_to_string(dir.join("decom_result.csv")).expect("decom csv");
    let pulses = read_waveforms(&waveforms);
    let reference = read_reference(&reference);
    assert_eq!(pulses.len(), 500);
    assert_eq!(reference.len(), 713);

    let denoised = run_stage(&mut Denoise::new(DenoiseConfig::default()), pulses).unwrap();
    assert_eq!(denoised.emitted.len(), 500);
    let denoised: Vec<Pulse> = denoised.emitted.into_iter().map(|p| *p).collect();

    // The package's method in our terms (module documentation).
    let package = DecomposeConfig {
        min_relative_amplitude: 0.22,
        min_prominence_snr: 2.0,
        refine_passes: 0,
        max_iterations: 200,
        ..DecomposeConfig::default()
    };
    // The defaults (only min_snr × noise) and the ablations that explain their difference
    // from the reference (docs/accuracy.md), for the record; asserted: the package's method.
    for (name, config) in [
        ("defaults", DecomposeConfig::default()),
        (
            "defaults, no residual refinement",
            DecomposeConfig {
                refine_passes: 0,
                ..DecomposeConfig::default()
            },
        ),
        (
            "min_relative_amplitude 0.22",
            DecomposeConfig {
                min_relative_amplitude: 0.22,
                ..DecomposeConfig::default()
            },
        ),
        (
            "min_relative_amplitude 0.22, no refinement",
            DecomposeConfig {
                min_relative_amplitude: 0.22,
                refine_passes: 0,
                ..DecomposeConfig::default()
            },
        ),
        (
            "0.22, min_prominence_snr 2",
            DecomposeConfig {
                min_relative_amplitude: 0.22,
                min_prominence_snr: 2.0,
                ..DecomposeConfig::default()
            },
        ),
        (
            "0.22, min_prominence_snr 2, no refinement",
            DecomposeConfig {
                max_iterations: 30,
                ..package.clone()
            },
        ),
    ] {
        report(
            name,
            &compare(&denoised, &reference, config),
            reference.len(),
        );
    }
    let c = compare(&denoised, &reference, package);
    report(
        "0.22, min_prominence_snr 2, no refinement, max_iterations 200",
        &c,
        reference.len(),
    );
    let share = c.matched as f64 / reference.len() as f64;
    let extra_in_ref_waveforms = c.extra_in_ref_waveforms;
    let d_mu = c.d_mu;
    // Measured on 2026-11-25: 654/713 matched (91.7 %), 54 extra components in the 482
    // waveforms with a reference; before the prominence test and the converged fit (the
    // relative threshold alone, refinement on) 632 (88.6 %) and 74. The target is 95 %;
    // what is left is mostly the package's baseline (`min − 1`, a pedestal its Gaussians
    // absorb) and its 3-bin running mean, not ours to copy (docs/accuracy.md). The thresholds
    // sit between the two: a return to the old share or old extras fails, numerical noise
    // (LM path, f32 rounding) passes.
    assert!(share >= 0.90, "matched share {share}");
    assert!(
        extra_in_ref_waveforms <= 62,
        "{extra_in_ref_waveforms} extra components"
    );
    let mean_mu = d_mu.iter().sum::<f64>() / d_mu.len() as f64;
    assert!(
        mean_mu.abs() < 0.2,
        "systematic centre offset {mean_mu} bin"
    );

    // The waveformlidar-compatible decomposition (docs/signal.md): the package's `decom`
    // reproduced option by option, for users who must compare with its products. Each
    // ablation row puts one of our own choices back, to show what each option is worth.
    let waveformlidar = DecomposeConfig::waveformlidar_compatible();
    for (name, config) in [
        (
            "waveformlidar, but the denoised signal (pre-trigger median, 0.2 GHz low-pass)",
            DecomposeConfig {
                baseline: DecomposeBaseline::Denoised,
                running_mean_bins: 0,
                ..waveformlidar.clone()
            },
        ),
        (
            "waveformlidar, but the denoised signal with the running mean",
            DecomposeConfig {
                baseline: DecomposeBaseline::Denoised,
                ..waveformlidar.clone()
            },
        ),
        (
            "waveformlidar, but no running mean",
            DecomposeConfig {
                running_mean_bins: 0,
                ..waveformlidar.clone()
            },
        ),
        (
            "waveformlidar, but peak_rule rise_and_fall",
            DecomposeConfig {
                peak_rule: PeakRule::RiseAndFall,
                ..waveformlidar.clone()
            },
        ),
        (
            "waveformlidar, but start_values half_width",
            DecomposeConfig {
                start_values: StartValues::HalfWidth,
                ..waveformlidar.clone()
            },
        ),
        (
            "waveformlidar, but sigma_max_bins 30",
            DecomposeConfig {
                sigma_max_bins: 30.0,
                ..waveformlidar.clone()
            },
        ),
    ] {
        report(
            name,
            &compare(&denoised, &reference, config),
            reference.len(),
        );
    }
    let c = compare(&denoised, &reference, waveformlidar);
    report("waveformlidar-compatible", &c, reference.len());
    // Measured on 2026-11-26: 702/713 matched (98.5 %), 14 extra components in the 482
    // waveforms with a reference, |Δμ| p90 0.049 bin, A ratio median 1.000 (|ratio − 1| p90
    // 0.005); the best setting in our own terms above: 654 (91.7 %) and 54. The thresholds
    // sit between the two: losing any one option (each ablation above) fails at least one of
    // them, numerical noise (LM path, f32 rounding) passes.
    let share = c.matched as f64 / reference.len() as f64;
    assert!(
        share >= 0.97,
        "waveformlidar-compatible: matched share {share}"
    );
    assert!(
        c.extra_in_ref_waveforms <= 30,
        "waveformlidar-compatible: {} extra components",
        c.extra_in_ref_waveforms
    );
    // Not only the positions: the package's parameters themselves.
    let abs_mu: Vec<f64> = c.d_mu.iter().map(|d| d.abs()).collect();
    let p90 = quantile(&abs_mu, 0.9);
    assert!(p90 < 0.15, "waveformlidar-compatible: |Δμ| p90 {p90} bin");
    let amp = quantile(&c.r_amp, 0.5);
    assert!(
        (amp - 1.0).abs() < 0.01,
        "waveformlidar-compatible: A ratio median {amp}"
    );
}
