"""Reads the daemon's /metrics text (stdin) with the Prometheus project's own parser
(prometheus_client) and checks what a Prometheus server would rely on: every family parses with
its declared type, histograms are cumulative and end at +Inf with _count equal to the +Inf
bucket, counters are non-negative. Prints a JSON summary for the Rust test to compare."""

import json
import math
import sys

from prometheus_client.parser import text_string_to_metric_families

text = sys.stdin.read()
families = {f.name: f for f in text_string_to_metric_families(text)}
summary = {"families": {}, "values": {}}
for name, f in families.items():
    summary["families"][name] = f.type
    if f.type == "histogram":
        by_labels = {}
        for s in f.samples:
            key = tuple(sorted((k, v) for k, v in s.labels.items() if k != "le"))
            by_labels.setdefault(key, {"buckets": [], "count": None})
            if s.name.endswith("_bucket"):
                by_labels[key]["buckets"].append((float(s.labels["le"]), s.value))
            elif s.name.endswith("_count"):
                by_labels[key]["count"] = s.value
        for key, h in by_labels.items():
            b = sorted(h["buckets"])
            assert b, f"{name}{key}: no buckets"
            assert math.isinf(b[-1][0]), f"{name}{key}: last bucket is not +Inf"
            counts = [c for _, c in b]
            assert counts == sorted(counts), f"{name}{key}: buckets not cumulative {counts}"
            assert h["count"] == counts[-1], f"{name}{key}: _count {h['count']} != +Inf {counts[-1]}"
    for s in f.samples:
        if f.type == "counter":
            assert s.value >= 0, f"{s.name}: negative counter {s.value}"
        if not s.labels:
            summary["values"][s.name] = s.value
print(json.dumps(summary))
