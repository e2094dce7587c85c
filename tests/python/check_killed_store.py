"""Reads every tile a killed run committed, with zarr-python (a real client).

Usage: check_killed_store.py STORE
Each tile the store has committed (its tile record, or its journal line with its shards renamed
into place: `fwstore.py`) must decode in all four data arrays and hold samples; a killed run's arrays span the whole extent (the run had not fitted them yet), and each
tile's chunk is where the recorded span (attributes fwlidar.arrays) puts it. Prints the number of
tiles and samples read as JSON; exits non-zero otherwise.
"""
import json
import sys

import numpy as np
import zarr

from fwstore import committed_tiles

root = sys.argv[1]
g = zarr.open_group(root, mode="r")
grid = g.attrs["fwlidar"]["grid"]
span = g.attrs["fwlidar"]["arrays"]
assert not span["fitted"], span
assert span["tile_min"] == grid["tile_min"] and span["tiles"] == grid["tiles"], (span, grid)
tmin = span["tile_min"]
levels = g["sample_count"].chunks[0]  # a height chunk (the inner chunk when tiles are grouped)
tiles = samples = 0
for (tx, ty), rec in sorted(committed_tiles(root).items()):
    name = f"{tx}_{ty}"
    row, col = ty - tmin[1], tx - tmin[0]
    t = g["sample_count"].shape[1] // span["tiles"][1]
    kc = rec["chunks"][0] - span.get("level_chunk_min", 0)
    window = (slice(kc * levels, (kc + 1) * levels), slice(row * t, (row + 1) * t),
              slice(col * t, (col + 1) * t))
    blocks = {a: np.asarray(g[a][window]) for a in
              ("intensity_sum", "sample_count", "intensity_max", "pulse_count")}
    n = int(blocks["sample_count"].sum())
    assert n > 0, f"tile {name} has no samples"
    assert np.all(np.isfinite(blocks["intensity_max"][blocks["sample_count"] > 0]))
    tiles += 1
    samples += n
assert tiles > 0, "no committed tile"
print(json.dumps({"tiles": tiles, "samples": samples}))
