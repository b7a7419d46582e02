#!/usr/bin/env python3
"""Peridynamics peer comparison with LAMMPS (Debian package `lammps`, pair_style peri/lps).

Runs the same bar in Amalgam (build/bench/amalgam_pd_wave) and in LAMMPS: nx x ny x nz particles
on a simple-cubic lattice of spacing lc = 0.01 m, horizon 3.015 lc, glass (K = 48 GPa, G = 28.8
GPa, rho = 2200 kg/m^3), no fracture, the first three layers started at 1 m/s along x, a fixed
time step. Reports (1) the wave's arrival time at the far end (first time the last layer's mean
x velocity exceeds 10 % of v0) for both codes and the bar-theory time, and (2) time per step
and directed bond-updates per second at 1 and 2 threads (Amalgam, OpenMP) and 1 and 2 MPI ranks
(LAMMPS), medians over --repeats runs.

    python3 bench/pd_peer.py [--build build] [--repeats 3] [--big 200x32x32] [--out docs/pd_peer.md]

See docs/benchmarks.md, "Peridynamics: LAMMPS peer".
"""
import argparse
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile

LC = 0.01
DELTA = 3.015 * LC
K, G, RHO = 48e9, 28.8e9, 2200.0
V0 = 1.0

LAMMPS_INPUT = """units si
dimension 3
boundary s s s
atom_style peri
atom_modify map array
lattice sc {lc}
region bar block 0 {xmax} 0 {ymax} 0 {zmax} units lattice
create_box 1 bar
create_atoms 1 region bar
pair_style peri/lps
pair_coeff * * {K} {G} {delta} 1.0 0.0
set group all density {rho}
set group all volume {vol}
velocity all set 0 0 0
neighbor {skin} bin
region strike block INF 2.5 INF INF INF INF units lattice
group striker region strike
region farend block {farx} INF INF INF INF INF units lattice
group far region farend
compute vfar far reduce ave vx
fix 1 all nve
timestep {dt}
thermo_style custom step time c_vfar
thermo 1
run 0
velocity striker set {v0} 0 0 units box
run {steps}
"""


