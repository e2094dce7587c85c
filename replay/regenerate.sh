#!/usr/bin/env bash
# Regenerates the replay samples from their scenes (deterministic: the same fwlidar version,
# scene and seed give the same bytes; tests/cli.rs and tests/scene_sim.rs check it).
# Usage: bash replay/regenerate.sh   (from the repository root)
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
bin=target/release/fwlidar
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# name, scene, extra arguments
while read -r name scene extra; do
    [ -z "$name" ] && continue
    # shellcheck disable=SC2086
    "$bin" simulate --scene "config/scenes/$scene" --out "$tmp/$name.fwcap" --no-progress \
        --no-truth-voxels $extra >/dev/null
    cp "$tmp/$name.fwcap" "replay/$name.fwcap"
    # Described scenes: the truth waveforms beside the capture.
    if [ -f "$tmp/$name.truth.fwcap" ]; then cp "$tmp/$name.truth.fwcap" "replay/$name.truth.fwcap"; fi
    ls -l "replay/$name.fwcap"
done <<'LIST'
two_layer two_layer.toml
tree_plot tree_plot.toml
grass_patches grass_patches.toml
survey_line survey_line.toml --pulses 6000
LIST
