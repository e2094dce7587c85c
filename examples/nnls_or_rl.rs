//! The measurement behind docs/accuracy.md, "Choosing NNLS or RL per pulse": on the tradeoff
//! sweep's simulated pulses, NNLS drawn as the 2 ns pulse (spikes only near echoes, τ = 4) and
//! accelerated RL to the 2 ns pulse (13 + 33 coarse iterations) side by side; the eq. 14 RMSE
//! of each, of the per-pulse oracle choice, and of the residual rule
//! `F = (χ²_RL − χ²_NNLS) / (n s²) > t`, `s² = χ²_NNLS / (n − k)`.
//!
//! `cargo run --release --example nnls_or_rl -- [PULSES_PER_CASE] [NOISE_FRACTION] [SEED]`
//! (defaults 1000, 0.03, 2012: the sweep's).

use fwlidar::signal::deconvolve::{
    Deconvolver, Gate, Gated, MethodConfig, NnlsConfig, RlConfig, Targeted,
};
use fwlidar::signal::denoise::{Denoise, DenoiseConfig};
use fwlidar::signal::kernel::{Kernel, convolve_same};
use fwlidar::sim::truth::{TRUTH_FWHM_NS, TruthFamily, TruthGenerator, TruthPulse, gaussian_pulse};

/// Bins per simulated waveform (the sweep's).
const BINS: usize = 225;
/// Thresholds of the residual rule reported.
const THRESHOLDS: [f64; 4] = [0.2, 0.3, 0.5, 0.7];

/// One pulse's squared errors (each over the truth's peak, summed over bins) and rule statistic.
struct Scored {
    case: usize,
    nnls: f64,
    rl: f64,
    f: f64,
}

/// Σ ((truth − processed) / max truth)².
fn squared_error(truth: &[f32], processed: &[f32]) -> f64 {
    let peak = truth.iter().fold(0.0f32, |m, &v| m.max(v)) as f64;
    truth
        .iter()
        .zip(processed)
        .map(|(&t, &p)| ((t as f64 - p as f64) / peak).powi(2))
        .sum()
}

/// Σ (y − x ⊛ k)², `fit` as scratch.
fn residual(y: &[f32], x: &[f32], k: &Kernel, fit: &mut [f32]) -> f64 {
    convolve_same(x, k, fit);
    y.iter()
        .zip(fit.iter())
        .map(|(&a, &b)| ((a - b) as f64).powi(2))
        .sum()
}

fn targeted(method: &MethodConfig, target: Option<f64>, taps: usize) -> Targeted {
    let gated = Gated::build(method, Gate::default_for(method), BINS, taps);
    Targeted::new(Box::new(gated), target, BINS, taps)
}

fn score_case(
    generator: &TruthGenerator,
    width_ns: f64,
    family: TruthFamily,
    (pulses, noise): (u64, f32),
    case: usize,
    out: &mut Vec<Scored>,
) {
    let k = gaussian_pulse(width_ns, 1.0).expect("pulse");
    let reduced = gaussian_pulse((width_ns.powi(2) - TRUTH_FWHM_NS.powi(2)).sqrt(), 1.0)
        .expect("reduced pulse");
    let nnls = MethodConfig::Nnls(NnlsConfig {
        support_at_noise: Some(4.0),
        ..NnlsConfig::default()
    });
    let rl = MethodConfig::RichardsonLucy(RlConfig {
        iterations: 13,
        accelerate: true,
        coarse_iterations: 33,
        ..RlConfig::default()
    });
    let mut sparse = targeted(&nnls, None, k.len());
    let mut smooth = targeted(&rl, Some(TRUTH_FWHM_NS), k.len());
    let mut denoise = Denoise::new(DenoiseConfig {
        max_samples: BINS,
        ..DenoiseConfig::default()
    });
    let mut p = TruthPulse::default();
    let [mut d, mut spikes, mut drawn, mut smoothed, mut fit] = [(); 5].map(|_| vec![0.0f32; BINS]);
    for i in 0..pulses {
        generator.pulse(family, i, &k, noise, &mut p);
        let level = denoise
            .denoise_segment(&p.received, 1.0, &mut d)
            .expect("denoise")
            .noise_v;
        sparse.run(&d, &k, level, 1.0, &mut spikes).expect("nnls");
        smooth.run(&d, &k, level, 1.0, &mut smoothed).expect("rl");
        convolve_same(&spikes, generator.truth_kernel(), &mut drawn);
        let chi_nnls = residual(&d, &spikes, &k, &mut fit);
        let chi_rl = residual(&d, &smoothed, &reduced, &mut fit);
        let nonzero = spikes.iter().filter(|&&v| v > 0.0).count();
        let s2 = chi_nnls / (BINS - nonzero.min(BINS - 1)) as f64;
        out.push(Scored {
            case,
            nnls: squared_error(&p.truth, &drawn),
            rl: squared_error(&p.truth, &smoothed),
            f: (chi_rl - chi_nnls) / (BINS as f64 * s2.max(f64::MIN_POSITIVE)),
        });
    }
}

/// Pooled eq. 14 RMSE when `nnls_when` picks NNLS for a pulse.
fn pooled(scored: &[Scored], nnls_when: impl Fn(&Scored) -> bool) -> f64 {
    let sum: f64 = scored
        .iter()
        .map(|s| if nnls_when(s) { s.nnls } else { s.rl })
        .sum();
    (sum / (scored.len() * BINS) as f64).sqrt()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, default: &str| args.get(i).cloned().unwrap_or_else(|| default.into());
    let pulses: u64 = arg(1, "1000").parse().expect("pulses per case");
    let noise: f32 = arg(2, "0.03").parse().expect("noise fraction");
    let seed: u64 = arg(3, "2012").parse().expect("seed");
    let generator = TruthGenerator::new(BINS, 1.0, seed).expect("generator");
    let mut scored = Vec::new();
    let mut names = Vec::new();
    for width in [4.0, 8.0, 16.0] {
        for family in TruthFamily::ALL {
            score_case(
                &generator,
                width,
                family,
                (pulses, noise),
                names.len(),
                &mut scored,
            );
            names.push(format!("{} {width} ns", family.name()));
        }
    }
    println!("noise {noise}, {pulses} pulses per case, seed {seed}; eq. 14 RMSE");
    println!("| case | NNLS to 2 ns | RL-acc to 2 ns 13+33 | oracle |");
    for (c, name) in names.iter().enumerate() {
        let of: Vec<&Scored> = scored.iter().filter(|s| s.case == c).collect();
        let rmse = |pick: &dyn Fn(&Scored) -> f64| {
            (of.iter().map(|s| pick(s)).sum::<f64>() / (of.len() * BINS) as f64).sqrt()
        };
        println!(
            "| {name} | {:.4} | {:.4} | {:.4} |",
            rmse(&|s| s.nnls),
            rmse(&|s| s.rl),
            rmse(&|s| s.nnls.min(s.rl))
        );
    }
    println!(
        "pooled: NNLS {:.4}, RL {:.4}, oracle {:.4}",
        pooled(&scored, |_| true),
        pooled(&scored, |_| false),
        pooled(&scored, |s| s.nnls < s.rl)
    );
    for t in THRESHOLDS {
        println!("rule F > {t}: {:.4}", pooled(&scored, |s| s.f > t));
    }
}
