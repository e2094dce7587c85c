#!/usr/bin/env bash
# Side by side, in one run, on the same waveforms: fwlidar's signal chain (criterion benches
# signal, deconvolve, nnls, decompose) and what a scientist would otherwise run (numpy, scipy,
# scikit-image; benches/compare/signal_python.py).
#
# 1. The criterion benches run with FWLIDAR_BENCH_WAVEFORMS set: each writes the exact inputs it
#    times (raw little-endian arrays) to that directory and prints their FNV-1a 64 checksums.
# 2. The Python script reads the same files (printing the same checksums), times the Python
#    equivalents (timeit, median) and prints a markdown table of both medians and the ratio,
#    taking fwlidar's medians from target/criterion/*/new/estimates.json of step 1.
#
# Needs python3 with numpy, scipy and scikit-image; a venv is made if FWLIDAR_BENCH_VENV (default
# target/bench-venv) has none. Extra arguments go to criterion (default: 1 s warm-up, 4 s).
set -euo pipefail
cd "$(dirname "$0")/../.."
venv=${FWLIDAR_BENCH_VENV:-target/bench-venv}
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q numpy scipy scikit-image
fi
target=${CARGO_TARGET_DIR:-target}
waveforms="$target/bench-waveforms"
rm -rf "$waveforms"
criterion_args=("$@")
[ ${#criterion_args[@]} -eq 0 ] && criterion_args=(--warm-up-time 1 --measurement-time 4)
lscpu | grep -m1 "Model name" || true
echo "date: $(date -u +%F), load average: $(cut -d' ' -f1-3 /proc/loadavg)"
for bench in signal deconvolve nnls decompose; do
  FWLIDAR_BENCH_WAVEFORMS="$waveforms" cargo bench -q --bench "$bench" -- "${criterion_args[@]}" 2>&1 |
    grep -E "^waveform|^[a-z_0-9/]+$|time:|^[a-z_0-9/]+ +time:"
done
"$venv/bin/python" benches/compare/signal_python.py --waveforms "$waveforms" --target "$target"
