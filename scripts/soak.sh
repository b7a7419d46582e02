#!/usr/bin/env bash
# Soak run: simulates SCENE for MINUTES wall-clock minutes (default scenes/soak_million.json, 30),
# samples the process's resident memory every 10 s, then stops it with SIGTERM (which writes a
# checkpoint) and prints RSS, allocated leaves and active leaves after warm-up: they must stay
# flat. Files: OUT/rss.csv (elapsed_s, rss_mb) and OUT/diagnostics.csv (per frame, with leaves and
# rss_mb columns). Usage: scripts/soak.sh [SCENE] [MINUTES] [THREADS]
# AMALGAM_SOAK_RESUME=CHECKPOINT continues an earlier soak (its checkpoint, copied elsewhere).
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
scene="${1:-$root/scenes/soak_million.json}"
minutes="${2:-30}"
threads="${3:-2}"
bin="${AMALGAM_BUILD_DIR:-$root/build}/bin/amalgam"
out="${AMALGAM_SOAK_OUT:-$root/out/soak}"
rm -rf "$out" && mkdir -p "$out"
resume=()
if [ -n "${AMALGAM_SOAK_RESUME:-}" ]; then resume=(--resume "$AMALGAM_SOAK_RESUME"); fi
"$bin" run "$scene" --threads "$threads" --quiet --out "$out" "${resume[@]}" &
pid=$!
echo "elapsed_s,rss_mb" > "$out/rss.csv"
start=$(date +%s)
end=$((start + minutes * 60))
while kill -0 "$pid" 2>/dev/null && [ "$(date +%s)" -lt "$end" ]; do
  rss_kb=$(ps -o rss= -p "$pid" 2>/dev/null || echo 0)
  echo "$(( $(date +%s) - start )),$(awk "BEGIN{printf \"%.1f\", ${rss_kb:-0} / 1024}")" >> "$out/rss.csv"
  sleep 10
done
kill -TERM "$pid" 2>/dev/null || true
wait "$pid" || true
# Summary: the first 10 % of the run is warm-up.
awk -F, 'NR > 1 { t[NR] = $1; r[NR] = $2; n = NR }
  END { w = int(n / 10) + 2; lo = 1e30; hi = 0
        for (i = w; i <= n; ++i) { if (r[i] < lo) lo = r[i]; if (r[i] > hi) hi = r[i] }
        printf "RSS after warm-up (%d samples, %d s to %d s): min %.1f MB, max %.1f MB, growth %.2f %%\n",
               n - w + 1, t[w], t[n], lo, hi, 100 * (hi - lo) / lo }' "$out/rss.csv"
awk -F, 'NR == 1 { for (i = 1; i <= NF; ++i) c[$i] = i; next }
  { n++; f[n] = $c["frame"]; l[n] = $c["leaves"]; a[n] = $c["active_leaves"]; s[n] = $c["substeps"]; tot += $c["substeps"] }
  END { w = int(n / 10) + 1; lmin = 1e30; lmax = 0; amin = 1e30; amax = 0
        for (i = w; i <= n; ++i) { if (l[i] < lmin) lmin = l[i]; if (l[i] > lmax) lmax = l[i]; if (a[i] < amin) amin = a[i]; if (a[i] > amax) amax = a[i] }
        printf "frames %d (%d substeps); after warm-up (frame %d on): allocated leaves %d..%d, active leaves %d..%d\n",
               n, tot, f[w], lmin, lmax, amin, amax }' "$out/diagnostics.csv"
