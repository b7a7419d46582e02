#!/usr/bin/env bash
# Physics validation table (issue 27, docs/validation.md): runs each validation case of the
# release build, parses what it prints, and writes docs/validation_table.md with the reference,
# the measured value (a mean with its spread over the case's time window where the case has one),
# the tolerance, pass or fail, the commit and the machine.
#
#   scripts/validate_physics.sh [--build DIR] [--out FILE] [--double DIR]
#
# --double DIR also runs the column cases on a double build in DIR (configured and built here
# with -DAMALGAM_REAL=double when missing: ~8 minutes on 2 cores). The default run takes ~5
# minutes. The simulations are deterministic (bitwise the same on every backend and thread
# count), so repeats give the same values: the spreads are over each case's time window.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
build="$root/build" out="$root/docs/validation_table.md" double=""
while [ $# -gt 0 ]; do
  case "$1" in
    --build) build="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --double) double="$2"; shift 2 ;;
    *) echo "usage: validate_physics.sh [--build DIR] [--out FILE] [--double DIR]" >&2; exit 2 ;;
  esac
done
[ -x "$build/tests/test_fidelity" ] || AMALGAM_BUILD_DIR="$build" "$root/scripts/build.sh"
logs="$(mktemp -d)"
trap 'rm -rf "$logs"' EXIT
run() {  # run NAME BINARY FILTER: the case's output in $logs/NAME.log
  echo "validate_physics: $1" >&2
  "$2" --gtest_filter="$3" > "$logs/$1.log" 2>&1 || true
}
run fidelity "$build/tests/test_fidelity" 'Fidelity.*'
run water "$build/tests/test_material_validation" 'MaterialValidation.WaterColumnHydrostaticPressure'
run sand "$build/tests/test_material_validation" 'MaterialValidation.SandPileSlopeMatchesFrictionAngle'
run axial "$build/tests/test_validation" 'Transfers/AxialBar.*'
run pdwave "$build/tests/test_peridynamics" 'PdValidation.LongitudinalWaveTravelsAtTheBarSpeed'
if [ -n "$double" ]; then
  if [ ! -x "$double/tests/test_fidelity" ]; then
    cmake -S "$root" -B "$double" -G Ninja -DCMAKE_BUILD_TYPE=Release -DAMALGAM_REAL=double >/dev/null
    cmake --build "$double" --target test_fidelity >/dev/null
  fi
  run fidelity_double "$double/tests/test_fidelity" 'Fidelity.Column*'
fi
commit="$(git -C "$root" rev-parse --short HEAD)$(git -C "$root" diff --quiet || echo ' (modified)')"
machine="$(nproc) cores, $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo), $(. /etc/os-release && echo "$PRETTY_NAME")"
python3 - "$logs" "$out" "$commit" "$machine" <<'EOF'
import datetime, glob, os, re, sys
logs, out, commit, machine = sys.argv[1:5]
def read(name):
    p = os.path.join(logs, name + ".log")
    return open(p).read() if os.path.exists(p) else ""
rows = []
def row(case, ref, value, tol, ok, how):
    rows.append(f"| {case} | {ref} | {value} | {tol} | {'pass' if ok else '**fail**'} | `{how}` |")
for name, label in (("fidelity", "float"), ("fidelity_double", "double")):
    for m in re.finditer(r"column at \(([^)]*)\): compression ([\d.e+-]+) m \(sd ([\d.e+-]+)\), "
                         r"analytic ([\d.e+-]+) m, ([+-][\d.]+) %", read(name)):
        where, c, sd, a, err = m.group(1), float(m.group(2)), float(m.group(3)), float(m.group(4)), float(m.group(5))
        row(f"elastic column at rest, {label}, corner ({where})", f"ρg/E·(Hy − y²/2): {a:.4e} m",
            f"{err:+.2f} % (sd {100 * sd / a:.2f} %, t = 2–3 s)", "2 %", abs(err) <= 2,
            f"test_fidelity ({label} build)")
w = read("water")
m = re.search(r"dp/dy = ([\d.-]+) Pa/m, rho g = ([\d.-]+) Pa/m \(([+-][\d.]+) %\)", w)
r = re.search(r"layer error RMS ([\d.]+) %, max ([\d.]+) %", w)
if m and r:
    err = float(m.group(3))
    row("hydrostatic pressure, water column (PIC, Tait)", "dp/dy = −ρg",
        f"{err:+.2f} % (layers over t = 1.5–2.5 s: RMS {r.group(1)} %, max {r.group(2)} %)", "3 %",
        abs(err) <= 3 and float(r.group(1)) <= 3, "test_material_validation --gtest_filter='*Water*'")
m = re.search(r"flank slope ([\d.]+) deg over \d+ bins \(friction angle (\d+)\)", read("sand"))
if m:
    a, phi = float(m.group(1)), float(m.group(2))
    row("sand column angle of repose (Drucker–Prager)", f"friction angle {phi:.0f}°",
        f"{a:.2f}° (at rest, one run)", "3°", abs(a - phi) <= 3,
        "test_material_validation --gtest_filter='*Sand*'")
for m in re.finditer(r"axial bar (\w+) order (\d): period ([\d.]+) s, analytic ([\d.]+) s, error ([+-]?[\d.]+) %",
                     read("axial")):
    err = float(m.group(5))
    row(f"axial bar vibration period, {m.group(1)} order {m.group(2)}", f"4L/c = {m.group(4)} s",
        f"{err:+.3f} % (mean over the crossings of 2.3 periods)", "2 %", abs(err) <= 2,
        "test_validation --gtest_filter='*AxialBar*'")
for m in re.finditer(r"(\w+): bar wave speed ([\d.]+) m/s, sqrt\(E/rho\) = ([\d.]+) m/s: ratio ([\d.]+)",
                     read("pdwave")):
    ratio = float(m.group(4))
    row(f"peridynamic bar wave speed, {m.group(1)} form", f"√(E/ρ) = {m.group(3)} m/s",
        f"{100 * (ratio - 1):+.2f} % (first zero crossing of the fundamental mode)", "2 %",
        abs(ratio - 1) <= 0.02, "test_peridynamics --gtest_filter='*LongitudinalWave*'")
date = datetime.date.today().isoformat()
text = f"""# Validation table

Generated by `scripts/validate_physics.sh` on {date} at commit `{commit}` ({machine}, release
build, float unless stated). Cases and how to read them: [validation.md](validation.md).

| case | reference | measured | tolerance | | reproduce |
|---|---|---|---|---|---|
""" + "\n".join(rows) + "\n"
open(out, "w").write(text)
print(text)
fails = sum("**fail**" in r for r in rows)
sys.exit(1 if fails or not rows else 0)
EOF
