#!/usr/bin/env bash
# Side by side, in one run: fwlidar's denoise stage (criterion) and the numpy/scipy equivalent a
# user would otherwise write. Needs python3 with numpy and scipy (a venv is made if missing).
set -euo pipefail
cd "$(dirname "$0")/../.."
venv=${FWLIDAR_BENCH_VENV:-target/bench-venv}
if [ ! -x "$venv/bin/python" ]; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q numpy scipy
fi
cargo bench --bench signal -- --warm-up-time 1 --measurement-time 5 2>&1 | grep -E "^denoise|time:"
"$venv/bin/python" benches/compare/denoise_numpy.py
