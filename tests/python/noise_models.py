#!/usr/bin/env python3
"""Deconvolution over noise models: the held-out benchmark of issue 37.

One run scores ``fwlidar process`` settings beside scikit-image's Richardson-Lucy and scipy's
NNLS on the same simulated waveforms, for one or several **noise models**, **system pulse
widths** and **sample intervals**. Nothing here is tuned on: the rows are drawn from a fixed
seed (numpy's PCG64 ``default_rng``) per configuration.

Waveforms (per row, times in ns, ``--record-ns`` long, sampled every ``--sample-ns``):

- a **ground** echo at 210–235 ns, amplitude uniform in [0.6, 1.0];
- a **canopy** of 2–4 scatterers at 40–170 ns, amplitudes uniform in [0.1, 0.5];
- one **close pair** in the canopy: two surfaces 0.75 × the system pulse's FWHM apart,
  amplitudes uniform in [0.25, 0.5], placed at least 1.5 FWHM from every other scatterer;
- **received**: every surface seen through a Gaussian system pulse of ``--pulse-fwhm-ns``
  (unit area over the samples), then the noise model (below), ``P`` = the row's noise-free
  peak;
- **truth**: the same surfaces through a 2 ns FWHM Gaussian of unit area, no noise.

Noise models (``--model``, or ``all``):

- ``gaussian``: white Gaussian, σ = 0.03 P;
- ``uniform_offset``: a pedestal of 0.1 P plus uniform noise in ±0.03 P (a non-zero mean, as
  the seed's own simulations);
- ``poisson``: shot noise — the row scaled to 200 photo-electrons at its peak over a
  background of 2 per sample, drawn from Poisson, scaled back (variance follows the signal);
- ``drift``: a baseline drifting linearly from 0.05 P to 0.15 P along the record, plus white
  Gaussian σ = 0.01 P;
- ``quantised``: a pedestal of 0.1 P, white Gaussian σ = 0.01 P, then an 8-bit digitizer
  (256 codes over [0, 1.25 (P + pedestal)]), values kept in signal units;
- ``saturated``: a pedestal of 0.1 P, white Gaussian σ = 0.02 P, clipped at 0.1 P + 0.6 P
  (the strongest echoes' tops cut);
- ``shot_8bit``: shot noise as ``poisson``, on a pedestal of 0.1 P, then the 8-bit digitizer
  of ``quantised`` (the held-out set of issue 55).

**Kernel mismatch** (``--kernel-mismatch F``, e.g. 0.1 or -0.1): the rows are drawn with a
system pulse of (1 + F) × ``--pulse-fwhm-ns`` while the kernel given to every row (fwlidar's
``--kernel``, scikit-image's PSF, scipy's matrix) keeps ``--pulse-fwhm-ns``: the system pulse is
known only to 10 %. A run whose label ends in ``@true`` gets the true pulse as ``--kernel``
instead (what the same setting reaches with the right kernel).

Rows scored (in this order): ``raw``; ``skimage-rl200`` (``skimage.restoration.
richardson_lucy``, 200 iterations, its defaults, on the rows with their baseline removed and
negatives clipped, the sampled system pulse as PSF); ``scipy-nnls+2ns`` (``scipy.optimize.nnls``
per row against the system pulse's convolution matrix, on the baseline-corrected rows, the
spikes then drawn with the 2 ns pulse); and each ``--run LABEL=ARGS`` (``fwlidar process
--input rows.npy --kernel kernel.npy --sample-ns S --out OUT.npy --no-progress ARGS``; without
``--run``, the issue's table of settings and ``rl20-2ns``, RL 20 to the 2 ns target).

Scores (per row group, pooled over rows):

- **RMSE / raw**: the RMSE against the truth over every sample, each row's baseline (the
  median of its first 30 ns, echo-free by construction) removed first, divided by the same
  RMSE of the raw rows;
- **pairs**: the share of close pairs resolved: both surfaces have a local maximum within
  max(1 sample, 1 ns) of their time, and the output dips between the two below 80 % of the
  smaller of the two maxima.

Output: a markdown table per configuration on stdout, and with ``--json FILE`` every score as
``[{"model", "pulse_fwhm_ns", "sample_ns", "row", "rmse_ratio", "pairs"}]``. Exit 2 on a usage or
run error.

Example: ``noise_models.py --fwlidar target/release/fwlidar --workdir /tmp/nm --model all``.
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np

MODELS = ("gaussian", "uniform_offset", "poisson", "drift", "quantised", "saturated", "shot_8bit")
TRUTH_FWHM_NS = 2.0
PAIR_GAP_FWHM = 0.75
BASELINE_NS = 30.0
DIP = 0.8
KERNEL_ZEROS = 8

DEFAULT_RUNS = (
    "nnls-2ns=--method nnls --target-fwhm-ns 2",
    "rl200-2ns=--method rl --iterations 200 --target-fwhm-ns 2",
    "rl-2ns=--method rl --target-fwhm-ns 2",
    # A fixed small count: what the noise-aware stop must never end worse than.
    "rl20-2ns=--method rl --iterations 20 --target-fwhm-ns 2",
    "rl200-2ns-stop1=--method rl --iterations 200 --target-fwhm-ns 2 --stop-at-noise 1",
    "rl200=--method rl --iterations 200",
)


def gaussian(t, centre, fwhm, dt):
    """A unit-area Gaussian of FWHM ``fwhm`` ns at ``centre`` ns, sampled at ``t`` (sum = 1)."""
    s = fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return np.exp(-0.5 * ((t - centre) / s) ** 2) * dt / (s * np.sqrt(2.0 * np.pi))


def draw_surfaces(rng, fwhm):
    """(times ns, amplitudes) of one row's surfaces, the close pair first."""
    gap = PAIR_GAP_FWHM * fwhm
    while True:
        p0 = rng.uniform(50.0, 160.0 - gap)
        canopy = rng.uniform(40.0, 170.0, size=rng.integers(2, 5))
        far = np.abs(canopy[:, None] - np.array([p0, p0 + gap])[None, :]).min(axis=1)
        if np.all(far >= 1.5 * fwhm):
            break
    times = np.concatenate([[p0, p0 + gap], canopy, [rng.uniform(210.0, 235.0)]])
    amps = np.concatenate(
        [
            rng.uniform(0.25, 0.5, size=2),
            rng.uniform(0.1, 0.5, size=len(canopy)),
            [rng.uniform(0.6, 1.0)],
        ]
    )
    return times, amps


