//! Direct (time-domain) convolution and correlation on zero-padded buffers, shared by
//! Richardson-Lucy and Gold.
//!
//! Layout: a padded buffer `xp` holds the segment at `pad .. pad + n` with zeros on both sides
//! (`pad ≥ m`, the kernel length), so the sums of the kernel convention
//! (`(k ⊛ x)[i] = Σ_j taps[j] · x[i + center − j]`, see [`crate::signal::kernel`]) need no
//! boundary tests: every tap is one contiguous multiply-add over `n` outputs (an "axpy"), which
//! the compiler vectorises without reassociating any sum. Taps are processed four at a time to
//! cut loads and stores per multiply-add. On x86-64 CPUs with AVX2 and FMA the same loop is
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
    let m = taps.len();
    debug_assert!(pad >= m && center < m.max(1));
    dispatch(xp, taps, out, |j| pad + center - j);
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
    let m = taps.len();
    debug_assert!(pad >= m && center < m.max(1));
    dispatch(xp, taps, out, |j| pad - center + j);
}

fn dispatch(xp: &[f32], taps: &[f32], out: &mut [f32], offset: impl Fn(usize) -> usize) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            unsafe { axpy_sum_avx2(xp, taps, out, &offset) };
            return;
        }
    }
    axpy_sum::<false>(xp, taps, out, &offset);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn axpy_sum_avx2(xp: &[f32], taps: &[f32], out: &mut [f32], offset: &dyn Fn(usize) -> usize) {
    axpy_sum::<true>(xp, taps, out, offset)
}

/// `out[i] = Σ_j taps[j] · xp[offset(j) + i]`; `FMA` uses fused multiply-adds (only where the
/// CPU has them: elsewhere `mul_add` is a slow library call).
#[inline(always)]
fn axpy_sum<const FMA: bool>(
    xp: &[f32],
    taps: &[f32],
    out: &mut [f32],
    offset: &dyn Fn(usize) -> usize,
) {
    let n = out.len();
    out.fill(0.0);
    let mut j = 0;
    while j + 4 <= taps.len() {
        let (t0, t1, t2, t3) = (taps[j], taps[j + 1], taps[j + 2], taps[j + 3]);
        let s0 = &xp[offset(j)..][..n];
        let s1 = &xp[offset(j + 1)..][..n];
        let s2 = &xp[offset(j + 2)..][..n];
        let s3 = &xp[offset(j + 3)..][..n];
        for ((((o, &a), &b), &c), &d) in out.iter_mut().zip(s0).zip(s1).zip(s2).zip(s3) {
            if FMA {
                *o = t3.mul_add(d, t2.mul_add(c, t1.mul_add(b, t0.mul_add(a, *o))));
            } else {
                *o += (t0 * a + t1 * b) + (t2 * c + t3 * d);
            }
        }
        j += 4;
    }
    while j < taps.len() {
        let t = taps[j];
        let s = &xp[offset(j)..][..n];
        for (o, &a) in out.iter_mut().zip(s) {
            if FMA {
                *o = t.mul_add(a, *o);
            } else {
                *o += t * a;
            }
        }
        j += 1;
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
        let n = 23;
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
