"""Reads returns.las (point format 6) or returns.las + returns.wdp (format 9) with laspy (and the
.wdp with plain Python) and checks them against what the writer was given.

Usage: python read_las.py OUT_DIR EXPECTED.json
EXPECTED.json: {"wkt": str, "point_format": 6 | 9 (default 9), "las": file name (default
returns.las), "points": [{x, y, z, gps_time, return_number, number_of_returns, intensity,
amplitude, width, backscatter (null: no data), residual, and for format 9 location_ps,
xyz_t: [3], first_sample: [3], bits, spacing_ps, gain, offset, counts: [...]}, ...]} in file
order. Exits non-zero with a message on the first inconsistency.
"""
import json
import struct
import sys
from pathlib import Path

try:
    import laspy
    import numpy as np
except ImportError as e:  # the Rust test turns this into a failure naming the package
    print(f"MISSING PYTHON PACKAGE: {e.name} (install it into the venv: pip install {e.name})")
    sys.exit(3)


def main(out: Path, expected_path: Path) -> None:
    exp = json.loads(expected_path.read_text())
    pts = exp["points"]
    fmt = exp.get("point_format", 9)
    las_name = exp.get("las", "returns.las")
    wdp_path = out / (las_name[:-4] + ".wdp")
    las = laspy.read(out / las_name)
    h = las.header
    assert (h.version.major, h.version.minor) == (1, 4), h.version
    assert h.point_format.id == fmt, h.point_format.id
    assert h.point_count == len(pts) == len(las.points), (h.point_count, len(pts))
    assert h.global_encoding.waveform_data_packets_external == (fmt == 9), "global encoding bit 2"
    assert not h.global_encoding.waveform_data_packets_internal
    if fmt == 6:
        assert not wdp_path.exists(), "format 6 writes no .wdp"
    assert h.global_encoding.wkt, "global encoding bit 4"
    assert list(h.scales) == [0.001] * 3, h.scales

    # The CRS.
    wkts = [v for v in h.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)]
    if exp["wkt"] is None:
        assert not wkts, wkts
    else:
        assert len(wkts) == 1 and wkts[0].string == exp["wkt"], wkts
    # The Extra Bytes VLR: names, types, options, no-data, descriptions with units.
    eb = [v for v in h.vlrs if v.record_id == 4 and v.user_id == "LASF_Spec"]
    assert len(eb) == 1, eb
    structs = eb[0].extra_bytes_structs
    got = [(d.name.decode(), d.data_type, d.options) for d in structs]
    assert got == [("amplitude", 9, 0), ("width", 9, 0), ("backscatter", 9, 1), ("residual", 9, 0)], got
    assert structs[0].no_data is None, "amplitude declares no no-data"
    nd = float(np.asarray(structs[2].no_data).ravel()[0])
    assert nd == -9999.0, structs[2].no_data
    desc = [d.description.decode() for d in structs]
    assert desc[0].endswith("(V)") and desc[1].endswith("(ns)") and desc[3].endswith("(V)"), desc
    assert list(las.point_format.extra_dimension_names) == ["amplitude", "width", "backscatter", "residual"]
    if not pts and fmt == 6:
        assert list(h.mins) == [0, 0, 0] and list(h.maxs) == [0, 0, 0], (h.mins, h.maxs)
        print(f"laspy {laspy.__version__}: 0 points, format 6: all as written")
        return
    if not pts:
        wdp = wdp_path.read_bytes()
        assert len(wdp) == 60 and struct.unpack("<Q", wdp[20:28])[0] == 0, len(wdp)
        assert list(h.mins) == [0, 0, 0] and list(h.maxs) == [0, 0, 0], (h.mins, h.maxs)
        print(f"laspy {laspy.__version__}: 0 points, empty .wdp: all as written")
        return

    # Positions within 1 mm, times, return numbering.
    def col(name):
        return np.array([p[name] for p in pts], dtype=np.float64)

    for axis, name in ((las.x, "x"), (las.y, "y"), (las.z, "z")):
        err = np.abs(np.asarray(axis) - col(name)).max()
        assert err <= 0.0005 + 1e-9, f"{name} off by {err} m"
    assert np.array_equal(np.asarray(las.gps_time), col("gps_time")), "gps_time"
    assert np.array_equal(np.asarray(las.return_number), col("return_number")), "return_number"
    assert np.array_equal(np.asarray(las.number_of_returns), col("number_of_returns"))
    assert np.array_equal(np.asarray(las.intensity), col("intensity")), "intensity"
    # Header bounds hold the points.
    assert np.isclose(h.mins, [las.x.min(), las.y.min(), las.z.min()], atol=1e-9).all(), h.mins
    assert np.isclose(h.maxs, [las.x.max(), las.y.max(), las.z.max()], atol=1e-9).all(), h.maxs
    by_return = np.bincount(np.asarray(las.return_number), minlength=16)[1:16]
    assert list(h.number_of_points_by_return) == list(by_return), h.number_of_points_by_return

    # Extra bytes read back as named dimensions.
    assert np.allclose(np.asarray(las.amplitude), col("amplitude"), rtol=1e-6), "amplitude"
    assert np.allclose(np.asarray(las.width), col("width"), rtol=1e-6), "width"
    assert np.allclose(np.asarray(las.residual), col("residual"), rtol=1e-6), "residual"
    bs = np.asarray(las.backscatter, dtype=np.float64)
    want = np.array([np.nan if p["backscatter"] is None else p["backscatter"] for p in pts])
    nodata = np.isnan(want)
    assert np.all(bs[nodata] == -9999.0), "backscatter no-data"
    assert np.allclose(bs[~nodata], want[~nodata], rtol=1e-6), "backscatter"
    if fmt == 6:
        print(f"laspy {laspy.__version__}: {len(pts)} points of format 6, "
              f"{int(nodata.sum())} without backscatter: all as written")
        return

    # Wave packet fields and the parametric line.
    loc = np.asarray(las.return_point_wave_location, dtype=np.float64)
    assert np.allclose(loc, col("location_ps"), rtol=1e-6, atol=1e-3), "return point location"
    xyz_t = np.stack([np.asarray(las.x_t), np.asarray(las.y_t), np.asarray(las.z_t)], axis=1)
    assert np.allclose(xyz_t, np.array([p["xyz_t"] for p in pts]), rtol=1e-6), "x_t, y_t, z_t"
    # The convention: the packet's first sample lies at P + L * (x_t, y_t, z_t).
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
    first = xyz + loc[:, None] * xyz_t.astype(np.float64)
    err = np.abs(first - np.array([p["first_sample"] for p in pts])).max()
    assert err <= 0.001, f"first sample off by {err} m"

    descriptors = {
        v.record_id - 99: v.parsed_record
        for v in h.vlrs
        if isinstance(v, laspy.vlrs.known.WaveformPacketVlr)
    }
    assert 1 <= len(descriptors) <= 255, len(descriptors)
    wdp = wdp_path.read_bytes()
    reserved, user_id, record_id, length, _desc = struct.unpack("<H16sHQ32s", wdp[:60])
    assert user_id.rstrip(b"\0") == b"LASF_Spec" and record_id == 65535, (user_id, record_id)
    assert length == len(wdp) - 60, (length, len(wdp))

    index = np.asarray(las.wavepacket_index)
    offset = np.asarray(las.wavepacket_offset)
    size = np.asarray(las.wavepacket_size)
    packets = set()
    for i, p in enumerate(pts):
        d = descriptors[int(index[i])]
        assert d.bits_per_sample == p["bits"], (i, d.bits_per_sample)
        assert d.waveform_compression_type == 0
        assert d.number_of_samples == len(p["counts"]), (i, d.number_of_samples)
        assert d.temporal_sample_spacing == p["spacing_ps"], (i, d.temporal_sample_spacing)
        assert d.digitizer_gain == p["gain"] and d.digitizer_offset == p["offset"], i
        nbytes = len(p["counts"]) * p["bits"] // 8
        assert size[i] == nbytes, (i, size[i], nbytes)
        o = int(offset[i])
        assert 60 <= o and o + nbytes <= len(wdp), (i, o)
        dtype = "<u1" if p["bits"] == 8 else "<u2"
        counts = np.frombuffer(wdp[o:o + nbytes], dtype=dtype)
        assert np.array_equal(counts, np.array(p["counts"])), f"point {i}: waveform bytes differ"
        # The first sample lies at P + L * (x_t, y_t, z_t); volts from the descriptor.
        packets.add(o)
    # Packets do not overlap and tile the .wdp after its header.
    sizes = {int(offset[i]): int(size[i]) for i in range(len(pts))}
    at = 60
    for o in sorted(packets):
        assert o == at, f"packet at {o}, expected {at}"
        at += sizes[o]
    assert at == len(wdp), (at, len(wdp))
    print(f"laspy {laspy.__version__}: {len(pts)} points, {len(descriptors)} descriptors, "
          f"{len(packets)} packets, {len(wdp)} bytes of .wdp: all as written")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
