//! Direct (time-domain) convolution and correlation on zero-padded buffers, shared by
//! Richardson-Lucy and Gold.
//!
//! Layout: a padded buffer `xp` holds the segment at `pad .. pad + n` with zeros on both sides
//! (`pad ≥ m`, the kernel length), so the sums of the kernel convention
//! (`(k ⊛ x)[i] = Σ_j taps[j] · x[i + center − j]`, see [`crate::signal::kernel`]) need no
//! boundary tests: every tap is one contiguous multiply-add over the outputs, which
//! the compiler vectorises without reassociating any sum. Outputs are processed in blocks of 64
//! kept in registers across all taps (one load and one multiply-add per tap and vector). On x86-64 CPUs with AVX2 and FMA the same loop is
//! compiled a second time for those features and chosen at run time (8-wide fused
//! multiply-adds instead of 4-wide SSE multiply then add).
//!
//! Cost: `2 · n · m` floating-point operations per convolution or correlation.

/// `out[i] = Σ_j taps[j] · xp[pad + i + center − j]` (convolution, `out.len()` outputs).
/// Requires `pad ≥ taps.len()`, `center < taps.len()` and `xp.len() ≥ pad + out.len() + pad`.
pub(crate) fn convolve_padded(
    xp: &[f32],
    pad: usize,
    taps: &[f32],
    center: usize,
    out: &mut [f32],
) {
    // Output i, tap j reads xp[pad + center − j + i].
    dispatch(xp, taps, out, pad + center, true);
}

/// `out[i] = Σ_j taps[j] · xp[pad + i − center + j]` (correlation, the adjoint of
/// [`convolve_padded`]). Same requirements.
pub(crate) fn correlate_padded(
    xp: &[f32],
    pad: usize,
    taps: &[f32],
    center: usize,
    out: &mut [f32],
) {
    dispatch(xp, taps, out, pad - center, false);
}

/// Tap `j` of output `i` reads `xp[base − j + i]` (`reverse`) or `xp[base + j + i]`.
fn dispatch(xp: &[f32], taps: &[f32], out: &mut [f32], base: usize, reverse: bool) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            unsafe { block_sum_avx2(xp, taps, out, base, reverse) };
            return;
        }
    }
    block_sum::<false>(xp, taps, out, base, reverse);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn block_sum_avx2(xp: &[f32], taps: &[f32], out: &mut [f32], base: usize, reverse: bool) {
    block_sum::<true>(xp, taps, out, base, reverse)
}

/// Outputs per register block (eight 8-lane vectors: enough independent accumulators to hide
/// the multiply-add latency on two FMA ports).
const BLOCK: usize = 64;

/// The sum over taps, `BLOCK` outputs at a time held in registers across all taps (one load
/// and one multiply-add per tap and vector, no stores until the block is done); `FMA` uses
/// fused multiply-adds (only where the CPU has them: elsewhere `mul_add` is a slow library
/// call).
#[inline(always)]
fn block_sum<const FMA: bool>(
    xp: &[f32],
    taps: &[f32],
    out: &mut [f32],
    base: usize,
    reverse: bool,
) {
    let offset = |j: usize| if reverse { base - j } else { base + j };
    let n = out.len();
    let full = n / BLOCK * BLOCK;
    for (b, chunk) in out[..full].chunks_exact_mut(BLOCK).enumerate() {
        let i0 = b * BLOCK;
        let mut acc = [0.0f32; BLOCK];
        for (j, &t) in taps.iter().enumerate() {
            let o = offset(j) + i0;
            let s: &[f32; BLOCK] = xp[o..o + BLOCK].try_into().expect("block length");
            for (a, &v) in acc.iter_mut().zip(s) {
                *a = if FMA { t.mul_add(v, *a) } else { *a + t * v };
            }
        }
        chunk.copy_from_slice(&acc);
    }
    let tail = &mut out[full..];
    tail.fill(0.0);
    let m = tail.len();
    for (j, &t) in taps.iter().enumerate() {
        let o = offset(j) + full;
        for (a, &v) in tail.iter_mut().zip(&xp[o..o + m]) {
            *a = if FMA { t.mul_add(v, *a) } else { *a + t * v };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signal::kernel::{Kernel, convolve_same, correlate_same};

    #[test]
    fn deconvolve_direct_matches_the_reference_convolution() {
        let mut k = Kernel::default();
        k.set_from_taps(&[0.5, 2.0, -0.3, 0.8, 0.1, 0.2, 0.3], 2, 8)
            .unwrap();
        for n in [23usize, 150] {
            let x: Vec<f32> = (0..n).map(|i| ((i * 7) % 5) as f32 - 1.0).collect();
            let pad = k.len();
            let mut xp = vec![0.0; n + 2 * pad];
            xp[pad..pad + n].copy_from_slice(&x);
            let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
            convolve_padded(&xp, pad, &k.taps, k.center, &mut a);
            convolve_same(&x, &k, &mut b);
            for (p, q) in a.iter().zip(&b) {
                assert!((p - q).abs() < 1e-5);
            }
            correlate_padded(&xp, pad, &k.taps, k.center, &mut a);
            correlate_same(&x, &k, &mut b);
            for (p, q) in a.iter().zip(&b) {
                assert!((p - q).abs() < 1e-5);
            }
        }
    }
}
