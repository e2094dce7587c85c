#!/usr/bin/env python3
"""Close echo pairs: the benchmark of issue 19, waveforms the project's own sweep has not seen.

Waveforms (fixed seed, numpy's PCG64 ``default_rng(seed)``):

- ``--waveforms`` rows of ``--bins`` (225) bins at 1 ns; in each, two **close pairs** and one
  **single echo**, at continuous (sub-bin) two-way times. A pair is two hard surfaces 6 ns
  apart (0.75 × the system pulse's 8 ns FWHM), each of amplitude uniform in [0.05, 0.4] (weak
  returns: canopy, low vegetation); the single echo is the strong one (ground, uniform in
  [0.8, 1.0]). The three lie in three placement ranges (first surface at 40–51, 100–111,
  165–176 bins, the single in a random one), at least 33 bins apart.
- **Received**: every surface seen through an 8 ns FWHM Gaussian pulse of unit area (the
  system pulse, evaluated at the bins), plus a digitizer **pedestal** of 10 % of the row's
  noise-free peak, plus uniform white noise in ±3 % of that peak (``fwlidar tradeoff``'s
  default ``--noise 0.03``, the seed's noise model).
- **Truth**: the same surfaces seen through a 2 ns FWHM Gaussian of unit area (the seed's
  "near-perfect" pulse), no pedestal, no noise.
- **Kernel file** given to ``fwlidar process --kernel``: the 8 ns pulse sampled at integer
  offsets within ±3.5 standard deviations, unit sum (as ``src/sim/truth.rs``), preceded and
  followed by 8 zeros (``process`` takes the median of a kernel row's first 8 samples as its
  baseline; zeros keep the taps as they are).

Files in ``--workdir``: ``waveforms.npy`` (float32 rows), ``kernel.npy``, ``truth.npy``,
``surfaces.csv`` (``waveform,position_bins``), and one ``out-LABEL.npy`` per ``--run``.

Rows scored (in this order):

- ``raw``: the received waveform.
- ``skimage-rl200``: ``skimage.restoration.richardson_lucy`` 200 iterations (its defaults:
  start 0.5, ``clip=True``, no ``filter_epsilon``) on the received rows with their baseline
  removed (the median of each row's first 8 samples subtracted, as ``fwlidar process``'s denoise
  does) and negative samples clipped to 0 (RL's data are non-negative), float64, the 8 ns taps
  as PSF (one 2-D call with a 1 × m PSF: row by row).
- every ``--run LABEL=ARGS``: ``fwlidar process --input waveforms.npy --kernel kernel.npy
  --out OUT.npy --no-progress ARGS``; a LABEL ending in ``+2ns`` has its output convolved with
  the 2 ns truth pulse before scoring (the "convolved afterwards" row of the issue). Without
  ``--run``, the issue's table: ``rl200`` (``--method rl --iterations 200``),
  ``rl200-no-denoise`` (and ``--no-denoise``), ``nnls`` (``--method nnls``) and ``nnls+2ns``.

Scores:

- **RMSE / raw**: the RMSE of the output against the truth over every bin of every row
  (pooled), divided by the same RMSE of the raw received rows. Below 1 is better than raw.
- **pairs resolved**: the share of close pairs (truth spikes at ``p`` and ``p + 6``) for which
  the output has **two distinct local maxima**, one within ±1 bin of ``p`` and one within ±1 bin
  of ``p + 6`` (``p`` continuous; a maximum at bin ``i`` is within when ``|i − p| ≤ 1``). A local maximum is as ``fwlidar tradeoff`` counts peaks
  (``eval::metrics::local_peaks``): a bin where the first difference turns from positive to
  negative, a flat top counted at its first bin, kept only when its value is above 5 % of the
  row's maximum (and above 0). The two windows cannot share a maximum (6 > 2 × 1).
- **singles**: the share of single echoes with a local maximum (same rule) within ±1 bin, and
  **false / row**: local maxima farther than 1 bin from every surface, per row (reported,
  not targeted).

Targets: ``--expect "LABEL METRIC OP VALUE"``, METRIC ``rmse`` (RMSE / raw) or ``pairs`` or
``singles``, OP one of ``<= < >= >``, VALUE a number or another row's label (its same metric).
The table is printed (markdown) either way; the exit status is 1 when an expectation fails, 2
for a usage or run error.

Example: ``close_pairs.py --fwlidar target/release/fwlidar --workdir /tmp/cp
--expect "rl200 rmse < 1" --expect "skimage-rl200 pairs >= 0.4"``.
"""

