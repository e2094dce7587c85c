#!/usr/bin/env python3
"""Why fwlidar's Richardson-Lucy 200 differs from scikit-image's on the same input (issue 19).

A numpy re-implementation of RL with every difference between the two as a switch, run on the
close-pair set of ``tests/python/close_pairs.py`` (same generator, same seed, same scores), one
factor switched at a time from each side:

- ``start``: scikit-image starts from a flat 0.5; fwlidar from the data / max(data) + 1e-3
  (in data units: ``y + 1e-3 · max(y)``).
- ``clip``: scikit-image clips the estimate to [-1, 1] after every iteration (``clip=True``);
  fwlidar caps it at 1e9 · max(y) and flushes values below 1e-30 · max(y).
- ``floor``: scikit-image divides by ``k ⊛ σ + 1e-12``; fwlidar by ``max(k ⊛ σ, 1e-6 · max(y))``
  and sets the ratio to 0 where y = 0.
- ``float32``: scikit-image follows the input (float64 here); fwlidar computes in float32.
- ``lowpass``: fwlidar's denoise (0.2 GHz low-pass) before RL (its rows come from
  ``fwlidar process --method none``); scikit-image gets the baseline-removed rows only.
- ``negatives``: both clip negative data to 0 here (scikit-image run on raw negatives
  oscillates to ±1: reported as its own row).
- ``filter_epsilon``: scikit-image's option (ratio 0 where ``k ⊛ σ`` is below it), off in both.
- edges: both treat samples outside the segment as zero (scikit-image's ``mode='same'``
  convolution, fwlidar's padded convolution), so there is no switch; the "fwlidar" variant is
  checked against ``fwlidar process`` on the same rows.

Usage: ``rl_factors.py --fwlidar target/release/fwlidar --workdir DIR``; prints a markdown table.
"""

import argparse
import os
import subprocess
import sys

import numpy as np
from scipy.signal import fftconvolve

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "tests", "python"))
import close_pairs as cp  # noqa: E402

SKIMAGE = dict(start="flat", clip=True, floor="eps", dtype=np.float64, lowpass=False, fe=None)
FWLIDAR = dict(start="data", clip=False, floor="fw", dtype=np.float32, lowpass=True, fe=None)


def rl(y, taps, iterations, start, clip, floor, dtype, fe):
    y = y.astype(dtype)
    k = taps.astype(dtype)[None, :]
    km = np.flip(k)
    peak = y.max(axis=1, keepdims=True)
    if start == "flat":
        x = np.full(y.shape, 0.5, dtype=dtype)
    else:
        x = (y + dtype(1e-3) * peak).astype(dtype)
    for _ in range(iterations):
        conv = fftconvolve(x, k, mode="same", axes=1).astype(dtype)
        if floor == "eps":
            conv = conv + dtype(1e-12)
            ratio = y / conv
        else:
            ratio = np.where(y > 0, y / np.maximum(conv, dtype(1e-6) * peak), 0).astype(dtype)
        if fe:
            ratio = np.where(conv < fe, 0, ratio).astype(dtype)
        x = (x * fftconvolve(ratio, km, mode="same", axes=1)).astype(dtype)
        if clip:
            x = np.clip(x, -1, 1)
        else:
            x = np.minimum(np.maximum(x, 0), dtype(1e9) * peak)
            x = np.where(x < dtype(1e-30) * peak, 0, x).astype(dtype)
    return x.astype(np.float64)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--fwlidar", required=True)
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--waveforms", type=int, default=500)
    ap.add_argument("--iterations", type=int, default=200)
    a = ap.parse_args()
    os.makedirs(a.workdir, exist_ok=True)
    received, truth, surfaces, pairs, singles = cp.make_set(a.waveforms, 225, 19)
    raw_rmse = float(np.sqrt(np.mean((received - truth) ** 2)))
    taps, _ = cp.gaussian_taps(cp.SYSTEM_FWHM_NS)
    inp = os.path.join(a.workdir, "waveforms.npy")
    kern = os.path.join(a.workdir, "kernel.npy")
    np.save(inp, received.astype(np.float32))
    z = np.zeros(cp.KERNEL_ZEROS)
    np.save(kern, np.concatenate([z, taps, z]).astype(np.float32)[None, :])

    def process(args, data=inp):
        out = os.path.join(a.workdir, "out.npy")
        subprocess.run(
            [a.fwlidar, "process", "--input", data, "--kernel", kern, "--out", out, "--no-progress"]
            + args,
            check=True,
            capture_output=True,
        )
        return np.load(out).astype(np.float64)

    clipped = cp.baseline_removed(received)
    denoised = process(["--method", "none"])
    score = lambda out: cp.score(out, truth, raw_rmse, pairs, singles, surfaces)  # noqa: E731

    def variant(cfg):
        data = denoised if cfg["lowpass"] else clipped
        data = np.maximum(data, 0)
        return rl(data, taps, a.iterations, cfg["start"], cfg["clip"], cfg["floor"], cfg["dtype"], cfg["fe"])

    rows = []
    rows.append(("scikit-image's choices (numpy)", score(variant(SKIMAGE))))
    from skimage import restoration

    rows.append(
        (
            "scikit-image `richardson_lucy` itself",
            score(restoration.richardson_lucy(clipped, taps[None, :], num_iter=a.iterations)),
        )
    )
    rows.append(
        (
            "scikit-image on the unclipped negatives (baseline removed only)",
            score(
                restoration.richardson_lucy(
                    received - np.median(received[:, :8], axis=1, keepdims=True),
                    taps[None, :],
                    num_iter=a.iterations,
                )
            ),
        )
    )
    switches = [
        ("start", "data + 1e-3·max", "flat 0.5"),
        ("clip", "cap 1e9·max", "clip to [-1, 1]"),
        ("floor", "max(k⊛σ, 1e-6·max), 0 where y = 0", "k⊛σ + 1e-12"),
        ("dtype", "float32", "float64"),
        ("lowpass", "0.2 GHz low-pass (denoise)", "none"),
    ]
    values = {"start": ("data", "flat"), "clip": (False, True), "floor": ("fw", "eps"),
              "dtype": (np.float32, np.float64), "lowpass": (True, False)}
    for key, fw_name, sk_name in switches:
        cfg = dict(SKIMAGE, **{key: values[key][0]})
        rows.append((f"scikit-image's, but {key}: {fw_name}", score(variant(cfg))))
    for key, fw_name, sk_name in switches:
        cfg = dict(FWLIDAR, **{key: values[key][1]})
        rows.append((f"fwlidar's, but {key}: {sk_name}", score(variant(cfg))))
    fw = variant(FWLIDAR)
    rows.append(("fwlidar's choices (numpy)", score(fw)))
    real = process(["--method", "rl", "--iterations", str(a.iterations)])
    rows.append(("`fwlidar process --method rl` itself", score(real)))
    rows.append(("fwlidar's, with filter_epsilon = 1e-3·max", score(
        rl(np.maximum(denoised, 0), taps, a.iterations, "data", False, "fw", np.float32,
           1e-3 * float(np.maximum(denoised, 0).max())))))
    diff = np.max(np.abs(fw - real)) / np.max(np.abs(real))
    print(f"numpy fwlidar variant vs fwlidar process: largest difference {diff:.2e} of the peak\n")
    print("| RL-200 variant | RMSE / raw | pairs resolved | false / row |")
    print("|---|---:|---:|---:|")
    for name, s in rows:
        print(f"| {name} | {s['rmse']:.3f} | {s['pairs']:.2f} | {s['false']:.2f} |")


if __name__ == "__main__":
    main()
