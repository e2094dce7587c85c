#!/usr/bin/env bash
# Tree reconstruction scored against the simulator's truth (docs/accuracy.md, "3D tree
# reconstruction"): every combination of scene (the listed-branch trees of
# config/scenes/branch_trees.toml and the seed's tree plot), leaf-off / leaf-on, outgoing pulse
# 2 / 4 / 8 ns, nadir / 10° off nadir, raw / deconvolved waveforms. Each is simulated, then
# `fwlidar trees CAPTURE --truth <stem>.branches.csv`; the scores (trees.json) become one
# markdown table on stdout and a CSV.
#
#   benches/trees_accuracy.sh [WORK_DIR]      (default: target/trees_accuracy)
#
# Uses the release binary (built if missing). About 5 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-target/trees_accuracy}"
mkdir -p "$work"
if [ -z "${FWLIDAR_BIN:-}" ]; then cargo build --release --quiet; fi
bin="${FWLIDAR_BIN:-$(pwd)/target/release/fwlidar}"
scenes="${SCENES:-branch_trees tree_plot}"
pulses="${PULSES:-2 4 8}"
zeniths="${ZENITHS:-0 10}"
leaves="${LEAVES:-off on}"
waveforms="${WAVEFORMS:-raw deconvolved}"
for scene in $scenes; do
  case "$scene" in
    branch_trees) n=3; on_lad=0.8 ;;
    tree_plot) n=6; on_lad="" ;;
    *) echo "unknown scene $scene" >&2; exit 2 ;;
  esac
  for leaf in $leaves; do
    sets=()
    if [ "$leaf" = off ]; then
      for i in $(seq 0 $((n - 1))); do sets+=(--set "tree[$i].leaf_area_density=0"); done
    elif [ -n "$on_lad" ]; then
      for i in $(seq 0 $((n - 1))); do sets+=(--set "tree[$i].leaf_area_density=$on_lad"); done
    fi
    for p in $pulses; do
      for z in $zeniths; do
        cap="$work/${scene}_${leaf}_${p}ns_z${z}.fwcap"
        "$bin" simulate --scene "config/scenes/$scene.toml" --out "$cap" --no-truth-voxels \
          --set "sensor.outgoing_fwhm_ns=$p" --set "flight.scan.zenith_deg=$z" \
          --set "flight.scan.azimuth_deg=90" "${sets[@]}" >/dev/null 2>&1
        for w in $waveforms; do
          out="$work/${scene}_${leaf}_${p}ns_z${z}_$w"
          "$bin" trees "$cap" --out "$out" --force --waveform "$w" \
            --truth "${cap%.fwcap}.branches.csv" >/dev/null 2>&1 || echo "failed: $out" >&2
        done
      done
    done
  done
done
python3 - "$work" <<'EOF'
import json, sys, glob, os
work = sys.argv[1]
rows = []
for path in sorted(glob.glob(os.path.join(work, "*", "trees.json"))):
    name = os.path.basename(os.path.dirname(path))
    scene, rest = name.split("_off_") if "_off_" in name else name.split("_on_")
    leaf = "off" if "_off_" in name else "on"
    pulse, zen, wave = rest.split("_")
    d = json.load(open(path))
    s = d["score"]
    r = d["reconstruction"]
    rows.append(dict(scene=scene, leaf=leaf, pulse=int(pulse[:-2]), zenith=int(zen[1:]),
                     waveform=wave, threshold=r["threshold"]["chosen_v"],
                     trees=f'{s["trees_found"]}/{s["trees"]}',
                     found=f'{s["branches_found"]}/{s["branches"]}',
                     pct=None if s["found_fraction"] is None else 100 * s["found_fraction"],
                     extra=s["extra_branches"],
                     az=s["azimuth_err_deg"], zen=s["zenith_err_deg"],
                     len=100 * s["length_err_rel"] if s["length_err_rel"] is not None else None,
                     base=s["base_err_m"], stem=s["stem_position_err_m"], height=s["height_err_m"],
                     per_tree=d["seconds"]["per_tree"]))
order = {"raw": 0, "deconvolved": 1}
rows.sort(key=lambda r: (r["scene"], r["leaf"] == "on", r["pulse"], r["zenith"], order[r["waveform"]]))
def f(v, d=1):
    return "–" if v is None or v != v else f"{v:.{d}f}"
print("| scene | leaves | pulse | zenith | waveform | trees | branches > 1 m found | extra | |Δazimuth| ° | |Δzenith| ° | |Δlength|/L % | stem pos. m | |Δheight| m | s/tree |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for r in rows:
    print(f'| {r["scene"]} | {r["leaf"]} | {r["pulse"]} ns | {r["zenith"]}° | {r["waveform"]} | {r["trees"]} | {r["found"]} ({f(r["pct"],0)} %) | {r["extra"]} | {f(r["az"])} | {f(r["zen"])} | {f(r["len"],0)} | {f(r["stem"],2)} | {f(r["height"],2)} | {f(r["per_tree"],2)} |')
with open(os.path.join(work, "scores.csv"), "w") as out:
    keys = list(rows[0].keys()) if rows else []
    out.write(",".join(keys) + "\n")
    for r in rows:
        out.write(",".join(str(r[k]) for k in keys) + "\n")
EOF
