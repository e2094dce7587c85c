"""Reads a simulated scene's truth voxel grid (<stem>.truth/voxels.zarr) with xarray and zarr
(real clients) and prints what it holds: the level with the most energy (the ground) and the
highest level holding a noticeable share of a column's energy (the canopy top), metres.

Usage: check_truth_voxels.py STORE
"""
import json
import sys
import warnings

import numpy as np
import xarray as xr

warnings.simplefilter("error")
ds = xr.open_zarr(sys.argv[1])
assert ds.intensity_sum.dims == ("z", "y", "x"), ds.intensity_sum.dims
for c in ("x", "y", "z"):
    assert c in ds.coords, c
assert ds.attrs["epsg"] == 32736, ds.attrs["epsg"]
# The store spans the tiles the truth fell in; the plot lies within 60 m of their centre.
cx = (float(ds.x[0]) + float(ds.x[-1])) / 2
cy = (float(ds.y[0]) + float(ds.y[-1])) / 2
lo_y, hi_y = sorted([cy - 60, cy + 60])
if float(ds.y[0]) > float(ds.y[-1]):
    lo_y, hi_y = hi_y, lo_y
win = ds.sel(x=slice(cx - 60, cx + 60), y=slice(lo_y, hi_y)).load()
s = win.intensity_sum.fillna(0).values.astype(float)
n = win.sample_count.values
z = win.z.values
assert np.isfinite(s).all()
per_level = s.sum(axis=(1, 2))
ground = float(z[int(np.argmax(per_level))])
# Highest level where some column holds at least 2 % of that column's largest voxel.
col_max = s.max(axis=0)
share = np.divide(s, col_max, out=np.zeros_like(s), where=col_max > 0)
levels = np.where((share >= 0.02).any(axis=(1, 2)))[0]
top = float(z[levels.max()])
print(json.dumps({
    "ground_m": ground,
    "top_m": top,
    "samples": int(n.sum()),
    "total": float(s.sum()),
}))
