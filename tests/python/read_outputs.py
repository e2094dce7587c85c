"""Reads replay output folders the way a scientist would, with numpy, laspy and pyproj, and
checks them.

Usage: python read_outputs.py DEFAULT_OUT CSV_OUT
  DEFAULT_OUT: `fwlidar replay` with the embedded configuration (the README's main job);
  CSV_OUT: the same replay with waveform_format = "csv" and returns = true.
Exits non-zero with a message on the first inconsistency.
"""
import json
import sys
from pathlib import Path

import laspy
import numpy as np


def read_csv_waveforms(out: Path):
    pulses = np.genfromtxt(out / "pulses.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    expected = ["row", "pulse_id", "gps_time", "segment", "kind", "channel", "start_ns",
                "sample_ns", "n_samples", "baseline_v", "noise_v"]
    assert list(pulses.dtype.names) == expected, pulses.dtype.names
    waves = [np.array(line.split(","), dtype=np.float32)
             for line in (out / "waveforms.csv").read_text().splitlines()]
    assert len(waves) == len(pulses), (len(waves), len(pulses))
    assert np.array_equal(pulses["row"], np.arange(len(pulses)))
    return pulses, waves


def main(default: Path, csv: Path) -> None:
    # The default writes binary outputs only: no text beside them.
    names = sorted(p.name for p in default.iterdir())
    for text in ("pulses.csv", "waveforms.csv", "returns.csv"):
        assert text not in names, f"{text} written without being asked for: {names}"
    summary = json.loads((default / "summary.json").read_text())

    # Processed waveforms: numpy reads them directly.
    w = np.load(default / "waveforms.npy", mmap_mode="r")
    ix = np.load(default / "waveform_index.npy")
    assert w.dtype == np.float32 and w.ndim == 1, (w.dtype, w.shape)
    assert list(ix.dtype.names) == ["pulse_id", "gps_time", "segment", "kind", "channel",
                                    "start_ns", "sample_ns", "n_samples", "offset",
                                    "baseline_v", "noise_v"], ix.dtype.names
    assert np.array_equal(ix["offset"][1:], np.cumsum(ix["n_samples"])[:-1].astype(np.uint64))
    assert int(ix["offset"][-1]) + int(ix["n_samples"][-1]) == w.shape[0]
    assert np.all(np.isfinite(w)), "non-finite sample"
    assert len(ix) / summary["pulses_out"] == 2.0, (len(ix), summary["pulses_out"])
    assert set(ix["kind"].tolist()) == {0, 1}

    # ... and hold exactly what the CSV output of the same run holds.
    pulses, waves = read_csv_waveforms(csv)
    assert len(waves) == len(ix), (len(waves), len(ix))
    for name in ("pulse_id", "segment", "channel", "n_samples"):
        assert np.array_equal(ix[name], pulses[name]), name
    assert np.array_equal(ix["kind"], (pulses["kind"] == "return").astype(np.uint8))
    assert np.allclose(ix["gps_time"], pulses["gps_time"], rtol=0, atol=1e-9)
    for i, wave in enumerate(waves):
        seg = w[int(ix["offset"][i]): int(ix["offset"][i]) + int(ix["n_samples"][i])]
        assert np.array_equal(seg, wave), f"segment {i} differs between waveforms.npy and .csv"

    # Returns: LAS 1.4 that laspy reads, with its CRS (pyproj) and extra dimensions, at the
    # positions returns.csv gives.
    las = laspy.read(default / "returns.las")
    assert las.header.version.major == 1 and las.header.version.minor == 4
    assert las.header.point_format.id == 6, las.header.point_format.id
    assert las.header.point_count == summary["sinks"]["las"]["points"] > 0
    crs = las.header.parse_crs()
    assert crs is not None and crs.to_epsg() == 32736, crs
    extras = list(las.point_format.extra_dimension_names)
    assert extras == ["amplitude", "width", "backscatter", "residual"], extras
    ret = np.genfromtxt(csv / "returns.csv", delimiter=",", names=True)
    assert len(ret) == las.header.point_count, (len(ret), las.header.point_count)
    order = np.lexsort((ret["time_ns"], ret["gps_time"]))
    got = np.stack([las.x, las.y, las.z], axis=1)
    want = np.stack([ret["x"], ret["y"], ret["z"]], axis=1)[order]
    got = got[np.lexsort((np.asarray(las.z), np.asarray(las.gps_time)))]
    want = want[np.lexsort((want[:, 2], ret["gps_time"][order]))]
    assert np.abs(got - want).max() <= 0.0011, np.abs(got - want).max()
    assert np.allclose(np.sort(las.amplitude), np.sort(ret["amplitude_v"]), rtol=1e-6, atol=1e-6)

    mean = np.stack([w[int(o): int(o) + int(n)] for o, n, k
                     in zip(ix["offset"], ix["n_samples"], ix["kind"]) if k == 1]).mean(axis=0)
    print(f"numpy {np.__version__}, laspy {laspy.__version__}: {len(ix)} segments of "
          f"{summary['pulses_out']} pulses read; mean return peak at bin {int(np.argmax(mean))}, "
          f"max {mean.max():.2f} V; returns.las {las.header.point_count} points in "
          f"EPSG:{crs.to_epsg()}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
