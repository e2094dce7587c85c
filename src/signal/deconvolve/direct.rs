//! Direct (time-domain) convolution and correlation on zero-padded buffers, shared by
//! Richardson-Lucy and Gold.
//!
//! Layout: a padded buffer `xp` holds the segment at `pad .. pad + n` with zeros on both sides
//! (`pad ≥ m`, the kernel length), so the sums of the kernel convention
//! (`(k ⊛ x)[i] = Σ_j taps[j] · x[i + center − j]`, see [`crate::signal::kernel`]) need no
//! boundary tests: every tap is one contiguous multiply-add over the outputs, which
//! the compiler vectorises without reassociating any sum. Outputs are processed in blocks of 64
//! kept in registers across all taps (one load and one multiply-add per tap and vector). On
//! x86-64 CPUs with AVX-512F the same loop is compiled for 16-lane registers (blocks of 128,
//! then 64, the last outputs in masked registers) and chosen at run time; with AVX2 and FMA
//! (and no AVX-512) it is compiled for 8-lane registers (blocks of 64, then 8). Every tier
//! performs, per output, the same fused multiply-adds in the same order, so their results are
//! bit-identical. Without either, the
//! portable build multiplies then adds (4-wide SSE).
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
    let n = out.len();
    dispatch(xp, taps, n, pad + center, true, Store(out));
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
    let n = out.len();
    dispatch(xp, taps, n, pad - center, false, Store(out));
}

/// What is done with each block of finished sums (`acc[r]` is output `i0 + r`) while it is
/// still in registers: stored as is, or turned into the next quantity of an iteration (so
/// that quantity needs no separate pass over memory).
pub(crate) trait Epilogue {
    /// Consumes the sums of outputs `i0 .. i0 + acc.len()`.
    fn store(&mut self, i0: usize, acc: &[f32]);
}

/// Stores the sums.
struct Store<'a>(&'a mut [f32]);

impl Epilogue for Store<'_> {
    #[inline(always)]
    fn store(&mut self, i0: usize, acc: &[f32]) {
        self.0[i0..i0 + acc.len()].copy_from_slice(acc);
    }
}

/// `k ⊛ xp` (as [`convolve_padded`], `n` outputs) handed block by block to `epilogue`.
pub(crate) fn convolve_padded_with(
    xp: &[f32],
    pad: usize,
    taps: &[f32],
    center: usize,
    n: usize,
    epilogue: impl Epilogue,
) {
    dispatch(xp, taps, n, pad + center, true, epilogue);
}

/// `k ⋆ xp` (as [`correlate_padded`], `n` outputs) handed block by block to `epilogue`.
pub(crate) fn correlate_padded_with(
    xp: &[f32],
    pad: usize,
    taps: &[f32],
    center: usize,
    n: usize,
    epilogue: impl Epilogue,
) {
    dispatch(xp, taps, n, pad - center, false, epilogue);
}

/// Tap `j` of output `i` reads `xp[base − j + i]` (`reverse`) or `xp[base + j + i]`.
///
/// Every tier computes each output as the same sequence of operations (taps in order, one
/// multiply-add each, fused wherever FMA is available), so the AVX-512 and AVX2 tiers give
/// bit-identical results; only the number of outputs per instruction differs.
#[inline(always)]
fn dispatch<E: Epilogue>(
    xp: &[f32],
    taps: &[f32],
    n: usize,
    base: usize,
    reverse: bool,
    mut epilogue: E,
) {
    assert!(
        xp.len()
            >= base
                + n
                + if reverse {
                    0
                } else {
                    taps.len().saturating_sub(1)
                }
    );
    assert!(!reverse || base + 1 >= taps.len());
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") && !force_avx2() {
            // SAFETY: the CPU supports the features the function is compiled for.
            unsafe { block_sum_avx512(xp, taps, n, base, reverse, &mut epilogue) };
            return;
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            unsafe { block_sum_avx2(xp, taps, n, base, reverse, &mut epilogue) };
            return;
        }
    }
    let done = blocks::<false, BLOCK, E>(xp, taps, n, base, reverse, 0, &mut epilogue);
    tail::<false, E>(xp, taps, n, base, reverse, done, &mut epilogue);
}

