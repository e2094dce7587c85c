#!/usr/bin/env bash
# Deconvolution by a kernel known to 10 % (issue 55; docs/accuracy.md, "Deconvolution by a
# learned kernel"): `tests/python/noise_models.py --kernel-mismatch ±0.1` on every noise model
# (the six of issue 37 and shot noise on an 8-bit digitizer) at 4, 8 and 16 ns system pulses and
# 0.5, 1 and 2 ns samples. The rows are drawn with a pulse 10 % wider (then narrower) than the
# kernel given; NNLS and RL to a 2 ns target run with the kernel given, with `--learn-kernel`
# (the given kernel stretched to the rows' echoes) and with the true pulse (`@true`), beside
# scikit-image's RL-200 and scipy's NNLS given the same wrong kernel. Writes every score
# (scores-*.json), the tables (scores-*.md) and summary.md: per model and mismatch, the RMSE with
# --learn-kernel over the RMSE with the true kernel (mean and worst over the nine pulse × sample
# configurations).
#
#   benches/kernel_mismatch.sh [WORK_DIR]      (default: target/kernel_mismatch)
#
# Uses the release binary (built if missing) and the project's venv (tests/run.sh makes it), or
# FWLIDAR_PYTHON. About 6 minutes on 2 cores with the default 200 rows (ROWS=...).
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-target/kernel_mismatch}"
mkdir -p "$work"
if [ -z "${FWLIDAR_BIN:-}" ]; then cargo build --release --quiet; fi
bin="${FWLIDAR_BIN:-$(pwd)/target/release/fwlidar}"
py="${FWLIDAR_PYTHON:-.venv/bin/python}"
for mis in 0.1 -0.1; do
  "$py" tests/python/noise_models.py --fwlidar "$bin" --workdir "$work/rows$mis" \
    --waveforms "${ROWS:-200}" --model all --kernel-mismatch "$mis" \
    --pulse-fwhm-ns 4 --pulse-fwhm-ns 8 --pulse-fwhm-ns 16 \
    --sample-ns 0.5 --sample-ns 1 --sample-ns 2 \
    --run "nnls-2ns=--method nnls --target-fwhm-ns 2" \
    --run "nnls-2ns-learn=--method nnls --target-fwhm-ns 2 --learn-kernel" \
    --run "nnls-2ns@true=--method nnls --target-fwhm-ns 2" \
    --run "rl-2ns=--method rl --target-fwhm-ns 2" \
    --run "rl-2ns-learn=--method rl --target-fwhm-ns 2 --learn-kernel" \
    --run "rl-2ns@true=--method rl --target-fwhm-ns 2" \
    --json "$work/scores$mis.json" > "$work/scores$mis.md"
done
"$py" - "$work"/scores0.1.json "$work"/scores-0.1.json > "$work/summary.md" <<'PY'
import collections, json, sys
scores = [s for f in sys.argv[1:] for s in json.load(open(f))]
models = list(dict.fromkeys(s["model"] for s in scores))
key = lambda s: (s["model"], s["kernel_mismatch"], s["pulse_fwhm_ns"], s["sample_ns"])
by = collections.defaultdict(dict)
for s in scores:
    by[key(s)][s["row"]] = s
for method in ("nnls-2ns", "rl-2ns"):
    print(f"\n{method}: RMSE / raw with the kernel given, with --learn-kernel, with the true "
          "kernel (mean over 4, 8, 16 ns x 0.5, 1, 2 ns); learned / true: mean and worst\n")
    print("| model | true pulse | given | learned | true | learned / true (mean) | (worst) |")
    print("|---|---|---|---|---|---|---|")
    for m in models:
        for mis in (0.1, -0.1):
            cs = [v for k, v in by.items() if k[0] == m and k[1] == mis]
            g = sum(c[method]["rmse_ratio"] for c in cs) / len(cs)
            l = sum(c[method + "-learn"]["rmse_ratio"] for c in cs) / len(cs)
            t = sum(c[method + "@true"]["rmse_ratio"] for c in cs) / len(cs)
            r = [c[method + "-learn"]["rmse_ratio"] / c[method + "@true"]["rmse_ratio"] for c in cs]
            w = max(range(len(cs)), key=lambda i: r[i])
            wc = cs[w][method]
            print(f"| {m} | {100 * mis:+.0f} % | {g:.3f} | {l:.3f} | {t:.3f} | "
                  f"{sum(r) / len(r):.3f} | {r[w]:.3f} ({wc['pulse_fwhm_ns']:g} ns / "
                  f"{wc['sample_ns']:g} ns) |")
PY
cat "$work/summary.md"
