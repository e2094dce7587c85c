"""What a scientist would otherwise run for fwlidar's signal chain, on the same waveforms.

Run by benches/compare/run.sh after the criterion benchmarks, which wrote the exact inputs they
time to $FWLIDAR_BENCH_WAVEFORMS (see benches/common/waveforms.rs). This script reads those
files (printing the same FNV-1a 64 checksums as the benchmarks, so both sides provably time the
same bytes), times the Python equivalents with timeit (repeat, median of the per-call times),
reads the criterion medians from target/criterion/.../new/estimates.json and prints a markdown
table with the ratios.

Python side, per waveform (everything that does not depend on the waveform is built once,
outside the timing, which favours Python):

- Denoise (CAO-like pulse: 64-sample outgoing + 256-sample return of u16 counts, 1 ns):
  counts -> volts, baseline = median of the first 8 samples, level shift (baseline subtracted
  before the FFT), zero-padding to twice the length, numpy.fft.rfft, bins above 0.2 GHz zeroed,
  irfft, noise level = mean |raw - baseline - smoothed|; per segment, both segments per pulse.
  The same steps as fwlidar's stage (which, on segments this long, also takes the baseline as
  the median of the first 8 samples). Also with scipy.fft.
- Richardson-Lucy 20 iterations: skimage.restoration.richardson_lucy(y, taps, num_iter=20,
  clip=False) on the same segment clipped at 0 (float32 in, so it computes in float32 like
  fwlidar; filter_epsilon=None, skimage's default). skimage starts from a flat 0.5 estimate,
  fwlidar from the data; the work per iteration (two convolutions of the segment with the
  43-tap kernel, one division, one multiplication) is the same.
- The on-board setting (RL 12 from the Wiener start to a 4 ns target, output noise floor;
  `RlConfig::onboard`, config/onboard.toml) against the same skimage RL 20 it replaces:
  skimage's RL has no way to start from a given estimate, so RL 20 is what a user would run.
- Wiener fused with the 0.2 GHz low-pass: numpy.fft, fwlidar's formula (pad to a 2-3-5 length
  >= n + m, kernel centred at index 0, segment scaled to unit peak, Tikhonov floor 1e-3),
  kernel spectrum computed per call (compared with fwlidar's per-shot-kernel benchmark).
- NNLS: scipy.optimize.nnls on the dense 256 x 256 "same" convolution matrix of the kernel,
  built once outside the timing. scipy solves to its own optimality tolerance; fwlidar stops at
  its KKT tolerance (1e-4 of max|R^T y|) or its iteration cap (50), see docs/performance.md.
- Decomposition of the 3-echo waveform: scipy.optimize.curve_fit of a sum of 3 Gaussians from
  hand-given starting values near the answer (no peak detection timed: generous to scipy;
  fwlidar's time includes detection, the fit and one residual-refinement pass).
"""
import argparse
import json
import os
import sys
import timeit

import numpy as np
import scipy
import scipy.fft
import scipy.optimize
import skimage
from skimage.restoration import richardson_lucy


