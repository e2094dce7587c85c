"""Opens a finished voxel store as a user would and checks that its arrays fit its tiles.

Usage: check_fitted_store.py STORE
Warnings are errors: `xr.open_zarr(STORE)`, with no `consolidated=` argument, must open the store
from its consolidated metadata without one. Checks, against the tile records the store keeps
(fwlidar_state/tiles/TX_TY), that the data arrays span exactly the bounding box of those tiles,
that the x and y coordinates are the centres of those tiles' voxels, that the consolidated
metadata lists every array, that zarr-python reads every recorded tile from the chunk the
attributes place it in, and that the cells outside the recorded tiles are empty. Prints one JSON
line: tiles, shape, sample_count and pulse_count sums, first and last coordinates.
"""
import json
import os
import sys
import warnings

import numpy as np
import xarray as xr
import zarr

warnings.simplefilter("error")
root = sys.argv[1]

ds = xr.open_zarr(root)
attrs = ds.attrs
span = attrs["fwlidar"]["arrays"]
assert span["fitted"] is True, span
t = attrs["tile_columns"]
vs = attrs["voxel_size_m"]
tm = attrs["tile_size_m"]
anchor = attrs["tile_grid_origin_m"]

tiles = []
records = os.path.join(root, "fwlidar_state", "tiles")
for name in sorted(os.listdir(records)) if os.path.isdir(records) else []:
    tx, ty = (int(v) for v in name.split("_"))
    tiles.append((tx, ty))
xs_t = [tx for tx, _ in tiles]
ys_t = [ty for _, ty in tiles]
if tiles:
    tmin = [min(xs_t), min(ys_t)]
    n = [max(xs_t) - tmin[0] + 1, max(ys_t) - tmin[1] + 1]
else:
    tmin, n = span["tile_min"], [0, 0]
assert span["tile_min"] == tmin and span["tiles"] == n, (span, tmin, n)

shape = ds.sample_count.shape
assert ds.sample_count.dims == ("z", "y", "x")
assert shape[1:] == (n[1] * t, n[0] * t), (shape, n)
for a in ("intensity_sum", "intensity_max", "pulse_count"):
    assert ds[a].shape == shape, (a, ds[a].shape)

# Coordinates: voxel centres of the tiles from the south-west one, evenly spaced.
x = ds.x.values
y = ds.y.values
west = anchor[0] + tmin[0] * tm[0]
south = anchor[1] + tmin[1] * tm[1]
assert np.allclose(x, west + (np.arange(len(x)) + 0.5) * vs[0], rtol=0, atol=1e-6), x[:3]
assert np.allclose(y, south + (np.arange(len(y)) + 0.5) * vs[1], rtol=0, atol=1e-6), y[:3]
assert attrs["origin_m"][:2] == [west, south], attrs["origin_m"]

# zarr-python: the consolidated metadata names every array; each recorded tile is the chunk at
# its place, and the rest is empty.
g = zarr.open_group(root, mode="r", use_consolidated=True)
assert g.metadata.consolidated_metadata is not None
names = set(g.metadata.consolidated_metadata.metadata)
for a in ("intensity_sum", "sample_count", "intensity_max", "pulse_count", "x", "y", "z", "spatial_ref"):
    assert a in names, (a, names)
counts = np.asarray(g["sample_count"][:])
pulses = np.asarray(g["pulse_count"][:])
covered = np.zeros(counts.shape[1:], dtype=bool)
per_tile = {}
for tx, ty in tiles:
    row, col = ty - tmin[1], tx - tmin[0]
    # Every height chunk of the tile (absent ones read as fill).
    block = np.asarray(g["sample_count"].blocks[:, row, col])
    window = counts[:, row * t:(row + 1) * t, col * t:(col + 1) * t]
    assert np.array_equal(block, window), (tx, ty)
    covered[row * t:(row + 1) * t, col * t:(col + 1) * t] = True
    per_tile[f"{tx}_{ty}"] = int(block.sum())
assert counts[:, ~covered].sum() == 0 and pulses[:, ~covered].sum() == 0

print(
    json.dumps(
        {
            "tiles": len(tiles),
            "shape": list(shape),
            "samples": int(ds.sample_count.sum()),
            "pulses": int(ds.pulse_count.sum()),
            "per_tile": per_tile,
            "x": [float(x[0]), float(x[-1])] if len(x) else [],
            "y": [float(y[0]), float(y[-1])] if len(y) else [],
        }
    )
)
