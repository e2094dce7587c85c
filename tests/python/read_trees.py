"""Open the products of `fwlidar trees` with the field's readers and check they agree.

Usage: read_trees.py OUT_DIR > result.json

- cylinders.ply with plyfile: vertex (x, y, z doubles) and face (vertex_indices, cylinder)
  elements; every cylinder of cylinders.csv has its 26 vertices and 36 faces, its two end
  centres at the start and end the table gives;
- clustered_points.las with laspy: the extra dimensions `cluster`, `tree`, `part` and `signal`;
  the number of points of each cylinder id equals the table's `points` column.
Prints one JSON object with what it read.
"""
import json
import sys

import laspy
import numpy as np
import pandas as pd
from plyfile import PlyData

out = sys.argv[1]
cyl = pd.read_csv(f"{out}/cylinders.csv")
ply = PlyData.read(f"{out}/cylinders.ply")
v = ply["vertex"]
f = ply["face"]
xyz = np.stack([v["x"], v["y"], v["z"]], axis=1)
per_v, per_f = 26, 36
assert len(xyz) == per_v * len(cyl), (len(xyz), len(cyl))
assert len(f.data) == per_f * len(cyl)
faces_of = np.asarray(f["cylinder"])
worst_end = 0.0
for k, row in enumerate(cyl.itertuples()):
    assert (faces_of[k * per_f:(k + 1) * per_f] == row.cylinder_id).all()
    start = np.array([row.start_x, row.start_y, row.start_z])
    axis = np.array([row.axis_x, row.axis_y, row.axis_z])
    end = start + row.length_m * axis
    c0, c1 = xyz[k * per_v + 24], xyz[k * per_v + 25]
    worst_end = max(worst_end, float(np.abs(c0 - start).max()), float(np.abs(c1 - end).max()))
    idx = [i for face in f["vertex_indices"][k * per_f:(k + 1) * per_f] for i in face]
    assert min(idx) >= k * per_v and max(idx) < (k + 1) * per_v
las = laspy.read(f"{out}/clustered_points.las")
names = set(las.point_format.extra_dimension_names)
assert {"cluster", "tree", "part", "signal"} <= names, names
cluster = np.asarray(las.cluster)
counts = {int(c): int(n) for c, n in zip(*np.unique(cluster[cluster >= 0], return_counts=True))}
mismatch = [int(r.cylinder_id) for r in cyl.itertuples() if counts.get(int(r.cylinder_id), 0) != r.points]
print(json.dumps({
    "cylinders": len(cyl),
    "branches": int((cyl.kind == "branch").sum()),
    "stems": int((cyl.kind == "stem").sum()),
    "ply_vertices": int(len(xyz)),
    "ply_faces": int(len(f.data)),
    "worst_end_centre_m": worst_end,
    "las_points": int(len(las.points)),
    "las_clustered": int((cluster >= 0).sum()),
    "point_count_mismatch": mismatch,
    "parts": {int(p): int(n) for p, n in zip(*np.unique(np.asarray(las.part), return_counts=True))},
}))
