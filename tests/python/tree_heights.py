"""Tree heights and crown thickness of replays of the tree plot against the scene's trees.

Usage: tree_heights.py TREES.csv LABEL=RUN_DIR [LABEL=RUN_DIR ...] > result.json

TREES.csv is `fwlidar simulate`'s `<stem>.trees.csv` (every tree's stem position in the
replay's UTM, height, crown shape, base and radius). Each RUN_DIR is a replay output with
`pulse_metrics.csv` and `rasters/chm.vrt`.

Per tree and run:
- `chm`: the highest canopy height model cell (read by rasterio) whose centre lies within
  `RADIUS_M` of the stem, minus the tree's height (m);
- `rectified` / `unrectified`: the same from pulse_metrics.csv, the pulses placed at their
  canopy top (top_x, top_y: where the beam met the crown) or at their ground point (x, y);
- crown thickness: the median `crown_thickness_m` of the pulses whose canopy top lies within
  half the crown radius of the stem, and the crown envelope's median vertical extent at those
  pulses (ellipsoid 2a sqrt(1 - r^2/R^2), cone (H - base)(1 - r/R)).
Prints one JSON object: {label: {"trees": [...], "median_abs_chm": ..., ...}}.
"""
import json
import sys

import numpy as np
import pandas as pd
import rasterio

RADIUS_M = 1.0


def envelope_thickness(t, r):
    rr = np.clip(r / t.crown_radius_m, 0.0, 1.0)
    depth = t.height_m - t.crown_base_m
    if t.crown_shape == "cone":
        return depth * (1.0 - rr)
    if t.crown_shape == "cylinder":
        return depth * np.ones_like(rr)
    return depth * np.sqrt(1.0 - rr * rr)


def chm_cells(run):
    with rasterio.open(f"{run}/rasters/chm.vrt") as r:
        a = r.read(1, masked=True)
        tr = r.transform
    rows, cols = np.nonzero(~np.ma.getmaskarray(a))
    xs, ys = tr * (cols + 0.5, rows + 0.5)
    return np.asarray(xs), np.asarray(ys), np.asarray(a[rows, cols].data, dtype=float)


def highest_within(xs, ys, v, x, y):
    sel = np.hypot(xs - x, ys - y) <= RADIUS_M
    return float(v[sel].max()) if sel.any() else float("nan")


def main():
    trees = pd.read_csv(sys.argv[1])
    out = {}
    for arg in sys.argv[2:]:
        label, run = arg.split("=", 1)
        m = pd.read_csv(f"{run}/pulse_metrics.csv")
        m = m[m.status == "ok"]
        cx, cy, cv = chm_cells(run)
        h = m.canopy_height.to_numpy(float)
        rows = []
        for t in trees.itertuples():
            chm = highest_within(cx, cy, cv, t.x, t.y)
            rect = highest_within(m.top_x.to_numpy(float), m.top_y.to_numpy(float), h, t.x, t.y)
            unrect = highest_within(m.x.to_numpy(float), m.y.to_numpy(float), h, t.x, t.y)
            r = np.hypot(m.top_x - t.x, m.top_y - t.y).to_numpy(float)
            inner = r <= 0.5 * t.crown_radius_m
            ct = m.crown_thickness_m.to_numpy(float)[inner]
            env = envelope_thickness(t, r[inner])
            rows.append(
                {
                    "tree": int(t.tree_id),
                    "shape": t.crown_shape,
                    "leaf_area_density": float(t.leaf_area_density),
                    "height_m": float(t.height_m),
                    "chm_error_m": chm - t.height_m,
                    "rectified_error_m": rect - t.height_m,
                    "unrectified_error_m": unrect - t.height_m,
                    "crown_pulses": int(inner.sum()),
                    "crown_thickness_median_m": float(np.median(ct)) if len(ct) else float("nan"),
                    "crown_thickness_p10_m": float(np.percentile(ct, 10)) if len(ct) else float("nan"),
                    "crown_thickness_p90_m": float(np.percentile(ct, 90)) if len(ct) else float("nan"),
                    "envelope_thickness_median_m": float(np.median(env)) if len(env) else float("nan"),
                }
            )

        def med_abs(key):
            return float(np.nanmedian([abs(x[key]) for x in rows]))

        out[label] = {
            "trees": rows,
            "median_abs_chm_m": med_abs("chm_error_m"),
            "median_abs_rectified_m": med_abs("rectified_error_m"),
            "median_abs_unrectified_m": med_abs("unrectified_error_m"),
            "pulses_ok": int(len(m)),
        }
    json.dump(out, sys.stdout, indent=1)


if __name__ == "__main__":
    main()
