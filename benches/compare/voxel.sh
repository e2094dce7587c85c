#!/usr/bin/env bash
# Side by side, in one run: fwlidar's voxel deposit (criterion bench `voxel`) and numpy
# vectorised voxelisation of the same pulse (benches/compare/voxel_python.py). Uses the Python
# of .venv (made by .ci/run) or $FWLIDAR_PYTHON. Extra arguments go to criterion.
set -euo pipefail
cd "$(dirname "$0")/../.."
py=${FWLIDAR_PYTHON:-.venv/bin/python}
target=${CARGO_TARGET_DIR:-target}
criterion_args=("$@")
[ ${#criterion_args[@]} -eq 0 ] && criterion_args=(--warm-up-time 1 --measurement-time 5)
lscpu | grep -m1 "Model name" || true
echo "date: $(date -u +%F), load average: $(cut -d' ' -f1-3 /proc/loadavg)"
cargo bench -q --bench voxel -- "${criterion_args[@]}" 2>&1 | grep -E "^voxel|time:|thrpt:"
"$py" benches/compare/voxel_python.py --target "$target"