/// Test hook: with `FORCE_AVX2` set, the AVX-512 tier is skipped (to check that both tiers
/// agree bit for bit on a CPU that has both).
#[cfg(all(test, target_arch = "x86_64"))]
fn force_avx2() -> bool {
    FORCE_AVX2.with(|f| f.get())
}

#[cfg(all(not(test), target_arch = "x86_64"))]
#[inline(always)]
fn force_avx2() -> bool {
    false
}

#[cfg(all(test, target_arch = "x86_64"))]
thread_local! {
    static FORCE_AVX2: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn block_sum_avx2<E: Epilogue>(
    xp: &[f32],
    taps: &[f32],
    n: usize,
    base: usize,
    reverse: bool,
    epilogue: &mut E,
) {
    let done = blocks::<true, BLOCK, E>(xp, taps, n, base, reverse, 0, epilogue);
    let done = blocks::<true, 8, E>(xp, taps, n, base, reverse, done, epilogue);
    tail::<true, E>(xp, taps, n, base, reverse, done, epilogue);
}

/// AVX-512: 16-lane fused multiply-adds. Blocks of 128 outputs (eight 16-lane accumulators,
/// enough to hide the latency on two FMA ports), then of 64, then the rest in four masked
/// registers ([`tail_avx512`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn block_sum_avx512<E: Epilogue>(
    xp: &[f32],
    taps: &[f32],
    n: usize,
    base: usize,
    reverse: bool,
    epilogue: &mut E,
) {
    let done = blocks::<true, BLOCK_512, E>(xp, taps, n, base, reverse, 0, epilogue);
    let done = blocks::<true, BLOCK, E>(xp, taps, n, base, reverse, done, epilogue);
    tail_avx512(xp, taps, n, base, reverse, done, epilogue);
}

/// The last fewer than [`BLOCK`] (64) outputs of the AVX-512 tier in four 16-lane registers at
/// once: per tap and register one masked load (lanes past `n` are neither read nor used) and
/// one fused multiply-add, the same operations per output as [`tail`], so the results are
/// bit-identical to it. Four independent accumulators hide the multiply-add latency; a short
/// echo window (tens of samples) otherwise spends most of its time in a scalar or one-register
/// loop.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn tail_avx512<E: Epilogue>(
    xp: &[f32],
    taps: &[f32],
    n: usize,
    base: usize,
    reverse: bool,
    start: usize,
    epilogue: &mut E,
) {
    use std::arch::x86_64::{
        __m512, _mm512_fmadd_ps, _mm512_maskz_loadu_ps, _mm512_set1_ps, _mm512_setzero_ps,
        _mm512_storeu_ps,
    };
    let m = n - start;
    if m == 0 {
        return;
    }
    assert!(m < BLOCK);
    // Lanes of each register that hold an output: all 16 up to the last, which holds the rest.
    let mask = |r: usize| -> u16 {
        let lanes = m.saturating_sub(16 * r).min(16);
        ((1u32 << lanes) - 1) as u16
    };
    let masks = [mask(0), mask(1), mask(2), mask(3)];
    let mut acc: [__m512; 4] = [_mm512_setzero_ps(); 4];
    for (j, &t) in taps.iter().enumerate() {
        let o = if reverse { base - j } else { base + j } + start;
        // The inputs of this tap: `m` floats, all inside `xp` (as `tail`'s slice).
        let s = &xp[o..o + m];
        let tv = _mm512_set1_ps(t);
        for (r, a) in acc.iter_mut().enumerate() {
            // SAFETY: the mask selects lanes 16·r .. 16·r + lanes, all inside `s`; masked-out
            // lanes are not accessed (a register with no lane loads nothing).
            let v = unsafe { _mm512_maskz_loadu_ps(masks[r], s.as_ptr().wrapping_add(16 * r)) };
            *a = _mm512_fmadd_ps(tv, v, *a);
        }
    }
    let mut buf = [0.0f32; BLOCK];
    for (r, a) in acc.iter().enumerate() {
        // SAFETY: `buf` holds 64 floats, register r goes to 16·r .. 16·r + 16.
        unsafe { _mm512_storeu_ps(buf.as_mut_ptr().add(16 * r), *a) };
    }
    epilogue.store(start, &buf[..m]);
}

