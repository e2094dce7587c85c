#!/usr/bin/env bash
# fwlidar's DBSCAN (petal-clustering) beside scikit-learn's on the same points, in one run:
# the criterion bench `trees/dbscan_scan_first` (which writes the points), then
# benches/compare/trees_dbscan.py; prints both means and the ratio. Needs scikit-learn in
# .venv (`.venv/bin/pip install scikit-learn`).
set -euo pipefail
cd "$(dirname "$0")/../.."
cargo bench --bench trees -- dbscan_scan_first 2>&1 | grep -E "dbscan_scan_first|time:"
ours=$(python3 -c 'import json; print(json.load(open("target/criterion/trees/dbscan_scan_first/new/estimates.json"))["mean"]["point_estimate"] / 1e6)')
theirs=$(.venv/bin/python benches/compare/trees_dbscan.py)
echo "scikit-learn: $theirs"
python3 - "$ours" "$theirs" <<'PY'
import json, sys
ours = float(sys.argv[1]); t = json.loads(sys.argv[2])
print(f"fwlidar (petal-clustering) mean {ours:.3f} ms; scikit-learn mean {t['mean_ms']:.3f} ms "
      f"(p50 {t['p50_ms']:.3f}, max {t['max_ms']:.3f}) on {t['points']} points, "
      f"{t['clusters']} clusters; scikit-learn / fwlidar = {t['mean_ms'] / ours:.2f}")
PY
