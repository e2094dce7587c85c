"""Tree heights and crown thickness of replays of the tree plot against the scene's trees.

Usage: tree_heights.py [--extent SIDE_M] TREES.csv LABEL=RUN_DIR [LABEL=RUN_DIR ...] > result.json

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
Only trees whose top is seen are scored (`visible`): the stem inside the scanned area (the
first rows of `--extent` below) and the apex not under a taller neighbour's crown; the others are
listed with `visible: false`.
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


def crown_top_at(o, d):
    """Height of tree o's crown envelope top at horizontal distance d from its stem (NaN outside)."""
    if d >= o.crown_radius_m:
        return float("nan")
    rr = d / o.crown_radius_m
    if o.crown_shape == "cone":
        return o.height_m - (o.height_m - o.crown_base_m) * rr
    if o.crown_shape == "cylinder":
        return o.height_m
    a = 0.5 * (o.height_m - o.crown_base_m)
    return o.crown_base_m + a + a * np.sqrt(1.0 - rr * rr)


def visible(trees, t, half_extent):
    if max(abs(t.scene_x), abs(t.scene_y)) > half_extent:
        return False
    for o in trees.itertuples():
        if o.tree_id == t.tree_id:
            continue
        top = crown_top_at(o, np.hypot(o.scene_x - t.scene_x, o.scene_y - t.scene_y))
        if top == top and top > t.height_m:
            return False
    return True


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


def finite_or_null(v):
    """NaN (no pulse near a tree, no crown pulses) as JSON null."""
    if isinstance(v, dict):
        return {k: finite_or_null(x) for k, x in v.items()}
    if isinstance(v, list):
        return [finite_or_null(x) for x in v]
    if isinstance(v, float) and v != v:
        return None
    return v


def main():
    args = sys.argv[1:]
    half_extent = float("inf")
    if args[0] == "--extent":
        # Half the side of the scanned square, m in the scene frame, less a margin of 0.5 m.
        half_extent = float(args[1]) / 2.0 - 0.5
        args = args[2:]
    trees = pd.read_csv(args[0])
    seen = {t.tree_id: visible(trees, t, half_extent) for t in trees.itertuples()}
    out = {}
    for arg in args[1:]:
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
                    "visible": bool(seen[t.tree_id]),
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
            return float(np.nanmedian([abs(x[key]) for x in rows if x["visible"]]))

        out[label] = {
            "trees": rows,
            "median_abs_chm_m": med_abs("chm_error_m"),
            "median_abs_rectified_m": med_abs("rectified_error_m"),
            "median_abs_unrectified_m": med_abs("unrectified_error_m"),
            "pulses_ok": int(len(m)),
            "trees_scored": int(sum(x["visible"] for x in rows)),
        }
    json.dump(finite_or_null(out), sys.stdout, indent=1)


if __name__ == "__main__":
    main()