def add_noise(rng, clean, model, t):
    peak = float(clean.max())
    n = clean.shape[0]
    if model == "gaussian":
        return clean + rng.normal(0.0, 0.03 * peak, n)
    if model == "uniform_offset":
        return clean + 0.1 * peak + rng.uniform(-0.03 * peak, 0.03 * peak, n)
    if model == "poisson":
        gain = 200.0 / peak
        return rng.poisson(clean * gain + 2.0).astype(float) / gain
    if model == "drift":
        base = peak * (0.05 + 0.10 * (t - t[0]) / max(t[-1] - t[0], 1e-9))
        return clean + base + rng.normal(0.0, 0.01 * peak, n)
    if model == "quantised":
        pedestal = 0.1 * peak
        y = clean + pedestal + rng.normal(0.0, 0.01 * peak, n)
        q = 1.25 * (peak + pedestal) / 255.0
        return np.clip(np.round(y / q), 0, 255) * q
    if model == "shot_8bit":
        gain = 200.0 / peak
        pedestal = 0.1 * peak
        y = rng.poisson(clean * gain + 2.0).astype(float) / gain + pedestal
        q = 1.25 * (peak + pedestal) / 255.0
        return np.clip(np.round(y / q), 0, 255) * q
    if model == "saturated":
        y = clean + 0.1 * peak + rng.normal(0.0, 0.02 * peak, n)
        return np.minimum(y, 0.7 * peak)
    raise ValueError(f"unknown noise model {model!r}")


def simulate(rows, model, fwhm, dt, record_ns, seed):
    t = np.arange(int(round(record_ns / dt))) * dt
    rng = np.random.default_rng(seed)
    received, truth, pairs = [], [], []
    for _ in range(rows):
        times, amps = draw_surfaces(rng, fwhm)
        clean = sum(a * gaussian(t, c, fwhm, dt) for c, a in zip(times, amps))
        received.append(add_noise(rng, clean, model, t))
        truth.append(sum(a * gaussian(t, c, TRUTH_FWHM_NS, dt) for c, a in zip(times, amps)))
        pairs.append((times[0], times[1]))
    return t, np.array(received), np.array(truth), pairs


def kernel_taps(fwhm, dt):
    s = fwhm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    half = int(np.ceil(3.5 * s / dt))
    k = gaussian(np.arange(-half, half + 1) * dt, 0.0, fwhm, dt)
    return k / k.sum()


def baseline_removed(rows, t):
    head = t < BASELINE_NS
    return rows - np.median(rows[:, head], axis=1, keepdims=True)


def local_maxima(y):
    """Indices where the first difference turns from positive to non-positive (a flat top at
    its first sample), above 0."""
    d = np.diff(y)
    i = np.nonzero((d[:-1] > 0) & (d[1:] <= 0))[0] + 1
    return i[y[i] > 0]


def resolved(y, t, pair, dt):
    tol = max(dt, 1.0)
    peaks = local_maxima(y)
    got = []
    for c in pair:
        near = peaks[np.abs(t[peaks] - c) <= tol]
        if len(near) == 0:
            return False
        got.append(near[np.argmax(y[near])])
    a, b = sorted(got)
    if a == b:
        return False
    dip = y[a : b + 1].min()
    return dip < DIP * min(y[a], y[b])


def score(out, received, truth, pairs, t, dt):
    raw_rmse = np.sqrt(np.mean((baseline_removed(received, t) - truth) ** 2))
    rmse = np.sqrt(np.mean((baseline_removed(out, t) - truth) ** 2))
    ok = [resolved(y, t, p, dt) for y, p in zip(out, pairs)]
    return rmse / raw_rmse, float(np.mean(ok))


