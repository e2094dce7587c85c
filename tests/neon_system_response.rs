//! The system response in two stages on real NEON (Harvard Forest) waveforms, as the
//! waveformlidar R package orders it: the response `h` measured from a flat-target return
//! (`imp.csv`) and its outgoing pulse (`imp_out.csv`), every return deconvolved by `h` (stage 1,
//! `kernel = { flat_target = … }`) and then by its own outgoing pulse (`outg.csv`, stage 2,
//! `kernel = "outgoing"`), after the crate's denoise stage.
//!
//! Checked: every pulse passes, outputs are finite and non-negative, the outgoing segments are
//! not touched by the deconvolutions, and the deconvolved returns peak where the denoised
//! returns peak (zero-phase kernels: no shift in time), and the two-stage result is sharper than
//! the denoised return.

use std::path::PathBuf;

use fwlidar::pipeline::testing::run_stage;
use fwlidar::pulse::{Pulse, SegmentKind};
use fwlidar::signal::deconvolve::response::response_from_flat_target;
use fwlidar::signal::deconvolve::{GoldConfig, MethodConfig};
use fwlidar::signal::{Denoise, DenoiseConfig};
use fwlidar::stages::deconvolve::{Deconvolve, DeconvolveConfig, KernelSource};

/// The NEON fixtures folder (`tests/data/waveform/neon_harv`, or under `$FWLIDAR_FIXTURES`).
fn neon() -> Option<PathBuf> {
    let d = fwlidar::fixtures::dir().join("waveform/neon_harv");
    assert!(d.join("imp.csv").is_file(), "missing {}", d.display());
    Some(d)
}

/// Rows of a CSV with a header line, as numbers.
fn rows(path: &PathBuf) -> Vec<Vec<f32>> {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.split(',').map(|x| x.trim().parse().unwrap()).collect())
        .collect()
}

/// A column file (one value per line) without its trailing zero padding.
fn column(path: &PathBuf) -> Vec<f32> {
    let mut v: Vec<f32> = rows(path).into_iter().map(|r| r[0]).collect();
    while v.last() == Some(&0.0) {
        v.pop();
    }
    v
}

/// Waveformlidar's deconvolution settings for simple waveforms ("small_paras": 30 iterations,
/// 2 repetitions, boost 1.8), Gold.
fn gold() -> MethodConfig {
    MethodConfig::Gold(GoldConfig {
        iterations: 30,
        repetitions: 2,
        boost: 1.8,
        stop_at_noise: None,
    })
}

