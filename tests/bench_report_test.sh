#!/usr/bin/env bash
# amalgam bench --report end to end on tiny cases: the files, one CSV row per case x
# configuration with finite positive throughputs and min <= median <= max, the report's sections,
# PNG signatures, the roofline section, the repeatability section of a --compare run, and usage errors.
# usage: bench_report_test.sh AMALGAM OUTDIR
set -euo pipefail
amalgam="$1"
out="$2"
rm -rf "$out"
mkdir -p "$out"
fail() { echo "bench_report_test: $*" >&2; exit 1; }
args=(--scale 0.02 --reps 3 --steps 1 --warmup 1 --cases mpm_mls,peridynamics --backends serial,openmp --threads 1,2)
"$amalgam" bench --report "$out/a" "${args[@]}" --commit abc123 > "$out/a.log"
"$amalgam" bench --report "$out/b" "${args[@]}" --compare "$out/a/results.csv" > "$out/b.log"
for f in results.csv kernels.csv report.md scaling.png breakdown.png; do
  [ -s "$out/b/$f" ] || fail "missing $f"
done
for f in scaling.png breakdown.png; do
  [ "$(head -c 8 "$out/b/$f" | od -An -tx1 | tr -d ' \n')" = "89504e470d0a1a0a" ] || fail "$f is not a PNG"
done
# 2 cases x (serial 1, openmp 1, openmp 2) = 6 rows + header
[ "$(wc -l < "$out/b/results.csv")" -eq 7 ] || fail "results.csv has $(wc -l < "$out/b/results.csv") lines, expected 7"
awk -F, 'NR > 1 { if (!($8 > 0) || $9 > $8 || $8 > $10 || $7 != 3) { print "bad row: " $0; bad = 1 } } END { exit bad }' \
  "$out/b/results.csv" || fail "results.csv rows"
grep -q '^peridynamics,openmp,2,bond-updates/s,.*,"peridynamics, state-based, plastic + fracture on",$' "$out/b/results.csv" ||
  fail "no peridynamics openmp x2 row (with its quoted method)"
grep -q '^mpm_mls,serial,1,mpm.p2g,' "$out/b/kernels.csv" || fail "no P2G region in kernels.csv"
for s in "## Summary" "## mpm_mls: explicit MPM, MLS, quadratic" "## peridynamics:" "## Repeatability" \
         "of 6 configurations changed by no more than the noise"; do
  grep -q "$s" "$out/b/report.md" || fail "report.md lacks '$s'"
done
grep -q "| commit | abc123 |" "$out/a/report.md" || fail "report.md lacks the commit"
# The roofline: a positive measured peak per thread count, and each counted kernel of the cases run
# with its flops, bytes, floors and measured times (numbers, not dashes).
grep -q "## Roofline: each kernel against this machine's ceilings" "$out/b/report.md" || fail "no roofline section"
for t in 1 2; do
  grep -Eq "^\| $t \| [0-9.]+ GB/s \| [1-9][0-9.]* GFLOP/s \| [0-9.]+ flop/B \|$" "$out/b/report.md" ||
    fail "no ceilings for $t thread(s)"
done
for k in 'mpm_mls \| mpm\.p2g' 'mpm_mls \| mpm\.g2p' 'peridynamics \| pd\.dilatation' 'peridynamics \| pd\.forces'; do
  grep -Eq "^\| $k \| [1-9][0-9]* \| [1-9][0-9]* \| [0-9.]+ \| (memory|compute) \| [0-9.]+ \| [0-9.]+ \| [0-9.]+ \| [0-9.]+ \| [0-9.]+ \(openmp x2\) \| [0-9.]+ \|$" \
    "$out/b/report.md" || fail "no roofline row for '$k'"
done
if grep -q "mpm_apic | mpm.p2g" "$out/b/report.md"; then fail "a roofline row for a case not run"; fi
if grep -q "## Repeatability" "$out/a/report.md"; then fail "a run without --compare has a repeatability section"; fi
# usage errors: exit 2 with the reason
set +e
msg=$("$amalgam" bench --report "$out/c" --cases nope 2>&1); rc=$?
set -e
[ $rc -eq 2 ] || fail "--cases nope exited $rc"
echo "$msg" | grep -q "unknown case 'nope' (known: mpm_mls," || fail "message: $msg"
set +e
msg=$("$amalgam" bench --report "$out/c" --compare "$out/missing.csv" 2>&1); rc=$?
set -e
[ $rc -eq 3 ] || fail "--compare of a missing file exited $rc"
echo "$msg" | grep -q "missing.csv: cannot open" || fail "message: $msg"
[ ! -e "$out/c/results.csv" ] || fail "a failed run wrote results"
echo "bench_report_test: ok"