def skimage_rl(received, t, k):
    from skimage.restoration import richardson_lucy

    y = np.clip(baseline_removed(received, t), 0.0, None)
    return richardson_lucy(y, k[None, :], num_iter=200)


def scipy_nnls(received, t, k, dt):
    from scipy.optimize import nnls

    n = received.shape[1]
    half = len(k) // 2
    a = np.zeros((n, n))
    for j in range(n):
        for m, v in enumerate(k):
            i = j + m - half
            if 0 <= i < n:
                a[i, j] = v
    draw = kernel_taps(TRUTH_FWHM_NS, dt)
    out = []
    for y in baseline_removed(received, t):
        x, _ = nnls(a, y, maxiter=50 * n)
        out.append(np.convolve(x, draw, mode="same"))
    return np.array(out)


def run_fwlidar(binary, workdir, label, args, dt):
    out = os.path.join(workdir, f"out-{label}.npy")
    kernel = "kernel_true.npy" if label.endswith("@true") else "kernel.npy"
    cmd = [binary, "process", "--input", os.path.join(workdir, "rows.npy"), "--kernel",
           os.path.join(workdir, kernel), "--sample-ns", str(dt), "--out", out,
           "--no-progress"] + args.split()
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.stderr.write(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr}\n")
        sys.exit(2)
    return np.load(out).astype(float)


def save_kernel(path, k):
    padded = np.concatenate([np.zeros(KERNEL_ZEROS), k, np.zeros(KERNEL_ZEROS)])
    np.save(path, padded[None, :].astype(np.float32))


def one_configuration(a, model, fwhm, dt, seed):
    true_fwhm = fwhm * (1.0 + a.kernel_mismatch)
    t, received, truth, pairs = simulate(a.waveforms, model, true_fwhm, dt, a.record_ns, seed)
    k = kernel_taps(fwhm, dt)
    np.save(os.path.join(a.workdir, "rows.npy"), received.astype(np.float32))
    save_kernel(os.path.join(a.workdir, "kernel.npy"), k)
    save_kernel(os.path.join(a.workdir, "kernel_true.npy"), kernel_taps(true_fwhm, dt))
    rows = [("raw", received), ("skimage-rl200", skimage_rl(received, t, k)),
            ("scipy-nnls+2ns", scipy_nnls(received, t, k, dt))]
    for spec in a.run or DEFAULT_RUNS:
        label, _, args = spec.partition("=")
        rows.append((label, run_fwlidar(a.fwlidar, a.workdir, label, args, dt)))
    results = []
    for label, out in rows:
        r, p = score(out, received, truth, pairs, t, dt)
        results.append({"model": model, "pulse_fwhm_ns": fwhm, "sample_ns": dt,
                        "kernel_mismatch": a.kernel_mismatch, "row": label,
                        "rmse_ratio": round(float(r), 4), "pairs": round(p, 4)})
    return results


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fwlidar", required=True)
    ap.add_argument("--workdir", required=True)
    ap.add_argument("--waveforms", type=int, default=200)
    ap.add_argument("--record-ns", type=float, default=256.0)
    ap.add_argument("--model", action="append", default=[],
                    help=f"one of {', '.join(MODELS)}, or all (repeatable; default gaussian)")
    ap.add_argument("--pulse-fwhm-ns", type=float, action="append", default=[])
    ap.add_argument("--sample-ns", type=float, action="append", default=[])
    ap.add_argument("--run", action="append", default=[], help="LABEL=ARGS for fwlidar process")
    ap.add_argument("--seed", type=int, default=37)
    ap.add_argument("--kernel-mismatch", type=float, default=0.0,
                    help="rows drawn with a pulse (1 + F) x the kernel's FWHM (e.g. 0.1)")
    ap.add_argument("--json")
    a = ap.parse_args()
    models = [m for x in (a.model or ["gaussian"]) for m in (MODELS if x == "all" else [x])]
    bad = [m for m in models if m not in MODELS]
    if bad or a.waveforms < 1 or not -0.5 < a.kernel_mismatch < 1.0:
        sys.stderr.write(f"unknown model(s) {bad} (known: {', '.join(MODELS)}) or no rows\n")
        sys.exit(2)
    os.makedirs(a.workdir, exist_ok=True)
    everything = []
    for fwhm in a.pulse_fwhm_ns or [8.0]:
        for dt in a.sample_ns or [1.0]:
            for i, model in enumerate(models):
                res = one_configuration(a, model, fwhm, dt, a.seed + 1000 * i)
                everything += res
                mis = (f", true pulse {100 * a.kernel_mismatch:+g} %" if a.kernel_mismatch else "")
                print(f"\n### {model}, {fwhm:g} ns pulse{mis}, {dt:g} ns samples, "
                      f"{a.waveforms} rows\n")
                print("| row | RMSE / raw | pairs resolved |\n|---|---|---|")
                for r in res:
                    print(f"| {r['row']} | {r['rmse_ratio']:.3f} | {100 * r['pairs']:.1f} % |")
                sys.stdout.flush()
    if a.json:
        with open(a.json, "w") as f:
            json.dump(everything, f, indent=1)


if __name__ == "__main__":
    main()