#[test]
fn neon_two_stage_system_response() {
    let Some(dir) = neon() else { return };
    let imp = column(&dir.join("imp.csv"));
    let imp_out = column(&dir.join("imp_out.csv"));
    assert_eq!((imp.len(), imp_out.len()), (80, 56));
    let outg = rows(&dir.join("outg.csv"));
    let ret = rows(&dir.join("return.csv"));
    assert_eq!((outg.len(), ret.len()), (500, 500));

    // The measured response: the flat target's echo has the shape of its outgoing pulse (both
    // ~15 bins wide at half maximum, the same tail), so h is narrow.
    let h = response_from_flat_target(&imp, &imp_out, &gold(), 256).expect("response");
    let core: f32 = h.taps[h.center.saturating_sub(2)..(h.center + 3).min(h.len())]
        .iter()
        .sum();
    println!(
        "NEON h: {} taps, centre {}, ±2 bins hold {core:.3}",
        h.len(),
        h.center
    );
    assert!(core > 0.5, "h is not narrow: {:?}", h);

    let pulses: Vec<Pulse> = outg
        .iter()
        .zip(&ret)
        .map(|(o, r)| {
            let mut p = Pulse {
                sample_ns: 1.0,
                ..Pulse::default()
            };
            let n = o.iter().rposition(|&v| v != 0.0).map_or(0, |i| i + 1);
            p.push_segment(
                SegmentKind::Outgoing,
                0,
                0.0,
                o[..n].iter().map(|&v| v as u16),
            );
            let mut i = 0;
            while i < r.len() {
                if r[i] == 0.0 {
                    i += 1;
                    continue;
                }
                let start = i;
                while i < r.len() && r[i] != 0.0 {
                    i += 1;
                }
                p.push_segment(
                    SegmentKind::Return,
                    0,
                    start as f64,
                    r[start..i].iter().map(|&v| v as u16),
                );
            }
            p
        })
        .collect();
    let denoised = run_stage(&mut Denoise::new(DenoiseConfig::default()), pulses).unwrap();
    assert_eq!(denoised.emitted.len(), 500);
    let before: Vec<Vec<f32>> = denoised.emitted.iter().map(|p| p.signal.clone()).collect();
    let mut first = Deconvolve::new(DeconvolveConfig {
        kernel: KernelSource::FlatTarget {
            ground_return: imp.clone(),
            outgoing: imp_out.clone(),
        },
        ..DeconvolveConfig::with_method(gold())
    })
    .unwrap();
    let mut second = Deconvolve::new(DeconvolveConfig::with_method(gold())).unwrap();
    let run = run_stage(&mut first, denoised.emitted.into_iter().map(|p| *p)).unwrap();
    assert_eq!(run.emitted.len(), 500, "stage 1 dropped {:?}", run.dropped);
    let run = run_stage(&mut second, run.emitted.into_iter().map(|p| *p)).unwrap();
    assert_eq!(run.emitted.len(), 500, "stage 2 dropped {:?}", run.dropped);

    let (mut segments, mut in_place, mut sharper) = (0usize, 0usize, 0usize);
    let mut shifts = Vec::new();
    for (p, b) in run.emitted.iter().zip(&before) {
        let o = p.outgoing().expect("outgoing");
        assert_eq!(
            p.signal_of(o),
            &b[p.segments[o].range()],
            "outgoing touched"
        );
        for (si, seg) in p.segments.iter().enumerate() {
            if seg.kind != SegmentKind::Return || seg.len < 16 {
                continue;
            }
            let y = p.signal_of(si);
            assert!(y.iter().all(|v| v.is_finite() && *v >= 0.0), "{y:?}");
            let raw = &b[seg.range()];
            let argmax = |x: &[f32]| {
                x.iter()
                    .enumerate()
                    .max_by(|a, b| a.1.total_cmp(b.1))
                    .unwrap()
                    .0 as i64
            };
            segments += 1;
            // The nearest local maximum of the denoised return at least 20 % of its maximum:
            // sharpening may change which of two nearly equal echoes is the highest.
            let top = raw.iter().copied().fold(0.0f32, f32::max);
            let at = argmax(y);
            let d = (1..raw.len() - 1)
                .filter(|&i| raw[i] >= raw[i - 1] && raw[i] > raw[i + 1] && raw[i] >= 0.2 * top)
                .map(|i| at - i as i64)
                .min_by_key(|d| d.abs())
                .unwrap_or(i64::MAX / 2);
            shifts.push(d);
            if d.abs() <= 2 {
                in_place += 1;
            }
            let peak_share = |x: &[f32]| {
                let s: f32 = x.iter().map(|v| v.max(0.0)).sum();
                x.iter().copied().fold(0.0f32, f32::max) / s.max(f32::MIN_POSITIVE)
            };
            if peak_share(y) > peak_share(raw) {
                sharper += 1;
            }
        }
    }
    shifts.sort_unstable();
    let hist: Vec<(i64, usize)> = (-4..=4)
        .map(|d| (d, shifts.iter().filter(|&&x| x == d).count()))
        .collect();
    println!(
        "shift histogram {hist:?}, beyond ±4: {}",
        shifts.iter().filter(|x| x.abs() > 4).count()
    );
    let median = shifts[shifts.len() / 2];
    println!(
        "NEON two-stage: {segments} return segments; highest sample within ±2 bins of a \
         local maximum of the denoised return: {in_place} ({:.1} %); median shift {median} bins; sharper: {sharper}",
        100.0 * in_place as f64 / segments as f64
    );
    assert!(segments >= 500);
    // Measured 2026-11-22: 450/508 (88.6 %) within ±2 bins, median 0, 30 beyond ±4, histogram
    // skewed to −1/−2. A single point target comes back exactly at its bin (the stage's
    // zero-phase unit test); in canopy the raw maximum of overlapping echoes lags, because
    // the tails of the earlier echoes (NEON's pulse has a long tail) pile up under the later
    // ones, and deconvolution removes the tails, so the sharpened maximum sits a bin or two
    // earlier. Beyond ±4: the highest deconvolved echo is one the raw record hides (below 20 %
    // of the maximum, or merged into a flank). A kernel off its peak would shift every
    // segment by its offset and move the median.
    assert!(
        (-1..=0).contains(&median),
        "returns moved in time: median {median}"
    );
    assert!(
        in_place as f64 >= 0.85 * segments as f64,
        "{in_place}/{segments} in place"
    );
    let far = shifts.iter().filter(|x| x.abs() > 4).count();
    assert!(
        far as f64 <= 0.1 * segments as f64,
        "{far}/{segments} beyond ±4 bins"
    );
    assert!(
        sharper as f64 >= 0.95 * segments as f64,
        "{sharper}/{segments} sharper"
    );
}
