//! The measurement behind docs/accuracy.md, "Choosing NNLS or RL per pulse": on the tradeoff
//! sweep's simulated pulses, NNLS drawn as the 2 ns pulse (spikes only near echoes, τ = 4) and
//! accelerated RL to the 2 ns pulse (13 + 33 coarse iterations) side by side; the eq. 14 RMSE
//! of each, of the per-pulse oracle choice, and of the residual rule
//! `F = (χ²_RL − χ²_NNLS) / (n s²) > t`, `s² = χ²_NNLS / (n − k)`. Also, per case, how
//! often NNLS is the better of the two; rules tried and not adopted (docs/accuracy.md, "NNLS
//! only where RL misfits"): running NNLS only when `χ²_RL` exceeds `c · n σ²` (σ the denoise
//! step's noise level), an AIC-like penalty on NNLS's spike count, and choosing by how much
//! wider the data's runs above the noise are than a single pulse's ("extendedness").
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
    /// RL's squared residual over the noise floor, `χ²_RL / (n σ²)`.
    r: f64,
    /// NNLS's squared residual over the noise floor, `χ²_NNLS / (n σ²)`.
    q: f64,
    /// Nonzero spikes of NNLS.
    k: usize,
    /// Extendedness at 3, 4 and 6 noise levels (energy-weighted run length over a single pulse's).
    e: [f64; 3],
}

/// Taps of `k` at or above `frac` of its peak (at least 1): the width, in samples, of a single
/// pulse's run above a level at `frac` of its peak.
fn kernel_width_above(k: &Kernel, frac: f64) -> f64 {
    let peak = k.taps.iter().fold(0.0f32, |m, &v| m.max(v)) as f64;
    let count = k.taps.iter().filter(|&&v| v as f64 >= frac * peak).count();
    count.max(1) as f64
}

/// Energy-weighted mean over the runs of `d` above `level` of run length / single-pulse width
/// above `level` at the run's peak (1 for isolated pulses, more for extended returns).
fn extendedness(d: &[f32], k: &Kernel, level: f64) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    let mut i = 0;
    while i < d.len() {
        if (d[i] as f64) <= level {
            i += 1;
            continue;
        }
        let start = i;
        let (mut peak, mut energy) = (0.0f64, 0.0f64);
        while i < d.len() && (d[i] as f64) > level {
            peak = peak.max(d[i] as f64);
            energy += d[i] as f64;
            i += 1;
        }
        let ratio = (i - start) as f64 / kernel_width_above(k, level / peak);
        num += energy * ratio;
        den += energy;
    }
    if den > 0.0 { num / den } else { 0.0 }
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
            r: chi_rl / (BINS as f64 * (level as f64).powi(2)).max(f64::MIN_POSITIVE),
            q: chi_nnls / (BINS as f64 * (level as f64).powi(2)).max(f64::MIN_POSITIVE),
            k: nonzero,
            e: [3.0, 4.0, 6.0].map(|t| extendedness(&d, &k, t * level as f64)),
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
    let q = |v: &mut Vec<f64>, p: f64| {
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            f64::NAN
        } else {
            v[((v.len() - 1) as f64 * p) as usize]
        }
    };
    for (label, pick) in [("rule keeps NNLS", true), ("rule keeps RL", false)] {
        let mut r: Vec<f64> = scored
            .iter()
            .filter(|s| (s.f > 0.5) == pick)
            .map(|s| s.r)
            .collect();
        let mut qq: Vec<f64> = scored
            .iter()
            .filter(|s| (s.f > 0.5) == pick)
            .map(|s| s.q)
            .collect();
        println!(
            "{label}: {} pulses; chi_rl/(n s2) p05 {:.3} p25 {:.3} p50 {:.3} p95 {:.3}; chi_nnls/(n s2) p50 {:.3}",
            r.len(),
            q(&mut r, 0.05),
            q(&mut r, 0.25),
            q(&mut r, 0.5),
            q(&mut r, 0.95),
            q(&mut qq, 0.5)
        );
    }
    for c in [0.6, 0.8, 1.0, 1.2, 1.5, 2.0, 3.0] {
        let runs = scored.iter().filter(|s| s.r > c).count() as f64 / scored.len() as f64;
        println!(
            "gate chi_rl > {c} n s2 then F > 0.5: NNLS runs on {:.1} %, {:.4}",
            100.0 * runs,
            pooled(&scored, |s| s.r > c && s.f > 0.5)
        );
    }
    for (c, name) in names.iter().enumerate() {
        let of: Vec<&Scored> = scored.iter().filter(|s| s.case == c).collect();
        let better = of.iter().filter(|s| s.nnls < s.rl).count() as f64 / of.len() as f64;
        let kept = of.iter().filter(|s| s.f > 0.5).count() as f64 / of.len() as f64;
        let mut kb: Vec<f64> = of
            .iter()
            .filter(|s| s.nnls < s.rl)
            .map(|s| s.k as f64)
            .collect();
        let mut kw: Vec<f64> = of
            .iter()
            .filter(|s| s.nnls >= s.rl)
            .map(|s| s.k as f64)
            .collect();
        println!(
            "{name}: NNLS better on {:.0} %, rule keeps it on {:.0} %; k when NNLS better p25/50/75 {}/{}/{}, when RL better {}/{}/{}",
            100.0 * better,
            100.0 * kept,
            q(&mut kb, 0.25),
            q(&mut kb, 0.5),
            q(&mut kb, 0.75),
            q(&mut kw, 0.25),
            q(&mut kw, 0.5),
            q(&mut kw, 0.75)
        );
    }
    for (c, name) in names.iter().enumerate() {
        let of: Vec<&Scored> = scored.iter().filter(|s| s.case == c).collect();
        for j in 0..3 {
            let mut e: Vec<f64> = of.iter().map(|s| s.e[j]).collect();
            print!(
                "{name} E{j} p10/50/90 {:.2}/{:.2}/{:.2}; ",
                q(&mut e, 0.1),
                q(&mut e, 0.5),
                q(&mut e, 0.9)
            );
        }
        println!();
    }
    for j in 0..3 {
        for e0 in [1.2, 1.4, 1.6, 1.8, 2.0, 2.5, 3.0] {
            println!(
                "E{j} < {e0} -> NNLS: {:.4} (NNLS on {:.0} %); or rule: {:.4}",
                pooled(&scored, |s| s.e[j] < e0),
                100.0 * scored.iter().filter(|s| s.e[j] < e0).count() as f64 / scored.len() as f64,
                pooled(&scored, |s| s.e[j] < e0 || s.f > 0.5)
            );
        }
    }
    for a in [0.5, 1.0, 2.0, 4.0, 8.0] {
        println!(
            "rule (chi_rl - chi_nnls)/s2 > {a} k: {:.4}",
            pooled(&scored, |s| (s.r - s.q) * BINS as f64 > a * s.k as f64)
        );
    }
}
