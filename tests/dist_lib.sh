# Shared by the distributed CLI tests (dist_pd_test.sh, dist_mpm_test.sh), sourced after they set
# amalgam, mpiexec, scene and out. Each function prints what failed and returns 1.
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OMPI_MCA_rmaps_base_oversubscribe=1
# mpi NP ARGS...: amalgam ARGS on NP ranks; NP = 0: one process without mpirun.
mpi() {
  local np=$1
  shift
  if [ "$np" -eq 0 ]; then timeout 300 "$amalgam" "$@"; else
    timeout 300 "$mpiexec" --oversubscribe -np "$np" "$amalgam" "$@"; fi
}
# reference PATTERNS...: the single-process run into $out/ref; files: its files matching PATTERNS.
reference() {
  rm -rf "$out"
  "$amalgam" run "$scene" --threads 1 --out "$out/ref" --quiet || { echo "single-process run failed"; return 1; }
  files=$(cd "$out/ref" && ls $*)  # the patterns expand here, in the reference run
}
same() {  # same DIR: every reference file bitwise equal in DIR
  for f in $files; do cmp -s "$out/ref/$f" "$1/$f" || { echo "$f differs in $1"; return 1; }; done
}
# same_state DIR: diagnostics.csv's physical columns (the ones summed over every particle, exactly:
# ExactSum, so with no particle gathered) bitwise equal to the reference run's. Not compared: wall
# times, memory, and `leaves` (allocated leaves summed over the ranks: the ghost halo counts once
# per rank that holds it).
same_state() {
  local cols="kinetic_J elastic_J momentum_x momentum_y momentum_z max_speed_m_s particles active_leaves sleeping max_damage bonds intact_bonds"
  pick() {
    awk -F, -v want="$cols" 'BEGIN { n = split(want, w, " "); for (i = 1; i <= n; ++i) keep[w[i]] = 1 }
      NR == 1 { for (i = 1; i <= NF; ++i) if ($i in keep) c[++m] = i }
      { line = ""; for (k = 1; k <= m; ++k) line = line $c[k] ","; print line }' "$1"
  }
  [ "$(pick "$out/ref/diagnostics.csv")" = "$(pick "$1/diagnostics.csv")" ] ||
    { echo "diagnostics.csv's state columns differ in $1"; return 1; }
  [ "$(pick "$1/diagnostics.csv" | head -1 | tr -cd , | wc -c)" -ge 6 ] ||
    { echo "diagnostics.csv of $1 lacks the state columns"; return 1; }
}
# ranks_match: runs on 1-4 ranks of one thread and on 2 ranks of 2 TBB threads, each bitwise.
ranks_match() {
  for np in 1 2 3 4; do
    mpi $np run "$scene" --threads 1 --out "$out/np$np" --quiet || { echo "run on $np ranks failed"; return 1; }
    same "$out/np$np" && same_state "$out/np$np" || return 1
  done
  mpi 2 run "$scene" --threads 2 --backend tbb --out "$out/np2t2" --quiet || { echo "2 x 2 failed"; return 1; }
  same "$out/np2t2" && same_state "$out/np2t2"
}
# resumes NP FRAMES NP2...: a checkpoint after FRAMES frames on NP ranks, resumed to the end on
# each NP2 (0: one process), bitwise.
resumes() {
  local np=$1 frames=$2
  shift 2
  mpi "$np" run "$scene" --threads 1 --frames "$frames" --out "$out/c$np" --quiet || { echo "$np-rank part failed"; return 1; }
  for np2 in "$@"; do
    rm -rf "$out/c$np-$np2" && cp -r "$out/c$np" "$out/c$np-$np2"
    mpi "$np2" run "$scene" --threads 1 --out "$out/c$np-$np2" --resume "$out/c$np-$np2/checkpoint.amck" --quiet ||
      { echo "resume of $np ranks on $np2 failed"; return 1; }
    same "$out/c$np-$np2" || return 1
  done
}
# refused NP SCENE DIR TEXT: SCENE on NP ranks stops with exit 3 and TEXT in its message, before
# any frame is written into DIR.
refused() {
  local msg rc
  msg=$(mpi "$1" run "$2" --out "$3" --quiet 2>&1)
  rc=$?
  [ $rc -eq 3 ] || { echo "$2 on $1 ranks exited $rc, expected 3: $msg"; return 1; }
  echo "$msg" | grep -qF "$4" || { echo "unclear message: $msg"; return 1; }
  ls "$3"/frame_* >/dev/null 2>&1 && { echo "$2 on $1 ranks wrote frames"; return 1; }
  return 0
}
# interrupted NP SUBSTEP NP2: SIGINT at the SUBSTEP-th substep on NP ranks: every rank stops with
# 130, one checkpoint, no half-written file; resumed on NP2 ranks, bitwise.
interrupted() {
  AMALGAM_TEST_SIGINT_AT_SUBSTEP=$2 mpi "$1" run "$scene" --threads 1 --out "$out/int" --quiet 2>/dev/null
  local rc=$?
  [ $rc -eq 130 ] || { echo "interrupted run on $1 ranks exited $rc, expected 130"; return 1; }
  [ -f "$out/int/checkpoint.amck" ] || { echo "no checkpoint after the interrupt"; return 1; }
  ls "$out/int"/*.tmp >/dev/null 2>&1 && { echo "half-written files left"; return 1; }
  mpi "$3" run "$scene" --threads 1 --out "$out/int" --resume "$out/int/checkpoint.amck" --quiet ||
    { echo "resume after the interrupt failed"; return 1; }
  same "$out/int"
}
# Per-rank output (`run --parts ranks`): every rank writes its part of each frame and checkpoint,
# rank 0 the manifests; `amalgam merge` joins them into the single process's files.
# parts_match NP...: runs on each NP with per-rank parts, merged: bitwise the single process's
# files (the checkpoint included: the joined parts are its bytes).
parts_match() {
  for np in "$@"; do
    mpi "$np" run "$scene" --threads 1 --parts ranks --out "$out/parts$np" --quiet || { echo "parts run on $np ranks failed"; return 1; }
    ls "$out/parts$np"/frame_0001.r000.pts "$out/parts$np"/frame_0001.manifest.json >/dev/null || { echo "no parts or manifest on $np ranks"; return 1; }
    "$amalgam" merge "$out/parts$np" >/dev/null || { echo "merge of $np ranks failed"; return 1; }
    same "$out/parts$np" && same_state "$out/parts$np" || return 1
  done
}
# parts_resumes NP FRAMES NP2...: a per-rank checkpoint after FRAMES frames on NP ranks (0: one
# process), resumed with per-rank parts on each NP2, merged: bitwise.
parts_resumes() {
  local np=$1 frames=$2
  shift 2
  mpi "$np" run "$scene" --threads 1 --parts ranks --frames "$frames" --out "$out/pc$np" --quiet || { echo "$np-rank parts run failed"; return 1; }
  head -c 1 "$out/pc$np/checkpoint.amck" | grep -q '{' || { echo "no checkpoint manifest on $np ranks"; return 1; }
  for np2 in "$@"; do
    rm -rf "$out/pc$np-$np2" && cp -r "$out/pc$np" "$out/pc$np-$np2"
    mpi "$np2" run "$scene" --threads 1 --parts ranks --out "$out/pc$np-$np2" --resume "$out/pc$np-$np2/checkpoint.amck" --quiet ||
      { echo "parts resume of $np ranks on $np2 failed"; return 1; }
    "$amalgam" merge "$out/pc$np-$np2" >/dev/null || { echo "merge after the resume $np -> $np2 failed"; return 1; }
    same "$out/pc$np-$np2" || { echo "(resume $np -> $np2 ranks with parts)"; return 1; }
  done
}
# parts_interrupted NP SUBSTEP NP2: SIGINT at the SUBSTEP-th substep on NP ranks with per-rank
# parts: exit 130 and a checkpoint manifest; resumed on NP2 ranks and merged, bitwise.
parts_interrupted() {
  AMALGAM_TEST_SIGINT_AT_SUBSTEP=$2 mpi "$1" run "$scene" --threads 1 --parts ranks --out "$out/pint" --quiet 2>/dev/null
  local rc=$?
  [ $rc -eq 130 ] || { echo "interrupted parts run on $1 ranks exited $rc, expected 130"; return 1; }
  head -c 1 "$out/pint/checkpoint.amck" | grep -q '{' || { echo "no checkpoint manifest after the interrupt"; return 1; }
  mpi "$3" run "$scene" --threads 1 --parts ranks --out "$out/pint" --resume "$out/pint/checkpoint.amck" --quiet ||
    { echo "resume of the interrupted parts run failed"; return 1; }
  "$amalgam" merge "$out/pint" >/dev/null || { echo "merge after the interrupt failed"; return 1; }
  same "$out/pint"
}
