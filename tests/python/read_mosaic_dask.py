"""Read a campaign mosaic lazily with xarray + dask and reduce it chunk by chunk.

Usage: read_mosaic_dask.py MOSAIC.zarr LINE.zarr... > result.json

Opens every store with `xarray.open_zarr` in dask chunks of one storage shard each (64 levels x
32 x 32 columns: a voxel tile's height chunk, 8 x 8 x 4 shards of them per dask chunk), checks
that nothing was read while opening (every variable is a dask array), then computes with dask's
threaded scheduler the total of `sample_count` of the mosaic and of each line store. Prints one
JSON object.
"""
import json
import sys
import time

import dask
import dask.array as da
import xarray as xr

mosaic, lines = sys.argv[1], sys.argv[2:]
CHUNKS = {"z": 256, "y": 256, "x": 256}


def totals(path):
    ds = xr.open_zarr(path, chunks=CHUNKS)
    lazy = all(isinstance(ds[v].data, da.Array) for v in ds.data_vars)
    return ds, lazy, ds["sample_count"].sum(dtype="int64")


t = time.perf_counter()
ds, lazy, s = totals(mosaic)
opened = time.perf_counter() - t
with dask.config.set(scheduler="threads"):
    t = time.perf_counter()
    (ms,) = dask.compute(s)
    seconds = time.perf_counter() - t
    line_s = []
    for path in lines:
        _, _, ls = totals(path)
        line_s.append(int(ls.compute()))
print(json.dumps({
    "lazy": bool(lazy),
    "npartitions": int(ds["sample_count"].data.npartitions),
    "chunksize": list(ds["sample_count"].data.chunksize),
    "open_seconds": opened,
    "compute_seconds": seconds,
    "mosaic_samples": int(ms),
    "line_samples": line_s,
    "dask": dask.__version__,
    "xarray": xr.__version__,
}))
