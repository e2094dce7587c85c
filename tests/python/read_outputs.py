"""Reads a replay output folder the way a scientist would, with numpy, and checks it.

Usage: python read_outputs.py OUT_DIR
Exits non-zero with a message on the first inconsistency.
"""
import json
import sys
from pathlib import Path

import numpy as np


def main(out: Path) -> None:
    pulses = np.genfromtxt(out / "pulses.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    expected = ["row", "pulse_id", "gps_time", "segment", "kind", "channel", "start_ns",
                "sample_ns", "n_samples", "baseline_v", "noise_v"]
    assert list(pulses.dtype.names) == expected, pulses.dtype.names
    waves = [np.array(line.split(","), dtype=np.float64)
             for line in (out / "waveforms.csv").read_text().splitlines()]
    assert len(waves) == len(pulses), (len(waves), len(pulses))
    assert np.array_equal(pulses["row"], np.arange(len(pulses)))
    lengths = np.array([len(w) for w in waves])
    assert np.array_equal(lengths, pulses["n_samples"]), "n_samples disagrees with waveforms.csv"
    assert all(np.all(np.isfinite(w)) for w in waves), "non-finite sample"
    summary = json.loads((out / "summary.json").read_text())
    segments_per_pulse = len(pulses) / summary["pulses_out"]
    assert segments_per_pulse == 2.0, segments_per_pulse
    kinds = set(pulses["kind"].tolist())
    assert kinds == {"outgoing", "return"}, kinds
    ret = np.stack([w for w, k in zip(waves, pulses["kind"]) if k == "return"])
    mean = ret.mean(axis=0)
    print(f"numpy {np.__version__}: {len(pulses)} segments of {summary['pulses_out']} pulses read; "
          f"mean return peak at bin {int(np.argmax(mean))}, max {mean.max():.2f} V")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
