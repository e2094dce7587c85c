"""Writes LAZ copies of a real waveform LAS file with the real LAZ writers (laspy, lazrs), for
tests/laz_reader.rs, and checks with laspy that they hold the same points, waveform fields
included.

Usage: python write_laz.py SOURCE.las OUT_DIR
Writes into OUT_DIR:
  r9.laz   laspy's LAZ of SOURCE (LAS 1.4, point format 9 stored as 137; lazrs, fixed chunks of
           50 000 points: one chunk here);
  r9v.laz  the same header and VLRs, the points compressed by lazrs directly in variable-size
           chunks of 500 points (finish_current_chunk), so several chunks and a chunk table with
           point counts;
  r4.las   SOURCE converted by laspy to LAS 1.3 point format 4 (the waveform fields kept);
  r4.laz   laspy's LAZ of r4.las (format 4 stored as 132: point-wise chunked, LASzip items v2).
Prints one JSON line: {"r9": [point format byte, chunk size, variable], ...}.
Exits non-zero with a message on the first inconsistency.
"""
import io
import json
import struct
import sys
from pathlib import Path

try:
    import laspy
    import lazrs
    import numpy as np
except ImportError as e:  # the Rust test turns this into a failure naming the package
    print(f"MISSING PYTHON PACKAGE: {e.name} (install it into the venv: pip install {e.name})")
    sys.exit(3)

WAVE_FIELDS = [
    "wavepacket_index",
    "wavepacket_offset",
    "wavepacket_size",
    "return_point_wave_location",
    "x_t",
    "y_t",
    "z_t",
]


def same_points(a, b, what):
    names = list(a.point_format.dimension_names)
    assert names == list(b.point_format.dimension_names), f"{what}: fields differ"
    for n in names:
        if not np.array_equal(np.asarray(a[n]), np.asarray(b[n])):
            raise SystemExit(f"{what}: field {n} differs after the round trip")
    for n in WAVE_FIELDS:
        assert n in names, f"{what}: no {n}"


def laszip_vlr(raw: bytes):
    """(offset of the VLR payload, its length) of the LASzip VLR, walking the VLRs."""
    header_size = struct.unpack_from("<H", raw, 94)[0]
    count = struct.unpack_from("<I", raw, 100)[0]
    at = header_size
    for _ in range(count):
        user = raw[at + 2:at + 18].rstrip(b"\0")
        rid, ln = struct.unpack_from("<HH", raw, at + 18)
        if user == b"laszip encoded" and rid == 22204:
            return at + 54, ln
        at += 54 + ln
    raise SystemExit("no LASzip VLR")


def main(src: Path, out: Path) -> None:
    las = laspy.read(src)
    assert las.header.point_format.id == 9, "the source is not point format 9"
    info = {}

    las.write(out / "r9.laz")
    back = laspy.read(out / "r9.laz")
    same_points(las, back, "r9.laz")

    # Variable-size chunks of 500 points: the header and VLRs of r9.laz with the LASzip VLR
    # rewritten for variable chunks, then the raw point records compressed by lazrs.
    raw = src.read_bytes()
    off = struct.unpack_from("<I", raw, 96)[0]
    rl = struct.unpack_from("<H", raw, 105)[0]
    n = struct.unpack_from("<Q", raw, 247)[0]
    fixed = (out / "r9.laz").read_bytes()
    foff = struct.unpack_from("<I", fixed, 96)[0]
    head = bytearray(fixed[:foff])
    vlr = lazrs.LazVlr.new_for_compression(9, rl - 59, True)
    data = vlr.record_data()
    at, ln = laszip_vlr(head)
    assert ln == len(data), (ln, len(data))
    head[at:at + ln] = data
    dest = io.BytesIO()
    dest.write(bytes(head))
    comp = lazrs.LasZipCompressor(dest, vlr)
    pts = raw[off:off + n * rl]
    for s in range(0, n, 500):
        comp.compress_many(pts[s * rl:min(n, s + 500) * rl])
        comp.finish_current_chunk()
    comp.done()
    (out / "r9v.laz").write_bytes(dest.getvalue())
    back = laspy.read(out / "r9v.laz")
    same_points(las, back, "r9v.laz")
    assert np.array_equal(back.points.array, las.points.array)

    l4 = laspy.convert(las, point_format_id=4, file_version="1.3")
    l4.write(out / "r4.las")
    l4.write(out / "r4.laz")
    a = laspy.read(out / "r4.las")
    b = laspy.read(out / "r4.laz")
    assert a.header.point_format.id == 4 and str(a.header.version) == "1.3"
    same_points(a, b, "r4.laz")
    for f in WAVE_FIELDS:
        if not np.array_equal(np.asarray(a[f]), np.asarray(las[f])):
            raise SystemExit(f"r4.las: {f} not kept by the conversion")

    for name in ["r9.laz", "r9v.laz", "r4.laz"]:
        raw = (out / name).read_bytes()
        at, _ = laszip_vlr(raw)
        chunk = struct.unpack_from("<I", raw, at + 12)[0]
        info[name] = [raw[104], chunk, chunk == 0xFFFFFFFF]
    print(json.dumps(info))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
