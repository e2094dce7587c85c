"""Reads every tile a killed run committed, with zarr-python (a real client).

Usage: check_killed_store.py STORE
Each tile whose record is committed (not pending) must decode in all four data arrays and hold
samples; a killed run's arrays span the whole extent (the run had not fitted them yet), and each
tile's chunk is where the recorded span (attributes fwlidar.arrays) puts it. Prints the number of
tiles and samples read as JSON; exits non-zero otherwise.
"""
import json
import os
import sys

import numpy as np
import zarr

root = sys.argv[1]
g = zarr.open_group(root, mode="r")
grid = g.attrs["fwlidar"]["grid"]
span = g.attrs["fwlidar"]["arrays"]
assert not span["fitted"], span
assert span["tile_min"] == grid["tile_min"] and span["tiles"] == grid["tiles"], (span, grid)
tmin = span["tile_min"]
records = os.path.join(root, "fwlidar_state", "tiles")
tiles = samples = 0
for name in sorted(os.listdir(records)):
    if name.endswith(".partial"):
        continue
    with open(os.path.join(records, name)) as f:
        rec = json.load(f)
    if rec.get("pending"):
        continue
    tx, ty = (int(v) for v in name.split("_"))
    row, col = ty - tmin[1], tx - tmin[0]
    blocks = {a: np.asarray(g[a].blocks[0, row, col]) for a in
              ("intensity_sum", "sample_count", "intensity_max", "pulse_count")}
    n = int(blocks["sample_count"].sum())
    assert n > 0, f"tile {name} has no samples"
    assert np.all(np.isfinite(blocks["intensity_max"][blocks["sample_count"] > 0]))
    tiles += 1
    samples += n
assert tiles > 0, "no committed tile"
print(json.dumps({"tiles": tiles, "samples": samples}))
