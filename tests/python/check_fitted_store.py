"""Opens a finished voxel store as a user would and checks that its arrays fit its tiles.

Usage: check_fitted_store.py STORE
Warnings are errors: `xr.open_zarr(STORE)`, with no `consolidated=` argument, must open the store
from its consolidated metadata without one. Checks, against the tiles the store has committed
(its tile records or its journal, `fwstore.py`), that the data arrays span exactly the bounding
box of those tiles (its low corner widened down to a whole shard file's group of tiles when tiles
are grouped, counted from the grid's first tile),
that the x and y coordinates are the centres of those tiles' voxels, that the consolidated
metadata lists every array, that zarr-python reads every recorded tile from the chunk the
attributes place it in, and that the cells outside the recorded tiles are empty (arrays too large to
read whole, tiles strewn over a wide area as in a spaceborne granule: that every stored chunk
file is a shard holding a recorded tile). Prints one JSON
line: tiles, shape, sample_count and pulse_count sums, first and last coordinates.
"""
import json
import os
import sys
import warnings

import numpy as np
import xarray as xr
import zarr

from fwstore import committed_tiles, group_tiles

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

tiles = sorted(committed_tiles(root))
group = group_tiles(zarr.open_array(os.path.join(root, "sample_count"), mode="r"), t)
first = attrs["fwlidar"]["grid"]["tile_min"]
xs_t = [tx for tx, _ in tiles]
ys_t = [ty for _, ty in tiles]
if tiles:
    low = [min(xs_t), min(ys_t)]
    tmin = [low[a] - (low[a] - first[a]) % group for a in range(2)]
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

# zarr-python: the consolidated metadata names every array; each recorded tile, read on its own
# (through the shard index), is the window at its place, and the rest is empty.
g = zarr.open_group(root, mode="r", use_consolidated=True)
assert g.metadata.consolidated_metadata is not None
names = set(g.metadata.consolidated_metadata.metadata)
for a in ("intensity_sum", "sample_count", "intensity_max", "pulse_count", "x", "y", "z", "spatial_ref"):
    assert a in names, (a, names)
def window(tx, ty):
    row, col = ty - tmin[1], tx - tmin[0]
    return (slice(None), slice(row * t, (row + 1) * t), slice(col * t, (col + 1) * t))


per_tile = {}
samples = pulses_sum = 0
for tx, ty in tiles:
    # Every height chunk of the tile (absent ones read as fill), read on its own.
    block = np.asarray(g["sample_count"][window(tx, ty)])
    per_tile[f"{tx}_{ty}"] = int(block.sum())
    samples += int(block.sum())
    pulses_sum += int(np.asarray(g["pulse_count"][window(tx, ty)]).sum())
if np.prod(shape) <= 2**27:
    # Small enough to read whole: the tiles' windows are what a whole read holds there, and
    # the rest is empty.
    counts = np.asarray(g["sample_count"][:])
    pulses = np.asarray(g["pulse_count"][:])
    covered = np.zeros(counts.shape[1:], dtype=bool)
    for tx, ty in tiles:
        w = window(tx, ty)
        assert int(counts[w].sum()) == per_tile[f"{tx}_{ty}"], (tx, ty)
        covered[w[1:]] = True
    assert counts[:, ~covered].sum() == 0 and pulses[:, ~covered].sum() == 0
    assert int(ds.sample_count.sum()) == samples and int(ds.pulse_count.sum()) == pulses_sum
else:
    # Too large to read whole (tiles strewn over a wide area: a spaceborne granule): every
    # stored chunk file is a shard that holds a committed tile.
    import glob

    shard = g["sample_count"].shards or g["sample_count"].chunks
    held = {((ty - tmin[1]) * t // shard[1], (tx - tmin[0]) * t // shard[2]) for tx, ty in tiles}
    for a in ("intensity_sum", "sample_count", "intensity_max", "pulse_count"):
        for f in glob.glob(os.path.join(root, a, "c", "*", "*", "*")):
            _, r, c = (int(v) for v in f.split(os.sep)[-3:])
            assert (r, c) in held, (a, f)

print(
    json.dumps(
        {
            "tiles": len(tiles),
            "shape": list(shape),
            "samples": samples,
            "pulses": pulses_sum,
            "per_tile": per_tile,
            "x": [float(x[0]), float(x[-1])] if len(x) else [],
            "y": [float(y[0]), float(y[-1])] if len(y) else [],
        }
    )
)
