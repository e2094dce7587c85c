#!/usr/bin/env bash
# Whole-run timings of a campaign (docs/performance.md, "A campaign ..."): wall clock of whole
# commands, three runs each, on simulated survey lines (config/scenes/survey_line.toml).
#   1. four crossing lines: `campaign run --local 1|2` (replays + merge + metrics rasters);
#   2. eight parallel lines 40 m apart: one flat merge, a pairwise tree, a chain;
#   3. one 200 000-pulse line: one replay against four `replay --shard i/4` one after another.
# Usage: benches/campaign.sh [WORK_DIR]   (needs `cargo build --release` first)
# Every run writes into a folder of its own and nothing is deleted between runs: on this VM's
# ext4, each `rm -rf` of a run's few thousand files made every later run slower (CPU and wall
# growing run after run: 4.3, 7.7, 10.8, 13.1 s for the same campaign), which is what made the
# earlier tree and chain figures spread by 2x.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
F=${FWLIDAR:-$root/target/release/fwlidar}
W=${1:-$(mktemp -d)}
mkdir -p "$W/lines" "$W/par"
cd "$W"
sim() { # out pulses start end
  [ -f "$1" ] || "$F" simulate --scene "$root/config/scenes/survey_line.toml" --pulses "$2" \
    --no-truth-voxels --out "$1" --set "flight.lines=[{start_m=$3, end_m=$4}]" >/dev/null 2>&1
}
sim lines/line0.fwcap 12000 "[-1.0, 0.0]" "[300.0, 0.0]"
sim lines/line1.fwcap 12000 "[0.0, -1.0]" "[0.0, 300.0]"
sim lines/line2.fwcap 12000 "[-1.0, -1.0]" "[200.0, 200.0]"
sim lines/line3.fwcap 12000 "[1.0, -1.0]" "[-200.0, 200.0]"
camp() { # file out captures
  printf '[campaign]\nname = "bench"\ncaptures = ["%s"]\nset = ["output.waveforms=false", "output.las=false", "output.rasters=false"]\nout = "%s"\nepsg = 32736\n' "$3" "$2" >"$1"
}
t() { local s e; s=$(date +%s.%N); "$@" >/dev/null 2>&1; e=$(date +%s.%N); echo "$e - $s" | bc; }
echo "== four crossing lines: campaign run --local N (wall s; merge s and metrics s from campaign.json)"
for n in 1 2; do
  for r in 1 2 3; do
    camp c$n$r.toml "out$n$r" "lines/line?.fwcap"
    w=$(t "$F" campaign run c$n$r.toml --local $n)
    m=$(python3 -c "import json;r=json.load(open('out$n$r/campaign.json'));print(round(r['merge']['wall_s'],2), round(r['metrics']['seconds'],2), round(sum(l['cpu_s'] for l in r['lines']),2), r['merge']['tiles_copied'], r['merge']['tiles'])")
    echo "processes $n run $r: wall $w s; merge, metrics, replay CPU, tiles copied / tiles: $m"
  done
done
echo "== eight parallel lines 40 m apart: merges"
for i in 0 1 2 3 4 5 6 7; do
  y=$((i * 40))
  sim par/p$i.fwcap 12000 "[-150.0, $y.0]" "[150.0, $y.0]"
done
camp p.toml outp "par/p?.fwcap"
"$F" campaign run p.toml --local 2 >/dev/null 2>&1
du -sb outp/lines/*/voxels.zarr | awk '{s+=$1} END {print "line stores:", s/1e6, "MB"}'
L=outp/lines
for r in 1 2 3; do
  mkdir -p "m$r"
  w=$(t "$F" merge --no-progress --out m$r/flat.zarr $L/p?/voxels.zarr)
  echo "flat (one merge of 8) run $r: $w s"
  s=$(date +%s.%N)
  for k in 0 1 2 3; do
    "$F" merge --no-progress --out m$r/a$k.zarr $L/p$((2 * k))/voxels.zarr $L/p$((2 * k + 1))/voxels.zarr >/dev/null
  done
  "$F" merge --no-progress --out m$r/b0.zarr m$r/a0.zarr m$r/a1.zarr >/dev/null
  "$F" merge --no-progress --out m$r/b1.zarr m$r/a2.zarr m$r/a3.zarr >/dev/null
  "$F" merge --no-progress --out m$r/tree.zarr m$r/b0.zarr m$r/b1.zarr >/dev/null
  e=$(date +%s.%N)
  echo "pairwise tree (7 merges, one at a time) run $r: $(echo "$e - $s" | bc) s"
  s=$(date +%s.%N)
  prev=$L/p0/voxels.zarr
  for i in 1 2 3 4 5 6 7; do
    "$F" merge --no-progress --out m$r/c$i.zarr "$prev" $L/p$i/voxels.zarr >/dev/null
    prev=m$r/c$i.zarr
  done
  e=$(date +%s.%N)
  echo "chain run $r: $(echo "$e - $s" | bc) s"
done
"$F" merge --no-progress --out m1/again.zarr $L/p?/voxels.zarr | sed 's/^/flat merge says: /'
diff -rq -x zarr.json m1/flat.zarr m1/tree.zarr >/dev/null && diff -rq -x zarr.json m1/flat.zarr m1/c7.zarr >/dev/null &&
  echo "flat, tree and chain: the same bytes (but the root zarr.json, which names the inputs)" || echo "flat, tree and chain DIFFER"
du -sb outp/mosaic.zarr | awk '{print "mosaic:", $1/1e6, "MB"}'
echo "== one 200 000-pulse line: whole against four shards"
sim long.fwcap 200000 "[-4000.0, 0.0]" "[4000.0, 0.0]"
for r in 1 2 3; do
  w=$(t "$F" replay long.fwcap --out whole$r --no-progress --set output.waveforms=false --set output.las=false)
  ws=0
  for i in 1 2 3 4; do
    x=$(t "$F" replay long.fwcap --out s$r$i --no-progress --shard $i/4 --set output.waveforms=false --set output.las=false)
    ws=$(echo "$ws + $x" | bc)
  done
  echo "run $r: whole $w s, four shards one after another $ws s"
done
"$F" merge --no-progress --out shards.zarr s11/voxels.zarr s12/voxels.zarr s13/voxels.zarr s14/voxels.zarr >/dev/null
du -sb whole1/voxels.zarr | awk '{print "whole line store:", $1/1e6, "MB"}'
s=$(date +%s.%N); "$F" campaign plan c11.toml >/dev/null 2>&1; e=$(date +%s.%N)
echo "campaign plan (opens every capture, georeferences the first pulse): $(echo "$e - $s" | bc) s"