def fnv1a64(b):
    h = 0xCBF29CE484222325
    for x in b:
        h ^= x
        h = (h * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def load(d, name, dtype):
    raw = open(os.path.join(d, name), "rb").read()
    print(f"waveform {name}: {len(raw)} bytes, fnv1a64 {fnv1a64(raw):016x}")
    return np.frombuffer(raw, dtype=dtype).copy()


def median_us(f, repeat=15, budget_s=0.25):
    f()
    t = timeit.timeit(f, number=3) / 3
    number = max(1, int(budget_s / max(t, 1e-7)))
    runs = timeit.repeat(f, number=number, repeat=repeat)
    per = sorted(r / number for r in runs)
    return per[len(per) // 2] * 1e6


def criterion_median_us(target, bench_id):
    path = os.path.join(target, "criterion", bench_id, "new", "estimates.json")
    with open(path) as f:
        return json.load(f)["median"]["point_estimate"] / 1e3


# ---------------------------------------------------------------------------------- denoise
def make_denoise(fft, gain=0.004, offset=0.0, dt_ns=1.0, cutoff_ghz=0.2, pretrigger=8):
    def denoise_segment(counts):
        v = offset + gain * counts.astype(np.float32)
        base = np.median(v[:pretrigger])
        x = v - base
        n = 2 * len(x)
        spec = fft.rfft(x, n)
        spec[int(np.floor(cutoff_ghz * n * dt_ns)) + 1:] = 0.0
        smooth = fft.irfft(spec, n)[: len(x)]
        noise = np.mean(np.abs(x - smooth))
        return smooth, base, noise

    return lambda pulse: [denoise_segment(s) for s in pulse]


# ---------------------------------------------------------------------------------- wiener
def fast_len(n):
    n = max(n, 2)
    while True:
        if n % 2 == 0:
            r = n
            for p in (2, 3, 5):
                while r % p == 0:
                    r //= p
            if r == 1:
                return n
        n += 1


def make_wiener(center, noise_v=0.002, cutoff_ghz=0.2, dt=1.0, rho=1e-3):
    def wiener(y, taps):
        n, m = len(y), len(taps)
        length = fast_len(n + m)
        scale = np.max(np.abs(y))
        k = np.zeros(length, dtype=np.float32)
        k[(np.arange(m) - center) % length] = taps
        p = np.fft.rfft(y / scale, length)
        r = np.fft.rfft(k)
        p2 = p.real ** 2 + p.imag ** 2
        r2 = r.real ** 2 + r.imag ** 2
        n2 = n * (noise_v / scale) ** 2
        s = p * np.conj(r) * p2 / (p2 * (r2 + rho) + n2 * np.maximum(r2, rho))
        s[int(np.floor(cutoff_ghz * length * dt)) + 1:] = 0.0
        return np.fft.irfft(s, length)[:n] * scale

    return wiener


# ---------------------------------------------------------------------------------- nnls
def conv_matrix(taps, center, n):
    """The "same" convolution matrix: (K x)[i] = sum_j taps[j] x[i + center - j]."""
    a = np.zeros((n, n))
    for i in range(n):
        for j, t in enumerate(taps):
            src = i + center - j
            if 0 <= src < n:
                a[i, src] = t
    return a


# ---------------------------------------------------------------------------------- decompose
def gauss3(t, a1, m1, s1, a2, m2, s2, a3, m3, s3):
    return (a1 * np.exp(-0.5 * ((t - m1) / s1) ** 2)
            + a2 * np.exp(-0.5 * ((t - m2) / s2) ** 2)
            + a3 * np.exp(-0.5 * ((t - m3) / s3) ** 2))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--waveforms", required=True)
    ap.add_argument("--target", default="target")
    args = ap.parse_args()
    d = args.waveforms

    print(f"versions: python {sys.version.split()[0]}, numpy {np.__version__}, "
          f"scipy {scipy.__version__}, scikit-image {skimage.__version__}")
    rows = []  # (stage, fwlidar bench id, fwlidar label, python label, python us)

    # Denoise.
    pulse = [load(d, "denoise_outgoing_u16", "<u2"), load(d, "denoise_return_u16", "<u2")]
    for name, fft in (("numpy.fft rfft low-pass", np.fft), ("scipy.fft rfft low-pass", scipy.fft)):
        f = make_denoise(fft)
        rows.append(("denoise (64 + 256 samples)", "denoise_outgoing64_return256_1ns",
                     "`denoise` stage", name, median_us(lambda: f(pulse))))

    # Richardson-Lucy and Wiener.
    y = load(d, "deconvolve_segment_f32", "<f4")
    taps = load(d, "deconvolve_kernel_f32", "<f4")
    taps2 = load(d, "deconvolve_kernel2_f32", "<f4")
    assert len(taps) % 2 == 1 and len(taps2) % 2 == 1
    yp = np.clip(y, 0, None).astype(np.float32)
    rl = lambda: richardson_lucy(yp, taps, num_iter=20, clip=False)
    assert rl().dtype == np.float32
    rows.append((f"Richardson-Lucy 20 it ({len(taps)} taps)",
                 "deconvolve_256_samples_41_taps/richardson_lucy_20", "`RichardsonLucy`",
                 "skimage `richardson_lucy`", median_us(rl)))
    # The on-board setting replaces RL 20: against it, what a user would otherwise run is the
    # same skimage call (skimage's RL cannot start from a given estimate).
    rows.append((f"on-board: RL 12 from the Wiener start ({len(taps)} taps)",
                 "deconvolve_256_samples_41_taps/richardson_lucy_12_wiener_start_onboard",
                 "`RichardsonLucy` (`RlConfig::onboard`)",
                 "skimage `richardson_lucy`, 20 it", median_us(rl)))
    wiener = make_wiener(len(taps) // 2)
    flip = [False]

    def wiener_per_shot():
        flip[0] = not flip[0]
        return wiener(y, taps if flip[0] else taps2)

    rows.append(("Wiener + low-pass, per-shot kernel",
                 "deconvolve_256_samples_41_taps/wiener_fused_per_shot_kernel", "`Wiener`",
                 "numpy.fft Wiener", median_us(wiener_per_shot)))

    # NNLS.
    ktaps = load(d, "nnls_kernel_f32", "<f4").astype(np.float64)
    a = conv_matrix(ktaps, len(ktaps) // 2, 256)
    for file, bench, label in (
        ("nnls_noisy_f32", "nnls_return256_gauss16ns_noisy", "two surfaces, noisy"),
        ("nnls_clean_f32", "nnls_return256_gauss16ns_clean", "two surfaces, clean"),
        ("nnls_full_budget_f32", "nnls_return256_gauss16ns_noisy_full_budget",
         "rough noise, no early stop"),
        ("nnls_dense_canopy_f32", "nnls_return256_gauss16ns_dense_canopy_cap",
         "dense canopy, no early stop"),
    ):
        yv = load(d, file, "<f4").astype(np.float64)
        rows.append((f"NNLS, {label}", bench, "`Nnls`", "scipy `nnls`, dense matrix",
                     median_us(lambda: scipy.optimize.nnls(a, yv), repeat=7)))

    # NNLS, `fwlidar process`'s setting (noise-weighted refit, clipped samples left out) against
    # scipy's NNLS run as a user would: the whole row, to convergence.
    ktaps = load(d, "nnls_process_kernel_f32", "<f4").astype(np.float64)
    a = conv_matrix(ktaps, len(ktaps) // 2, 256)
    for file, bench, label in (
        ("nnls_process_white_f32", "nnls_process_8ns_white", "white noise"),
        ("nnls_process_shot_f32", "nnls_process_8ns_shot", "shot noise (refit)"),
        ("nnls_process_clipped_f32", "nnls_process_8ns_clipped", "clipped top"),
    ):
        yv = load(d, file, "<f4").astype(np.float64)
        rows.append((f"NNLS as `process` runs it, 8 ns, {label}", bench,
                     "`Nnls` (budget 128, noise weights)", "scipy `nnls`, dense matrix",
                     median_us(lambda: scipy.optimize.nnls(a, yv), repeat=7)))

    # Decomposition.
    y3 = load(d, "decompose_3_echoes_f32", "<f4").astype(np.float64)
    t = np.arange(len(y3), dtype=np.float64)
    p0 = [y3[60], 60.0, 4.0, y3[128], 128.0, 4.0, y3[138], 138.0, 4.0]
    popt, _ = scipy.optimize.curve_fit(gauss3, t, y3, p0=p0)
    print("curve_fit result (A, mu, sigma):",
          ", ".join(f"({popt[i]:.2f}, {popt[i + 1]:.2f}, {popt[i + 2]:.2f})" for i in (0, 3, 6)))
    rows.append(("decomposition, 3 echoes", "decompose_3_echoes_256", "`Decomposer::fit`",
                 "scipy `curve_fit`, 3 Gaussians", median_us(
                     lambda: scipy.optimize.curve_fit(gauss3, t, y3, p0=p0), repeat=9)))

    print()
    print("| stage | fwlidar | median | Python | median | fwlidar faster by |")
    print("|---|---|---:|---|---:|---:|")
    for stage, bench, ours, theirs, py_us in rows:
        try:
            rs_us = criterion_median_us(args.target, bench)
        except FileNotFoundError:
            rs_us = float("nan")
        print(f"| {stage} | {ours} | {rs_us:.2f} us | {theirs} | {py_us:.1f} us | "
              f"{py_us / rs_us:.0f}x |")


if __name__ == "__main__":
    main()
