"""Reads fwlidar's voxels.zarr with zarr-python and xarray (real clients) and checks values.

Usage: check_voxels.py OUT_DIR volts|calibrated
Checks, against the replay's own returns.csv, waveforms.csv, pulses.csv and summary.json:
opening with no arguments and no warning (consolidated metadata), arrays fitted to the tiles
written, named dimensions and coordinates, CRS attributes, the sums and counts of the deposited bins,
that every return lies in an occupied voxel, pulse counts per level, and the two layers of the
two-layer scene at their heights. Prints one JSON line of figures; exits non-zero on failure.
"""
import csv
import json
import math
import sys
import warnings

import numpy as np
import xarray as xr
import zarr

out = sys.argv[1]
mode = sys.argv[2]
warnings.simplefilter("error")  # a warning from the readers is a failure

with open(f"{out}/summary.json") as f:
    summary = json.load(f)
dep = summary["sinks"]["voxels"]["deposits"]

# As a user opens it: consolidated metadata, no argument, no warning.
ds = xr.open_zarr(f"{out}/voxels.zarr")
# The arrays span the tiles written (fitted when the run ended), not the whole extent.
span = ds.attrs["fwlidar"]["arrays"]
assert span["fitted"] is True, span
t = ds.attrs["tile_columns"]
assert ds.sample_count.shape == (ds.sizes["z"], span["tiles"][1] * t, span["tiles"][0] * t)
# Everything deposited is in the arrays: the whole store sums to the deposits.
assert int(ds.sample_count.sum()) == dep["bins_deposited"], int(ds.sample_count.sum())
assert ds.intensity_sum.dims == ("z", "y", "x"), ds.intensity_sum.dims
for c in ("x", "y", "z"):
    assert c in ds.coords, c
assert ds.x.attrs["standard_name"] == "projection_x_coordinate"
assert ds.x.attrs["units"] == "m"
assert ds.attrs["epsg"] == 32736, ds.attrs["epsg"]
assert "UTM zone 36S" in ds.attrs["crs_wkt"], ds.attrs["crs_wkt"][:80]
assert "UTM zone 36S" in ds.spatial_ref.attrs["crs_wkt"]
assert ds.intensity_sum.attrs["grid_mapping"] == "spatial_ref"
assert list(ds.attrs["voxel_size_m"]) == [0.5, 0.5, 0.15]
assert "[voxels]" in ds.attrs["configuration"]
vs = ds.attrs["voxel_size_m"]
# The coordinates are voxel centres on the tile grid anchored at the CRS origin.
assert abs((float(ds.x[0]) - vs[0] / 2) / vs[0] - round((float(ds.x[0]) - vs[0] / 2) / vs[0])) < 1e-6

# Returns: every one lies in a voxel with samples (the window around them).
with open(f"{out}/returns.csv") as f:
    returns = list(csv.DictReader(f))
xs = np.array([float(r["x"]) for r in returns])
ys = np.array([float(r["y"]) for r in returns])
zs = np.array([float(r["z"]) for r in returns])
pad = 2.0
win = ds.sel(
    x=slice(xs.min() - pad, xs.max() + pad), y=slice(ys.min() - pad, ys.max() + pad)
).load()
counts = win.sample_count.values
sums = win.intensity_sum.values  # decoded with scale_factor: volts
assert counts.sum() == dep["bins_deposited"], (int(counts.sum()), dep["bins_deposited"])
# Untouched voxels: zero sums and counts (not masked), NaN maxima.
assert np.all(sums[counts == 0] == 0)
assert np.all(np.isnan(win.intensity_max.values[counts == 0]))

xi = np.floor((xs - float(win.x[0]) + vs[0] / 2) / vs[0]).astype(int)
yi = np.floor((ys - float(win.y[0]) + vs[1] / 2) / vs[1]).astype(int)
zi = np.floor((zs - float(win.z[0]) + vs[2] / 2) / vs[2]).astype(int)
inside = (zi >= 0) & (zi < counts.shape[0])
assert np.all(counts[zi[inside], yi[inside], xi[inside]] > 0), "a return in an empty voxel"

# The sum of all deposited intensity equals the sum of the deposited bins of waveforms.csv:
# every pulse deposits the same leading bins of its return segment (nadir, flat window).
with open(f"{out}/pulses.csv") as f:
    pulses = list(csv.DictReader(f))
per_pulse = dep["bins_deposited"] // dep["pulses_deposited"]
assert per_pulse * dep["pulses_deposited"] == dep["bins_deposited"]
expected = 0.0
with open(f"{out}/waveforms.csv") as f:
    for meta, line in zip(pulses, f):
        if meta["kind"] == "return":
            expected += sum(float(v) for v in line.split(",")[:per_pulse])
total = float(sums.sum())
quantum = ds.attrs["intensity_quantum"]
assert mode != "volts" or abs(total - expected) <= 1e-6 * abs(expected) + quantum * dep["bins_deposited"], (
    total,
    expected,
)

# A vertical beam passes every level of its window once: per level, the pulse counts over all
# columns add up to the number of pulses (levels fully inside the recorded window).
passes = win.pulse_count.values.sum(axis=(1, 2))
full = passes[(win.z.values > -4.5) & (win.z.values < 24.5)]
assert np.all(full == dep["pulses_deposited"]), full

# The scene's two layers: ground at 0 m and a canopy layer at 15 m (plus the +0.27 m of
# refraction the vacuum simulator leaves, docs/navigation.md). Mean intensity per level:
profile = sums.sum(axis=(1, 2)) / np.maximum(counts.sum(axis=(1, 2)), 1)
z = win.z.values
low = profile[z < 7.5]
high = profile[z >= 7.5]
z_ground = z[z < 7.5][np.argmax(low)]
z_canopy = z[z >= 7.5][np.argmax(high)]
assert abs(z_ground - 0.27) < 0.5, z_ground
assert abs(z_canopy - 15.27) < 0.5, z_canopy

# zarr-python directly: a shard file per tile (its columns over one height chunk) or per group of
# tiles (G x G tiles over K height chunks, whose inner chunk is a tile's height chunk, itself a
# shard: `[voxels] shard_tiles`, the default); the innermost chunks are 8 x 8 columns (or fewer: a
# divisor of the tile's columns).
g = zarr.open_group(f"{out}/voxels.zarr", mode="r")
a = g["sample_count"]
t = ds.attrs["tile_columns"]
levels = ds.attrs["fwlidar"]["grid"]["chunk_levels"]
assert a.shards is not None, a.metadata.codecs
assert a.shards[1] == a.shards[2] and a.shards[1] % t == 0, a.shards
if a.shards[1] == t and a.shards[0] == levels:
    inner = a.chunks
else:
    assert a.chunks == (levels, t, t) and a.shards[0] % levels == 0, (a.shards, a.chunks)
    (nested,) = a.metadata.codecs[0].codecs
    inner = nested.chunk_shape
assert inner[0] == levels and inner[1] == inner[2] and t % inner[1] == 0, inner
assert inner[1] == min(8, t) or 8 % inner[1] == 0, inner
print(
    json.dumps(
        {
            "bins": int(counts.sum()),
            "sum_v": total,
            "expected_v": expected,
            "ground_z": float(z_ground),
            "canopy_z": float(z_canopy),
            "zarr": zarr.__version__,
            "xarray": xr.__version__,
        }
    )
)