import argparse
import os
import subprocess
import sys

import numpy as np

SYSTEM_FWHM_NS = 8.0
TRUTH_FWHM_NS = 2.0
PAIR_GAP_BINS = 6  # 0.75 × 8 ns at 1 ns
NOISE_FRACTION = 0.03
PEAK_FLOOR = 0.05
TOLERANCE_BINS = 1
KERNEL_ZEROS = 8
SLOTS = (40, 100, 165)  # first bin of each surface group's 11-bin placement range
SINGLE_AMPLITUDE = (0.8, 1.0)  # the strong single echo (ground)
PAIR_AMPLITUDE = (0.05, 0.4)  # each surface of a close pair (weak: canopy, low vegetation)
PEDESTAL_FRACTION = 0.1  # digitizer baseline, fraction of the noise-free peak
DEFAULT_RUNS = [
    "rl200=--method rl --iterations 200",
    "rl200-no-denoise=--method rl --iterations 200 --no-denoise",
    "nnls=--method nnls",
    "nnls+2ns=--method nnls",
]


def gaussian_taps(fwhm_ns, sample_ns=1.0):
    """Unit-sum Gaussian taps at ±3.5 standard deviations (as src/sim/truth.rs), centre index."""
    sigma = fwhm_ns / sample_ns / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    half = max(int(np.ceil(3.5 * sigma)), 1)
    x = np.arange(-half, half + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / sigma) ** 2)
    return taps / taps.sum(), half


def convolve_rows(x, taps, centre):
    """Row-wise 'same' convolution with zeros outside (the project's kernel convention)."""
    n = x.shape[1]
    full = np.apply_along_axis(lambda r: np.convolve(r, taps), 1, x)
    return full[:, centre : centre + n]


def render(positions, amplitudes, fwhm_ns, bins):
    """Sum of unit-area Gaussians of FWHM ``fwhm_ns`` at continuous ``positions`` (bins)."""
    s = fwhm_ns / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    i = np.arange(bins, dtype=np.float64)
    g = np.exp(-0.5 * ((i[None, :] - positions[:, None]) / s) ** 2)
    return (amplitudes[:, None] * g).sum(axis=0) / (np.sqrt(2.0 * np.pi) * s)


def make_set(waveforms, bins, seed):
    """Received rows, truth rows, the surfaces of every row, the pair and single positions."""
    rng = np.random.default_rng(seed)
    received = np.zeros((waveforms, bins))
    truth = np.zeros((waveforms, bins))
    surfaces = []  # per row: the positions of its surfaces (bins, continuous)
    pairs = []  # (row, position of the pair's first surface)
    singles = []  # (row, position)
    if bins < SLOTS[-1] + 11 + PAIR_GAP_BINS + 30:
        raise SystemExit(f"--bins {bins} is too few (at least {SLOTS[-1] + 47})")
    for r in range(waveforms):
        single_slot = rng.integers(0, 3)
        pos, amp = [], []
        for slot in range(3):
            p = SLOTS[slot] + rng.integers(0, 11) + rng.uniform(0.0, 1.0)
            if slot == single_slot:
                pos.append(p)
                amp.append(rng.uniform(*SINGLE_AMPLITUDE))
                singles.append((r, p))
            else:
                pos += [p, p + PAIR_GAP_BINS]
                amp += [rng.uniform(*PAIR_AMPLITUDE), rng.uniform(*PAIR_AMPLITUDE)]
                pairs.append((r, p))
        pos, amp = np.array(pos), np.array(amp)
        surfaces.append(pos)
        received[r] = render(pos, amp, SYSTEM_FWHM_NS, bins)
        truth[r] = render(pos, amp, TRUTH_FWHM_NS, bins)
    peak = received.max(axis=1, keepdims=True)
    noise = rng.uniform(-1.0, 1.0, size=received.shape) * NOISE_FRACTION * peak
    received = received + PEDESTAL_FRACTION * peak + noise
    return received, truth, surfaces, pairs, singles


