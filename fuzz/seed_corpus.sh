#!/bin/sh
# Seeds fuzz/corpus/ from files of the repository (corpora are not committed).
#   capture_reader: replay/two_layer.fwcap cut to its first 8 KiB, prefixed with a mode byte
#                   0x00 (even: the bytes are read as they are, preamble included), plus the same
#                   records without the preamble behind mode byte 0x01 (odd: the target adds it).
#   frame_decode:   the payloads of the first frame and nav records of that capture.
#   config_load:    every file of config/.
#   waveform_table: a small CSV and NPY written here (mode byte 0x00 CSV, 0x01 NPY), plus the
#                   first lines of the NEON return.csv and imp.csv. Real files come from
#                   tests/data, or $FWLIDAR_FIXTURES when set.
#   pulsewaves_reader: the PulseWaves pairs of tests/data/waveform (when it exists), each
#                   cut to its header, records and first pulses (number_of_pulses patched to
#                   match), as u16 .pls length + .pls + .wvs.
#   nav_decoder:    the real receiver logs of tests/data/nav (gpsd NMEA logs, the NovAtel
#                   SPAN capture, the SBET files), each behind a mode byte 0x07, when it exists.
#   live_frames:    the first three digitizer frames of that capture as a live stream (28-byte
#                   headers with sequence numbers and CRC-32C, docs/formats.md), behind a mode
#                   byte 0x00 (pushed whole) and 0x05 (pushed in reads of 5 bytes).
#   hyper_points:   a LAS 1.4 point format 6 file of 20 points with the extra dimension
#                   `signal` (f32), as a replay's hyper_points.las, written here.
#   las_reader:     the real RIEGL LAS 1.4 file cut to its first 20 points with the .wdp bytes
#                   they use (u32 LE .las length, .las, .wdp), and the same with the packets
#                   internal (global encoding bit 1, appended EVLR); with a Python holding laspy
#                   and lazrs, also that cut as LAZ (only the descriptors used): format 9 (one
#                   chunk), format 9 in chunks of 5 points (lazrs), and format 4 (LAS 1.3).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(dirname "$here")
cap="$root/replay/two_layer.fwcap"
mkdir -p "$here/corpus/capture_reader" "$here/corpus/frame_decode" "$here/corpus/config_load" \
    "$here/corpus/waveform_table" "$here/corpus/pulsewaves_reader" "$here/corpus/las_reader" \
    "$here/corpus/nav_decoder" "$here/corpus/live_frames" "$here/corpus/hyper_points"

# capture_reader
{ printf '\000'; head -c 8192 "$cap"; } > "$here/corpus/capture_reader/two_layer_8k_raw"
{ printf '\001'; head -c 8192 "$cap" | tail -c +17; } > "$here/corpus/capture_reader/two_layer_8k_body"

# frame_decode: payloads of the first records (record = 12-byte header, payload, 4-byte CRC).
python3 - "$cap" "$here/corpus/frame_decode" <<'PY'
import struct, sys
data = open(sys.argv[1], "rb").read(1 << 16)
out = sys.argv[2]
at, n = 16, 0
while at + 16 <= len(data) and n < 16:
    if data[at:at + 4] != b"\xf5WLR":
        break
    kind = data[at + 4]
    (length,) = struct.unpack_from("<I", data, at + 8)
    payload = data[at + 12:at + 12 + length]
    if len(payload) < length:
        break
    if kind in (2, 3):
        open(f"{out}/record{n:02}_kind{kind}", "wb").write(payload)
        n += 1
    at += 16 + length
PY

# live_frames: the first three frame payloads of the capture, each behind a live header.
python3 - "$cap" "$here/corpus/live_frames" <<'PY'
import struct, sys
table = []
for i in range(256):
    c = i
    for _ in range(8):
        c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
    table.append(c)
def crc32c(b):
    c = 0xFFFFFFFF
    for x in b:
        c = table[(c ^ x) & 0xFF] ^ (c >> 8)
    return c ^ 0xFFFFFFFF
data = open(sys.argv[1], "rb").read(1 << 16)
at, frames = 16, []
while at + 16 <= len(data) and len(frames) < 3:
    if data[at:at + 4] != b"\xf5WLR":
        break
    kind = data[at + 4]
    (length,) = struct.unpack_from("<I", data, at + 8)
    payload = data[at + 12:at + 12 + length]
    if len(payload) < length:
        break
    if kind == 2:
        head = b"\xf5WLD" + struct.pack("<BBHQII", 1, 2, 0, len(frames), length, crc32c(payload))
        frames.append(head + struct.pack("<I", crc32c(head)) + payload)
    at += 16 + length
