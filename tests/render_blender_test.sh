#!/usr/bin/env bash
# Smoke test of scripts/render_blender.sh: renders a small surfaced frame (the points, the mesh
# and the density VDB of `amalgam run` with output.surfacing) with Blender headless, and checks
# the PNG exists, has the size asked for (three 64x48 panels side by side) and is not blank: each
# panel has pixels of different colours. Where `blender` is not on PATH it exits 77 (ctest
# SKIP_RETURN_CODE) with a message. Usage: render_blender_test.sh AMALGAM SCENE OUTDIR
set -u
amalgam=$1 scene=$2 out=$3
root="$(cd "$(dirname "$0")/.." && pwd)"
fail() { echo "FAIL: $*"; exit 1; }
if ! command -v "${BLENDER:-blender}" >/dev/null 2>&1; then
  echo "SKIPPED: blender is not installed (scripts/install_deps.sh --render installs it)"
  exit 77
fi
rm -rf "$out"
"$amalgam" run "$scene" --threads 2 --out "$out/run" --frames 1 --quiet || fail "run failed"
for f in frame_0001.ply surfacing_0001.ply surfacing_0001.vdb; do
  [ -s "$out/run/$f" ] || fail "run did not write $f"
done
"$root/scripts/render_blender.sh" --points "$out/run/frame_0001.ply" --mesh "$out/run/surfacing_0001.ply" \
  --vdb "$out/run/surfacing_0001.vdb" --out "$out/render.png" --size 64x48 --samples 4 --threads 2 \
  || fail "render_blender.sh failed"
# The PNG read with Python's standard library (zlib, PNG filters undone: PNG spec section 9).
python3 - "$out/render.png" 192 48 3 <<'PY' || fail "render check"
import struct, sys, zlib
path, want_w, want_h, panels = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
data = open(path, "rb").read()
assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
pos, idat, w = 8, b"", None
while pos < len(data):
    n, kind = struct.unpack(">I4s", data[pos:pos + 8])
    body = data[pos + 8:pos + 8 + n]
    if kind == b"IHDR":
        w, h, depth, ctype = struct.unpack(">IIBB", body[:10])
    elif kind == b"IDAT":
        idat += body
    pos += 12 + n
if (w, h) != (want_w, want_h):
    sys.exit("size %dx%d, expected %dx%d" % (w, h, want_w, want_h))
assert depth == 8 and ctype in (2, 6), "expected 8-bit RGB(A), got depth %d type %d" % (depth, ctype)
bpp = 3 if ctype == 2 else 4
raw, stride, rows, prev = zlib.decompress(idat), w * bpp, [], bytearray(w * bpp)
for y in range(h):
    ft, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
    for i in range(stride):
        a = line[i - bpp] if i >= bpp else 0
        b, c = prev[i], prev[i - bpp] if i >= bpp else 0
        p = a + b - c
        pred = [0, a, b, (a + b) // 2,
                a if abs(p - a) <= abs(p - b) and abs(p - a) <= abs(p - c) else b if abs(p - b) <= abs(p - c) else c][ft]
        line[i] = (line[i] + pred) & 255
    rows.append(line)
    prev = line
pw = w // panels
for k in range(panels):
    colours = {bytes(r[(x * bpp):(x * bpp + 3)]) for r in rows for x in range(k * pw, (k + 1) * pw)}
    if len(colours) < 10:
        sys.exit("panel %d is nearly uniform (%d colours)" % (k, len(colours)))
    print("panel %d: %d colours" % (k, len(colours)))
PY
echo "render smoke test: ${out}/render.png is 192x48 with three non-uniform panels"