def local_peaks(x, floor_fraction=PEAK_FLOOR):
    """Bins of the local maxima of x (eval::metrics::local_peaks's rule)."""
    mx = max(float(x.max()), 0.0)
    floor = max(floor_fraction * mx, 0.0)
    out = []
    rise_at = None
    for i in range(1, len(x)):
        d = x[i] - x[i - 1]
        if d > 0:
            rise_at = i
        elif d < 0 and rise_at is not None:
            if x[rise_at] > floor:
                out.append(rise_at)
            rise_at = None
    return out


def score(out, truth, raw_rmse, pairs, singles, surfaces):
    rmse = float(np.sqrt(np.mean((out - truth) ** 2)))
    peaks = [np.array(local_peaks(row), dtype=int) for row in out]

    def near(r, p):
        pk = peaks[r]
        return pk[np.abs(pk - p) <= TOLERANCE_BINS]

    resolved = 0
    for r, p in pairs:
        a, b = near(r, p), near(r, p + PAIR_GAP_BINS)
        if len(a) and len(b):
            resolved += 1
    found = sum(1 for r, p in singles if len(near(r, p)))
    false = 0
    for r, pk in enumerate(peaks):
        for q in pk:
            if np.min(np.abs(surfaces[r] - q)) > TOLERANCE_BINS:
                false += 1
    return {
        "rmse": rmse / raw_rmse,
        "pairs": resolved / max(len(pairs), 1),
        "singles": found / max(len(singles), 1),
        "false": false / out.shape[0],
    }


def skimage_rl(received, taps, iterations):
    from skimage import restoration

    return restoration.richardson_lucy(baseline_removed(received), taps[None, :], num_iter=iterations)


def baseline_removed(received):
    """Rows minus the median of their first 8 samples, negatives clipped to 0 (RL's data are
    non-negative; unclipped, scikit-image's RL turns the negative noise into ±1 oscillations)."""
    base = np.median(received[:, :KERNEL_ZEROS], axis=1, keepdims=True)
    return np.maximum(received - base, 0.0)


def run_fwlidar(binary, workdir, label, args, inp, kernel):
    out = os.path.join(workdir, "out-" + "".join(c if c.isalnum() else "_" for c in label) + ".npy")
    cmd = [binary, "process", "--input", inp, "--kernel", kernel, "--out", out, "--no-progress"]
    cmd += args.split()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.stderr.write(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stderr}\n")
        raise SystemExit(2)
    return np.load(out).astype(np.float64), " ".join(["fwlidar process"] + args.split())