def lammps(nx, ny, nz, dt, steps, ranks, workdir):
    """Runs LAMMPS; returns (arrival time or None, seconds per step, directed bonds)."""
    inp = LAMMPS_INPUT.format(lc=LC, xmax=nx - 0.5, ymax=ny - 0.5, zmax=nz - 0.5, K=K, G=G, delta=DELTA,
                              rho=RHO, vol=LC ** 3, skin=0.1 * LC, farx=nx - 1.5, dt=dt, v0=V0, steps=steps)
    path = os.path.join(workdir, "in.bar")
    with open(path, "w") as f:
        f.write(inp)
    cmd = ["lmp", "-in", path, "-log", os.path.join(workdir, "log.lammps"), "-screen", "none"]
    if ranks > 1:
        cmd = ["mpirun", "--allow-run-as-root", "--oversubscribe", "-np", str(ranks)] + cmd
    subprocess.run(cmd, check=True, cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    log = open(os.path.join(workdir, "log.lammps")).read()
    arrival = None
    rows = re.findall(r"^\s*(\d+)\s+([0-9.eE+-]+)\s+([0-9.eE+-]+)\s*$", log, re.M)
    for step, t, vfar in rows:
        if int(step) > 0 and float(vfar) > 0.1 * V0:
            arrival = float(t)
            break
    loops = re.findall(r"Loop time of ([0-9.eE+-]+) on \d+ procs for (\d+) steps", log)
    secs, nsteps = float(loops[-1][0]), int(loops[-1][1])
    bonds = re.findall(r"Peridynamic bonds:\s*\n\s*total # of bonds = (\d+)", log)
    nb = int(bonds[-1]) if bonds else None
    return arrival, secs / max(nsteps, 1), nb


def amalgam(exe, nx, ny, nz, dt, threads, timing_steps=0, repeats=1, correction=1, form="paper"):
    cmd = [exe, "--nx", str(nx), "--ny", str(ny), "--nz", str(nz), "--dt", str(dt), "--backend",
           "openmp", "--threads", str(threads), "--correction", str(correction), "--form", form]
    if timing_steps:
        cmd += ["--timing-steps", str(timing_steps), "--repeats", str(repeats), "--steps", "1"]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    res = {}
    for k, v in (line.split("=", 1) for line in out.splitlines() if "=" in line):
        try:
            res[k.strip()] = float(v)
        except ValueError:  # simd = avx512
            res[k.strip()] = v.strip()
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--build", default="build")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--wave", default="100x10x10", help="bar for the arrival times")
    ap.add_argument("--big", default="200x32x32", help="block for the throughput (>= 2e5 particles)")
    ap.add_argument("--timing-steps", type=int, default=10)
    ap.add_argument("--dt", type=float, default=5e-7)
    ap.add_argument("--out", default=None, help="also write the Markdown table here")
    args = ap.parse_args()
    if not shutil.which("lmp"):
        sys.exit("pd_peer.py: LAMMPS (lmp) not found: sudo apt-get install lammps openmpi-bin")
    exe = os.path.join(args.build, "bench", "amalgam_pd_wave")
    if not os.path.exists(exe):
        sys.exit(f"pd_peer.py: {exe} not found: build first (bash scripts/build.sh)")
    nx, ny, nz = (int(v) for v in args.wave.split("x"))
    bx, by, bz = (int(v) for v in args.big.split("x"))
    lines = []
    with tempfile.TemporaryDirectory() as work:
        steps = int(1.6 * nx * LC / math.sqrt(K / RHO) / args.dt)
        la, _, lb = lammps(nx, ny, nz, args.dt, steps, 1, work)
        am = amalgam(exe, nx, ny, nz, args.dt, 2)
        au = amalgam(exe, nx, ny, nz, args.dt, 2, correction=0, form="lps")
        E = 9 * K * G / (3 * K + G)
        bar_time = (nx - 2) * LC / math.sqrt(E / RHO)  # striker centre to the far layer
        lines.append(f"Wave in a bar of {nx}x{ny}x{nz} particles (lc = {LC} m, delta = 3.015 lc, glass), "
                     f"dt = {args.dt:g} s, arrival = last layer's mean vx > 10 % of v0:\n")
        lines.append("| run | arrival (us) | vs LAMMPS | vs bar theory (L - 2 lc) / sqrt(E/rho) |")
        lines.append("|---|---|---|---|")
        for name, t in [("LAMMPS peri/lps", la), ("Amalgam, paper form, corrected (default)", am["arrival_s"]),
                        ("Amalgam, LPS form, uncorrected", au["arrival_s"])]:
            rel = f"{t / la:.4f}" if la else "n/a"
            lines.append(f"| {name} | {t * 1e6:.2f} | {rel} | {t / bar_time:.4f} |")
        lines.append(f"\nbar theory: {bar_time * 1e6:.2f} us; directed bonds: Amalgam {int(am['bonds'])}, LAMMPS {lb}\n")
        # Throughput on the big block.
        lines.append(f"Throughput on {bx}x{by}x{bz} = {bx * by * bz} particles, medians of {args.repeats} runs "
                     f"of {args.timing_steps} steps (directed bond-updates/s: every bond i->j and j->i):\n")
        lines.append("| code | workers | s/step (median, min-max) | directed bond-updates/s |")
        lines.append("|---|---|---|---|")
        for ranks in (1, 2):
            times = []
            nb = None
            for _ in range(args.repeats):
                _, sps, nb = lammps(bx, by, bz, args.dt, args.timing_steps, ranks, work)
                times.append(sps)
            med = statistics.median(times)
            lines.append(f"| LAMMPS peri/lps | {ranks} MPI rank(s) | {med:.4f} ({min(times):.4f}-{max(times):.4f}) | "
                         f"{nb / med:.3g} |")
        for threads in (1, 2):
            r = amalgam(exe, bx, by, bz, args.dt, threads, args.timing_steps, args.repeats)
            lines.append(f"| Amalgam (paper form, corrected, SIMD path {r['simd']}) | {threads} OpenMP thread(s) | "
                         f"{r['seconds_per_step']:.4f} ({r['seconds_per_step_min']:.4f}-{r['seconds_per_step_max']:.4f}) | "
                         f"{r['bond_updates_per_s']:.3g} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)


if __name__ == "__main__":
    main()
