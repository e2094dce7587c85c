"""What a scientist would otherwise run to voxelise waveform bins: numpy, vectorised over a
batch of pulses (positions along the beam, floor to voxel indices, np.add.at for sums and
counts, np.maximum.at for maxima, np.unique per pulse for the pulses-passed count), timed per
pulse, beside fwlidar's criterion median for the same pulse (benches/voxel.rs: 256 bins from
40 m above the ground at 0.1499 m per ns, nadir and 20 degrees off nadir, 0.5 x 0.5 x 0.15 m
voxels, a 60 m height range, 32-column tiles).

Usage: voxel_python.py --target TARGET_DIR  (after `cargo bench --bench voxel`)
Prints a markdown table: fwlidar median, numpy median, ratio.
"""
import argparse
import json
import os
import sys
import timeit

import numpy as np


def criterion_median_us(target, bench_id):
    path = os.path.join(target, "criterion", bench_id, "new", "estimates.json")
    with open(path) as f:
        return json.load(f)["median"]["point_estimate"] / 1e3


def make(zenith_deg, batch):
    z = np.radians(zenith_deg)
    m = 0.1499
    d = np.array([m * np.sin(z), 0.0, -m * np.cos(z)])
    t = np.arange(256.0)
    signal = np.abs(np.sin(t * 0.1)).astype(np.float32)
    # The same pulse repeated `batch` times, as fwlidar's benchmark deposits it again and again.
    anchors = np.tile(np.array([500.2, 500.3, 40.0]), (batch, 1))
    shape = (400, 2048, 2048)  # levels, rows, columns of a 1 km store
    sums = np.zeros(shape[0] * shape[1] * shape[2] // 64, dtype=np.float64)  # one tile's worth
    counts = np.zeros_like(sums, dtype=np.uint32)
    maxima = np.full_like(sums, -np.inf, dtype=np.float32)
    passes = np.zeros_like(sums, dtype=np.uint32)
    inv = np.array([2.0, 2.0, 1 / 0.15])

    def run():
        pos = anchors[:, None, :] + t[None, :, None] * d[None, None, :]  # (batch, 256, 3)
        g = np.floor((pos - np.array([0.0, 0.0, -10.0])) * inv).astype(np.int64)
        ok = (g[..., 2] >= 0) & (g[..., 2] < 400)
        # Offsets in one 32 x 32 x 400 tile (columns contiguous, as fwlidar keeps them).
        col = (g[..., 1] % 32) * 32 + (g[..., 0] % 32)
        off = (col * 400 + g[..., 2])[ok]
        v = np.broadcast_to(signal, ok.shape)[ok]
        np.add.at(sums[: 32 * 32 * 400], off, v)
        np.add.at(counts[: 32 * 32 * 400], off, 1)
        np.maximum.at(maxima[: 32 * 32 * 400], off, v)
        # One pass per pulse and voxel.
        per_pulse = (np.arange(ok.shape[0])[:, None] * (32 * 32 * 400) + (col * 400 + g[..., 2]))[ok]
        u = np.unique(per_pulse) % (32 * 32 * 400)
        np.add.at(passes[: 32 * 32 * 400], u, 1)

    return run


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--target", default="target")
    ap.add_argument("--batch", type=int, default=1024)
    a = ap.parse_args()
    print(f"versions: python {sys.version.split()[0]}, numpy {np.__version__}")
    print()
    print("| case | fwlidar median per pulse | numpy median per pulse (batch of "
          f"{a.batch}) | fwlidar faster by |")
    print("|---|---:|---:|---:|")
    for name, zen in [("nadir", 0.0), ("off_nadir_20deg", 20.0)]:
        f = make(zen, a.batch)
        f()
        runs = timeit.repeat(f, number=1, repeat=15)
        py_us = sorted(runs)[len(runs) // 2] / a.batch * 1e6
        rs_us = criterion_median_us(a.target, f"voxel_deposit_256_bins/{name}")
        print(f"| {name} | {rs_us:.2f} us | {py_us:.2f} us | {py_us / rs_us:.1f}x |")


if __name__ == "__main__":
    main()