def parse_expect(text):
    parts = text.split()
    if len(parts) != 4 or parts[1] not in ("rmse", "pairs", "singles") or parts[2] not in (
        "<=",
        "<",
        ">=",
        ">",
    ):
        raise SystemExit(f'--expect "{text}": want "LABEL rmse|pairs|singles <=|<|>=|> VALUE|LABEL"')
    return parts


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fwlidar", help="the fwlidar binary (fwlidar rows are skipped without it)")
    ap.add_argument("--workdir", required=True, help="where the tables and outputs are written")
    ap.add_argument("--waveforms", type=int, default=500)
    ap.add_argument("--bins", type=int, default=225)
    ap.add_argument("--seed", type=int, default=19)
    ap.add_argument("--skimage-iterations", type=int, default=200)
    ap.add_argument("--run", action="append", default=None, metavar="LABEL=ARGS")
    ap.add_argument("--expect", action="append", default=[], metavar='"LABEL METRIC OP VALUE"')
    ap.add_argument("--no-skimage", action="store_true")
    a = ap.parse_args()
    expects = [parse_expect(e) for e in a.expect]
    os.makedirs(a.workdir, exist_ok=True)

    received, truth, surfaces, pairs, singles = make_set(a.waveforms, a.bins, a.seed)
    inp = os.path.join(a.workdir, "waveforms.npy")
    kernel = os.path.join(a.workdir, "kernel.npy")
    np.save(inp, received.astype(np.float32))
    np.save(os.path.join(a.workdir, "truth.npy"), truth.astype(np.float32))
    with open(os.path.join(a.workdir, "surfaces.csv"), "w") as f:
        f.write("waveform,position_bins\n")
        for r, pos in enumerate(surfaces):
            f.writelines(f"{r},{p:.4f}\n" for p in pos)
    sys_taps, _ = gaussian_taps(SYSTEM_FWHM_NS)
    zeros = np.zeros(KERNEL_ZEROS)
    np.save(kernel, np.concatenate([zeros, sys_taps, zeros]).astype(np.float32)[None, :])
    tru_taps, tru_c = gaussian_taps(TRUTH_FWHM_NS)

    raw_rmse = float(np.sqrt(np.mean((received - truth) ** 2)))
    rows = [("raw", "received waveform", score(received, truth, raw_rmse, pairs, singles, surfaces))]
    if not a.no_skimage:
        out = skimage_rl(received, sys_taps, a.skimage_iterations)
        rows.append(
            (
                f"skimage-rl{a.skimage_iterations}",
                f"skimage richardson_lucy {a.skimage_iterations}, baseline removed",
                score(out, truth, raw_rmse, pairs, singles, surfaces),
            )
        )
    runs = a.run if a.run is not None else DEFAULT_RUNS
    for spec in runs if a.fwlidar else []:
        if "=" not in spec:
            raise SystemExit(f'--run "{spec}": want LABEL=ARGS')
        label, args = spec.split("=", 1)
        out, what = run_fwlidar(a.fwlidar, a.workdir, label, args, inp, kernel)
        if label.endswith("+2ns"):
            out = convolve_rows(out, tru_taps, tru_c)
            what += ", then convolved with the 2 ns pulse"
        rows.append((label, what, score(out, truth, raw_rmse, pairs, singles, surfaces)))

    print(
        f"{a.waveforms} waveforms × {a.bins} bins, seed {a.seed}: {len(pairs)} close pairs "
        f"({PAIR_GAP_BINS} ns apart, 8 ns FWHM pulse), {len(singles)} single echoes, "
        f"noise ±{NOISE_FRACTION:.0%} of the peak; raw RMSE {raw_rmse:.5f}\n"
    )
    print("| row | processing | RMSE / raw | pairs resolved | singles found | false / row |")
    print("|---|---|---:|---:|---:|---:|")
    for label, what, s in rows:
        print(
            f"| {label} | {what} | {s['rmse']:.3f} | {s['pairs']:.2f} | {s['singles']:.2f} "
            f"| {s['false']:.2f} |"
        )

    by = {label: s for label, _, s in rows}
    failed = 0
    for label, metric, op, value in expects:
        if label not in by:
            sys.stderr.write(f"--expect names row {label}, which was not run\n")
            raise SystemExit(2)
        got = by[label][metric]
        if value in by:
            want, wname = by[value][metric], f"{value} ({by[value][metric]:.3f})"
        else:
            try:
                want = float(value)
            except ValueError:
                sys.stderr.write(f"--expect: {value} is neither a number nor a row label\n")
                raise SystemExit(2)
            wname = value
        ok = {"<=": got <= want, "<": got < want, ">=": got >= want, ">": got > want}[op]
        status = "ok" if ok else "FAILED"
        print(f"expect {label} {metric} {got:.3f} {op} {wname}: {status}")
        failed += not ok
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
