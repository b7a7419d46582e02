#!/usr/bin/env python3
"""Measured Poisson ratio of each material of a stretched-beam run (scenes/pd_beam_stretch.json).

Usage: scripts/poisson_contraction.py RUN_DIR [FRAME]

Reads RUN_DIR/frame_0000.ply and RUN_DIR/frame_FRAME.ply (binary PLY as amalgam writes it; the
particle order is stable in peridynamics runs, and `id` is checked). Per material: the axial strain
between the cross-sections at 1/4 and 3/4 of the beam length (mean x of particles within one
spacing of each), the lateral strain of the middle section (RMS distance from its centroid in the
two lateral directions) and nu = -lateral / axial. Pure Python (no numpy).
"""
import math
import struct
import sys


def read_ply(path):
    with open(path, "rb") as f:
        props, n = [], 0
        while True:
            line = f.readline().decode("ascii").strip()
            if line.startswith("element vertex"):
                n = int(line.split()[2])
            elif line.startswith("property"):
                _, typ, name = line.split()
                props.append((typ, name))
            elif line == "end_header":
                break
        fmt = "<" + "".join("f" if t == "float" else "i" for t, _ in props)
        size = struct.calcsize(fmt)
        data = f.read(n * size)
    names = [p for _, p in props]
    rows = [struct.unpack_from(fmt, data, i * size) for i in range(n)]
    return {name: [r[k] for r in rows] for k, name in enumerate(names)}


def main():
    run = sys.argv[1]
    frame = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    a = read_ply(f"{run}/frame_0000.ply")
    b = read_ply(f"{run}/frame_{frame:04d}.ply")
    if a["id"] != b["id"]:
        sys.exit("particle order changed between the frames")
    n = len(a["x"])
    print(f"frame {frame}: material, axial strain, lateral strain, measured nu")
    for m in sorted(set(a["material"])):
        idx = [i for i in range(n) if a["material"][i] == m]
        x0 = [a["x"][i] for i in idx]
        lo, hi = min(x0), max(x0)
        length = hi - lo
        h = length / 60  # about one spacing for the scene's beams

        def section(frac):
            c = lo + frac * length
            return [i for i in idx if abs(a["x"][i] - c) < h]

        q1, q3, mid = section(0.25), section(0.75), section(0.5)
        mean = lambda d, s: sum(d[i] for i in s) / len(s)
        axial = (mean(b["x"], q3) - mean(b["x"], q1)) / (mean(a["x"], q3) - mean(a["x"], q1)) - 1

        def spread(d):
            cy, cz = mean(d["y"], mid), mean(d["z"], mid)
            return math.sqrt(sum((d["y"][i] - cy) ** 2 + (d["z"][i] - cz) ** 2 for i in mid) / len(mid))

        lateral = spread(b) / spread(a) - 1
        print(f"  material {m}: {axial:.5f}, {lateral:.5f}, nu = {-lateral / axial:.3f}")


if __name__ == "__main__":
    main()