/// Outputs per register block (eight 8-lane vectors: enough independent accumulators to hide
/// the multiply-add latency on two FMA ports).
const BLOCK: usize = 64;

/// Outputs per register block of the AVX-512 tier (eight 16-lane vectors).
#[cfg(target_arch = "x86_64")]
const BLOCK_512: usize = 128;

/// The sum over taps for outputs `start .. n`, `B` outputs at a time held in registers across
/// all taps (one load and one multiply-add per tap and vector, no stores until the block is
/// done); `FMA` uses fused multiply-adds (only where the CPU has them: elsewhere `mul_add` is a
/// slow library call). Returns the end of the last full block.
#[inline(always)]
fn blocks<const FMA: bool, const B: usize, E: Epilogue>(
    xp: &[f32],
    taps: &[f32],
    n: usize,
    base: usize,
    reverse: bool,
    start: usize,
    epilogue: &mut E,
) -> usize {
    let offset = |j: usize| if reverse { base - j } else { base + j };
    let full = (n - start) / B * B;
    let mut i0 = start;
    while i0 < start + full {
        let mut acc = [0.0f32; B];
        for (j, &t) in taps.iter().enumerate() {
            let o = offset(j) + i0;
            let s: &[f32; B] = xp[o..o + B].try_into().expect("block length");
            for (a, &v) in acc.iter_mut().zip(s) {
                *a = if FMA { t.mul_add(v, *a) } else { *a + t * v };
            }
        }
        epilogue.store(i0, &acc);
        i0 += B;
    }
    i0
}

/// The outputs from `start` to `n` (fewer than [`BLOCK`]), one tap at a time over all of them.
#[inline(always)]
fn tail<const FMA: bool, E: Epilogue>(
    xp: &[f32],
    taps: &[f32],
    n: usize,
    base: usize,
    reverse: bool,
    start: usize,
    epilogue: &mut E,
) {
    let offset = |j: usize| if reverse { base - j } else { base + j };
    let m = n - start;
    if m == 0 {
        return;
    }
    let mut buf = [0.0f32; BLOCK];
    let acc = &mut buf[..m];
    for (j, &t) in taps.iter().enumerate() {
        let o = offset(j) + start;
        for (a, &v) in acc.iter_mut().zip(&xp[o..o + m]) {
            *a = if FMA { t.mul_add(v, *a) } else { *a + t * v };
        }
    }
    epilogue.store(start, acc);
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

    /// The AVX-512 and AVX2 tiers agree bit for bit (same operations per output), for every
    /// segment length around the block sizes.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn deconvolve_direct_tiers_agree_bit_for_bit() {
        let taps: Vec<f32> = (0..41)
            .map(|j| (-0.5 * ((j as f32 - 20.0) / 6.8).powi(2)).exp() * 0.06)
            .collect();
        for n in [
            1usize, 5, 15, 16, 17, 31, 32, 33, 40, 47, 48, 49, 63, 64, 65, 100, 127, 128, 129, 150,
            191, 200, 256, 300, 1000,
        ] {
            let pad = taps.len();
            let mut xp = vec![0.0f32; n + 2 * pad];
            for (i, v) in xp[pad..pad + n].iter_mut().enumerate() {
                *v = ((i * 7919 % 101) as f32 / 37.0).sin().abs() + 1e-3;
            }
            for conv in [true, false] {
                let run = |avx2: bool| {
                    FORCE_AVX2.with(|f| f.set(avx2));
                    let mut o = vec![0.0f32; n];
                    if conv {
                        convolve_padded(&xp, pad, &taps, 17, &mut o);
                    } else {
                        correlate_padded(&xp, pad, &taps, 17, &mut o);
                    }
                    FORCE_AVX2.with(|f| f.set(false));
                    o
                };
                let (a, b) = (run(false), run(true));
                for (p, q) in a.iter().zip(&b) {
                    assert_eq!(p.to_bits(), q.to_bits(), "n = {n}, conv = {conv}");
                }
            }
        }
    }
}
