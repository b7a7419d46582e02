#!/usr/bin/env bash
# The thread count follows the CPUs a process may run on (its affinity mask, as under mpirun's
# default binding), and asking for more threads than that is warned about, naming the fix.
# Usage: affinity_cli_test.sh AMALGAM SCENE OUTDIR [MPIEXEC]
set -u
amalgam=$1 scene=$2 out=$3 mpiexec=${4:-}
rm -rf "$out" && mkdir -p "$out"
[ "$(taskset -c 0 nproc)" = 1 ] || { echo "taskset cannot pin to one CPU here"; exit 1; }
info=$(taskset -c 0 "$amalgam" info) || { echo "info failed"; exit 1; }
echo "$info" | grep -Eq '^hardware threads: [0-9]+ \(this process may use 1\)$' ||
  { echo "info does not report the usable CPUs: $info"; exit 1; }
# Default thread count on one CPU: one thread, no warning.
log=$(taskset -c 0 "$amalgam" run "$scene" --frames 1 --out "$out/d" 2>&1) ||
  { echo "$log"; echo "run on one CPU failed"; exit 1; }
echo "$log" | grep -q "backend tbb x1," || { echo "$log"; echo "default threads on one CPU is not 1"; exit 1; }
echo "$log" | grep -q "warning" && { echo "$log"; echo "unexpected warning"; exit 1; }
# Two threads asked for on one CPU: they run (the user asked) and the warning says why it is slow.
log=$(taskset -c 0 "$amalgam" run "$scene" --frames 1 --threads 2 --out "$out/t" 2>&1) ||
  { echo "$log"; echo "run with 2 threads on one CPU failed"; exit 1; }
echo "$log" | grep -q "backend tbb x2," || { echo "$log"; echo "--threads 2 not honoured"; exit 1; }
echo "$log" | grep -q "amalgam: warning: 2 threads but this process may run on 1 CPU (its affinity mask)" ||
  { echo "$log"; echo "no warning for more threads than CPUs"; exit 1; }
# The same run on all CPUs (when there are 2 or more) warns of nothing.
if [ "$(nproc)" -ge 2 ]; then
  log=$("$amalgam" run "$scene" --frames 1 --threads 2 --out "$out/a" 2>&1) || { echo "$log"; exit 1; }
  echo "$log" | grep -q "warning" && { echo "$log"; echo "warning with enough CPUs"; exit 1; }
fi
# Under mpirun, 2 ranks are bound to a core each by default: each rank names itself and the fix.
if [ -n "$mpiexec" ]; then
  export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
  log=$(timeout 300 "$mpiexec" --oversubscribe --bind-to core -np 2 "$amalgam" run "$scene" \
    --frames 1 --threads 2 --out "$out/m" 2>&1) || { echo "$log"; echo "mpirun failed"; exit 1; }
  for r in 0 1; do
    echo "$log" | grep -q "amalgam: warning: 2 threads but MPI rank $r may run on 1 CPU (its affinity mask); the threads will share it. Start the ranks with \`mpirun --map-by slot:PE=2\` or \`--bind-to none\`" ||
      { echo "$log"; echo "no warning from rank $r"; exit 1; }
  done
fi
echo "threads follow the affinity mask; more threads than CPUs are warned about"