stream = b"".join(frames)
open(f"{sys.argv[2]}/three_frames_whole", "wb").write(b"\x00" + stream)
open(f"{sys.argv[2]}/three_frames_by5", "wb").write(b"\x05" + stream)
PY

# config_load
find "$root/config" -name '*.toml' | while read -r f; do
    cp "$f" "$here/corpus/config_load/$(basename "$(dirname "$f")")_$(basename "$f")"
done
# waveform_table
wt="$here/corpus/waveform_table"
printf '\000V1,V2,V3\n1.5, -2 ,3e-7,,\n\n4,nan,NaN\r\n0,0,0\n' > "$wt/small_csv"
python3 - "$wt/small_npy" <<'PY'
import struct, sys
header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }"
header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
data = struct.pack("<6f", 1.0, 2.0, float("nan"), 4.0, 5.0, 6.0)
blob = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + data
open(sys.argv[1], "wb").write(b"\x01" + blob)
PY
fx="${FWLIDAR_FIXTURES:-$root/tests/data}/waveform/neon_harv"
if [ -d "$fx" ]; then
    { printf '\000'; head -n 4 "$fx/return.csv"; } > "$wt/neon_return_head"
    { printf '\000'; cat "$fx/imp.csv"; } > "$wt/neon_imp"
fi

# pulsewaves_reader
wf="${FWLIDAR_FIXTURES:-$root/tests/data}/waveform"
if [ -d "$wf" ]; then
    python3 - "$here/corpus/pulsewaves_reader" "$wf/pulsewaves/test" "$wf/pulsewaves/lvis_example1" \
        "$wf/pulsewaves/las13fwf_example1" "$wf/riegl_q680i/100429_152240_2535pt_UTM" <<'PY'
import os, struct, sys
out = sys.argv[1]
for stem in sys.argv[2:]:
    pls = bytearray(open(stem + ".pls", "rb").read())
    wvs = open(stem + ".wvs", "rb").read()
    (start, count) = struct.unpack_from("<qq", pls, 176)
    (size,) = struct.unpack_from("<I", pls, 200)
    keep = min(count, 12)
    struct.pack_into("<q", pls, 184, keep)
    pls = pls[:start + keep * size]
    if keep < count:
        wend = struct.unpack_from("<q", open(stem + ".pls", "rb").read(), start + keep * size + 8)[0]
    else:
        wend = len(wvs)
    if len(pls) > 0xFFFF:
        continue
    name = os.path.basename(stem)
    open(f"{out}/{name}", "wb").write(struct.pack("<H", len(pls)) + bytes(pls) + wvs[:wend])
PY
fi

# las_reader
fl="${FWLIDAR_FIXTURES:-$root/tests/data}/waveform/riegl_q680i/100429_152240_2535pt_UTM"
if [ -f "$fl.las" ]; then
    python3 - "$fl" "$here/corpus/las_reader" <<'PY'
import struct, sys
stem, out = sys.argv[1], sys.argv[2]
las = open(stem + ".las", "rb").read()
wdp = open(stem + ".wdp", "rb").read()
opd, = struct.unpack_from("<I", las, 96)
rl, = struct.unpack_from("<H", las, 105)
n = 20
head = bytearray(las[:opd + n * rl])
struct.pack_into("<Q", head, 247, n)
end = max(struct.unpack_from("<Q", las, opd + i * rl + 31)[0]
          + struct.unpack_from("<I", las, opd + i * rl + 39)[0] for i in range(n))
wave = bytearray(wdp[:end])
struct.pack_into("<Q", wave, 20, len(wave) - 60)  # the cut record's length after its header
open(out + "/riegl_20_points_external", "wb").write(struct.pack("<I", len(head)) + head + wave)
inner = bytearray(head)
struct.pack_into("<H", inner, 6, 1 << 1)
struct.pack_into("<QQI", inner, 227, len(inner), len(inner), 1)
inner += wave
open(out + "/riegl_20_points_internal", "wb").write(struct.pack("<I", len(inner)) + inner)
PY
    # LAZ seeds need laspy and lazrs (the venv of .ci/run, or $FWLIDAR_PYTHON).
    py="${FWLIDAR_PYTHON:-$root/.venv/bin/python}"
    if [ -x "$py" ] && "$py" -c "import laspy, lazrs" 2>/dev/null; then
        "$py" - "$fl" "$here/corpus/las_reader" <<'PY'
