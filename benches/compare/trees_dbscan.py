"""scikit-learn's DBSCAN on the points fwlidar's DBSCAN is timed on (`benches/trees.rs`,
`trees/dbscan_scan_first`): target/trees_dbscan_points.npy and its eps / min_points.

Usage: trees_dbscan.py [REPEATS]   prints one JSON object (times in ms, clusters found)
"""
import json
import sys
import time

import numpy as np
from sklearn.cluster import DBSCAN

pts = np.load("target/trees_dbscan_points.npy")
par = json.load(open("target/trees_dbscan_points.json"))
n = int(sys.argv[1]) if len(sys.argv) > 1 else 30
times = []
labels = None
for _ in range(n):
    t = time.perf_counter()
    labels = DBSCAN(eps=par["eps"], min_samples=par["min_points"]).fit(pts).labels_
    times.append((time.perf_counter() - t) * 1e3)
times.sort()
print(json.dumps({
    "points": int(len(pts)),
    "clusters": int(labels.max() + 1),
    "noise": int((labels < 0).sum()),
    "mean_ms": float(np.mean(times)),
    "p50_ms": times[len(times) // 2],
    "max_ms": times[-1],
}))
