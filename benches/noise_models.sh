#!/usr/bin/env bash
# Deconvolution over noise models (issue 37; docs/accuracy.md, "Deconvolution over noise
# models"): `tests/python/noise_models.py` on every noise model (white Gaussian, uniform with a
# non-zero mean, Poisson shot noise, baseline drift, 8-bit quantisation, saturation) at 4, 8
# and 16 ns system pulses and 0.5, 1 and 2 ns samples, `fwlidar process` settings beside
# scikit-image's RL-200 and scipy's NNLS in the same run. Writes the per-configuration tables
# (scores.md), every score (scores.json) and the per-model summary (summary.md: mean over the
# nine pulse × sample configurations, and the 8 ns / 1 ns configuration alone).
#
#   benches/noise_models.sh [WORK_DIR]      (default: target/noise_models)
#
# Uses the release binary (built if missing) and the project's venv (.ci/run makes it), or
# FWLIDAR_PYTHON. About 80 s on 2 cores with the default 200 rows (ROWS=...).
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-target/noise_models}"
mkdir -p "$work"
if [ -z "${FWLIDAR_BIN:-}" ]; then cargo build --release --quiet; fi
bin="${FWLIDAR_BIN:-$(pwd)/target/release/fwlidar}"
py="${FWLIDAR_PYTHON:-.venv/bin/python}"
"$py" tests/python/noise_models.py --fwlidar "$bin" --workdir "$work" \
  --waveforms "${ROWS:-200}" --model all \
  --pulse-fwhm-ns 4 --pulse-fwhm-ns 8 --pulse-fwhm-ns 16 \
  --sample-ns 0.5 --sample-ns 1 --sample-ns 2 \
  --json "$work/scores.json" > "$work/scores.md"
"$py" - "$work/scores.json" > "$work/summary.md" <<'PY'
import collections, json, sys
scores = json.load(open(sys.argv[1]))
models = list(dict.fromkeys(s["model"] for s in scores))
rows = list(dict.fromkeys(s["row"] for s in scores))
by = collections.defaultdict(list)
for s in scores:
    by[(s["model"], s["row"])].append(s)
def table(pick, title):
    print(f"\n{title} (RMSE / raw, pairs resolved)\n")
    print("| row | " + " | ".join(models) + " |")
    print("|---" * (len(models) + 1) + "|")
    for r in rows:
        cells = []
        for m in models:
            c = [s for s in by[(m, r)] if pick(s)]
            rm = sum(s["rmse_ratio"] for s in c) / len(c)
            pa = sum(s["pairs"] for s in c) / len(c)
            cells.append(f"{rm:.3f} / {100 * pa:.0f} %")
        print(f"| {r} | " + " | ".join(cells) + " |")
table(lambda s: True, "Mean over 4, 8, 16 ns pulses x 0.5, 1, 2 ns samples")
table(lambda s: s["pulse_fwhm_ns"] == 8 and s["sample_ns"] == 1, "8 ns pulse, 1 ns samples")
PY
cat "$work/summary.md"
