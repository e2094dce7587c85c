//! The dot products of the metrics' Gaussian smoothing (step 1): every sample of the smoothed
//! waveform is the padded waveform's window times the kernel, summed as four partial sums over
//! the kernel's whole groups of four taps, added pairwise, then the kernel's last taps one by
//! one.
//!
//! Several outputs are summed side by side (independent additions hide each other's latency),
//! eight at a time with AVX where the CPU has it (one 4-lane vector per output's partial sums),
//! four otherwise. Each output's sum is the same sequence of `f64` multiplications and
//! additions (never fused) whatever the block or the instruction set, so the result is the
//! same bit for bit.

/// `out` = the `n` smoothed samples of `padded` (the waveform with the kernel's half length
/// of edge samples on each side, `n + k.len() − 1` long) with the kernel `k`.
pub(super) fn smooth_padded(padded: &[f64], k: &[f64], n: usize, out: &mut Vec<f64>) {
    assert!(!k.is_empty() && padded.len() + 1 >= n + k.len());
    out.clear();
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the CPU supports the feature the function is compiled for.
            unsafe { smooth_avx(padded, k, n, out) };
            return;
        }
    }
    smooth_blocks::<4>(padded, k, n, out);
}

/// [`smooth_blocks`] of eight outputs compiled for AVX (multiplications and additions only:
/// no fused multiply-add).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn smooth_avx(padded: &[f64], k: &[f64], n: usize, out: &mut Vec<f64>) {
    smooth_blocks::<8>(padded, k, n, out);
}

/// The outputs `B` at a time, then the rest one by one.
#[inline(always)]
fn smooth_blocks<const B: usize>(padded: &[f64], k: &[f64], n: usize, out: &mut Vec<f64>) {
    let mut i = 0;
    while i + B <= n {
        out.extend_from_slice(&block::<B>(&padded[i..i + B - 1 + k.len()], k));
        i += B;
    }
    for i in i..n {
        out.push(block::<1>(&padded[i..i + k.len()], k)[0]);
    }
}

/// `B` consecutive outputs: output `o` is the sum over the window starting at `window[o]`
/// (`window` is `k.len() + B − 1` long).
#[inline(always)]
fn block<const B: usize>(window: &[f64], k: &[f64]) -> [f64; B] {
    let whole = k.len() / 4 * 4;
    let window = &window[..k.len() + B - 1];
    let mut lanes = [[0.0f64; 4]; B];
    for c in (0..whole).step_by(4) {
        let kc: &[f64; 4] = k[c..c + 4].try_into().expect("four taps");
        for (o, lane) in lanes.iter_mut().enumerate() {
            let a: &[f64; 4] = window[o + c..o + c + 4].try_into().expect("four samples");
            for l in 0..4 {
                lane[l] += a[l] * kc[l];
            }
        }
    }
    let mut out = [0.0f64; B];
    for (o, lane) in lanes.iter().enumerate() {
        let mut acc = (lane[0] + lane[1]) + (lane[2] + lane[3]);
        for t in whole..k.len() {
            acc += window[o + t] * k[t];
        }
        out[o] = acc;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blocks of any size and the AVX tier give each output's sum bit for bit.
    #[test]
    fn every_block_size_sums_alike() {
        for taps in [1usize, 3, 4, 7, 29, 53] {
            let k: Vec<f64> = (0..taps).map(|i| 1.0 / (1.0 + i as f64 * 0.37)).collect();
            let n = 37;
            let padded: Vec<f64> = (0..n + taps - 1)
                .map(|i| (i as f64 * 0.731).sin() * 100.0 + 3.0)
                .collect();
            let one: Vec<f64> = (0..n)
                .map(|i| block::<1>(&padded[i..i + taps], &k)[0])
                .collect();
            let mut four = Vec::new();
            smooth_blocks::<4>(&padded, &k, n, &mut four);
            let mut eight = Vec::new();
            smooth_blocks::<8>(&padded, &k, n, &mut eight);
            let mut chosen = Vec::new();
            smooth_padded(&padded, &k, n, &mut chosen);
            for v in [&four, &eight, &chosen] {
                let bits: Vec<u64> = v.iter().map(|x| x.to_bits()).collect();
                let want: Vec<u64> = one.iter().map(|x| x.to_bits()).collect();
                assert_eq!(bits, want, "{taps} taps");
            }
        }
    }
}