import io, struct, sys
import laspy, lazrs
stem, out = sys.argv[1], sys.argv[2]
n = 20
las = laspy.read(stem + ".las")
wdp = open(stem + ".wdp", "rb").read()
cut = laspy.LasData(las.header, las.points[:n].copy())
used = set(int(i) for i in cut.wavepacket_index)
# Only the descriptors the points use: the fuzzer's mutations land in the compressed points.
cut.header.vlrs = [v for v in las.header.vlrs
                   if not (99 < v.record_id < 355) or v.record_id - 99 in used]
cut.update_header()
end = int(max(cut.wavepacket_offset + cut.wavepacket_size))
wave = bytearray(wdp[:end])
struct.pack_into("<Q", wave, 20, len(wave) - 60)
def seed(name, laz):
    open(f"{out}/{name}", "wb").write(struct.pack("<I", len(laz)) + laz + bytes(wave))
b = io.BytesIO(); cut.write(b, do_compress=True); seed("riegl_20_points_laz9", b.getvalue())
f4 = laspy.convert(cut, point_format_id=4, file_version="1.3")
b = io.BytesIO(); f4.write(b, do_compress=True); seed("riegl_20_points_laz4", b.getvalue())
# Variable-size chunks of 5 points (lazrs), so the chunk table holds point counts.
b = io.BytesIO(); cut.write(b, do_compress=True); fixed = b.getvalue()
off, = struct.unpack_from("<I", fixed, 96)
rl, = struct.unpack_from("<H", fixed, 105)
head = bytearray(fixed[:off])
vlr = lazrs.LazVlr.new_for_compression(9, rl - 59, True)
at = head.find(b"laszip encoded") - 2
head[at + 54:at + 54 + len(vlr.record_data())] = vlr.record_data()
raw = io.BytesIO(); cut.write(raw, do_compress=False); raw = raw.getvalue()
roff, = struct.unpack_from("<I", raw, 96)
dest = io.BytesIO(); dest.write(bytes(head))
comp = lazrs.LasZipCompressor(dest, vlr)
for s in range(0, n, 5):
    comp.compress_many(raw[roff + s * rl:roff + (s + 5) * rl])
    comp.finish_current_chunk()
comp.done()
seed("riegl_20_points_laz9_chunks", dest.getvalue())
PY
    fi
fi

# hyper_points
python3 - "$here/corpus/hyper_points/format6_signal_20_points.las" <<'PY'
import struct, sys
n, rec = 20, 34
vlr_data = bytearray(192)
vlr_data[2] = 9  # float
vlr_data[4:10] = b"signal"
vlr = struct.pack("<H16sHH32s", 0, b"LASF_Spec", 4, 192, b"extra bytes") + bytes(vlr_data)
offset = 375 + len(vlr)
h = bytearray(375)
h[0:4] = b"LASF"
h[24], h[25] = 1, 4
struct.pack_into("<HIIBHI", h, 94, 375, offset, 1, 6, rec, n)
struct.pack_into("<3d3d", h, 131, 0.001, 0.001, 0.001, 500000.0, 7000000.0, 0.0)
struct.pack_into("<Q", h, 247, n)
pts = b"".join(struct.pack("<3iHBBBBhHd", i * 250, i * 100, 1000 + i * 150, 100, 0x11, 0, 1, 0, 0, 0, 1.0 + i // 4)
               + struct.pack("<f", 0.5 + i) for i in range(n))
open(sys.argv[1], "wb").write(bytes(h) + vlr + pts)
PY

# nav_decoder
nv="${FWLIDAR_FIXTURES:-$root/tests/data}/nav"
if [ -d "$nv" ]; then
    for f in "$nv"/gpsd/*.log "$nv"/novatel/*.bin "$nv"/sbet/*.sbet; do
        { printf '\007'; cat "$f"; } > "$here/corpus/nav_decoder/$(basename "$f")"
    done
fi

ls -l "$here"/corpus/*
