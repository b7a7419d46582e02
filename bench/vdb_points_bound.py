# How small can P (16-bit fixed point in the voxel), v (half) and id (int32) get with the best
# general-purpose lossless compressors, whole frame at once (an upper bound on what OpenVDB's
# per-leaf Blosc/LZ4 can do)? Reads a binary PLY frame of amalgam (x y z vx vy vz ... id).
# Usage: python3 bench/vdb_points_bound.py FRAME.ply DX   (docs/output.md, issue 32)
import struct, sys, lzma, bz2, subprocess, math
from collections import Counter
path, dx = sys.argv[1], float(sys.argv[2])
f = open(path, 'rb'); props = []; n = 0
while True:
    line = f.readline().decode().strip()
    if line.startswith('element vertex'): n = int(line.split()[2])
    elif line.startswith('property'): props.append((line.split()[1], line.split()[2]))
    elif line == 'end_header': break
fmt = {'float': 'f', 'double': 'd', 'int': 'i', 'uint': 'I', 'uchar': 'B', 'int64': 'q', 'uint64': 'Q', 'int32': 'i', 'uint32': 'I', 'float32': 'f'}
rec = '<' + ''.join(fmt[t] for t, _ in props); size = struct.calcsize(rec)
names = [p for _, p in props]; data = f.read(n * size)
rows = [struct.unpack_from(rec, data, i * size) for i in range(n)]
ix = {k: names.index(k) for k in names}
pts = []
for r in rows:
    x = [r[ix['x']], r[ix['y']], r[ix['z']]]
    ijk = [math.floor(c / dx + 0.5) for c in x]
    q = [min(65535, max(0, int((c / dx - i + 0.5) * 65535))) for c, i in zip(x, ijk)]
    key = tuple(i >> 3 for i in ijk) + tuple(i & 7 for i in ijk) + (r[ix['id']],)
    pts.append((key, q, [r[ix['vx']], r[ix['vy']], r[ix['vz']]], r[ix['id']]))
pts.sort()
P = b''.join(struct.pack('<3H', *p[1]) for p in pts)
V = b''.join(struct.pack('<3e', *p[2]) for p in pts)
I = b''.join(struct.pack('<i', p[3]) for p in pts)
def shuffle(b, w):  # byte planes of w-byte elements
    return b''.join(b[k::w] for k in range(w))
def comp(b):
    best = min(len(lzma.compress(b, preset=9 | lzma.PRESET_EXTREME)), len(bz2.compress(b, 9)))
    z = subprocess.run(['zstd', '-19', '--ultra', '-c'], input=b, capture_output=True).stdout
    return min(best, len(z))
def h0(b, w):  # order-0 entropy of w-byte symbols, bytes
    c = Counter(b[i:i + w] for i in range(0, len(b), w)); m = sum(c.values())
    return -sum(v * math.log2(v / m) for v in c.values()) / 8
out = {}
for name, b, w in (('P', P, 2), ('v', V, 2), ('id', I, 4)):
    comps = [comp(b), comp(shuffle(b, w)), comp(shuffle(b, 3 * w) if w == 2 else b)]
    if w == 2:  # component planes x, y, z as separate 16-bit streams, each byte-shuffled
        planes = b''.join(shuffle(b''.join(b[6 * i + 2 * k:6 * i + 2 * k + 2] for i in range(n)), 2) for k in range(3))
        comps.append(comp(planes))
    out[name] = min(comps) / n
    print(f"{name}: raw {len(b)/n:.2f} B/particle, best lossless {out[name]:.2f} B/particle "
          f"(variants {[round(c / n, 2) for c in comps]}), order-0 entropy of {8*w}-bit symbols {h0(b, w) / n:.2f} B/particle")
print(f"n = {n}; P + v + id best lossless: {sum(out.values()):.2f} B/particle")
