#!/usr/bin/env bash
# Checks the layering of docs/architecture.md on the sources (run by ctest as layers.check):
#   core/ (exec, math, materials, particles, geometry) <- sparse_grid/ <- kernels/ <- solvers/ <- io/ <- apps/
# A layer includes only from layers to its left. Also: threading only in core/exec/ (kernels call
# exec::parallel_for), and each solver file belongs to one method family.
# Prints every violation and exits 1 if there is any.
set -uo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bad=0
fail() { echo "layers: $*"; bad=1; }

# Includes allowed from each layer (a project include is "dir/...").
check_includes() {
  local layer="$1" allowed="$2" f inc top
  for f in $(find "$layer" -name '*.cpp' -o -name '*.hpp' | sort); do
    while IFS= read -r inc; do
      top="${inc%%/*}"
      [ "$top" = "$inc" ] && continue  # same-folder or system include
      case " $allowed " in *" $top "*) ;; *) fail "$f includes $inc ($layer/ may include only: $allowed)";; esac
    done < <(sed -n 's/^#include "\([^"]*\)".*/\1/p' "$f")
  done
}
check_includes core "core"
check_includes sparse_grid "core sparse_grid"
check_includes kernels "core sparse_grid kernels"
check_includes solvers "core sparse_grid kernels solvers"
check_includes io "core sparse_grid solvers io"
check_includes apps "core sparse_grid kernels solvers io apps"

# Threading code lives in core/exec only.
stray=$(grep -rnE '#pragma omp|tbb::parallel_for|tbb::task_arena|std::thread\b' --include='*.cpp' --include='*.hpp' \
        core sparse_grid kernels solvers io apps | grep -v '^core/exec/')
[ -n "$stray" ] && fail "threading outside core/exec/:"$'\n'"$stray"

# One method family per solver and kernel file: MPM files (explicit core, implicit, A-ULMPM,
# enriched) never name peridynamics, and peridynamics files never name MPM's solver.
for f in $(find solvers kernels -name '*.cpp' -o -name '*.hpp' | sort); do
  case "$f" in
    # the seam, the factory, the run estimate and the catalogue of benchmark cases see every method
    */simulation.hpp|*/factory.*|*/estimate.*|*/scene_spec.*|*/bench_suite.*) continue ;;
  esac
  if grep -qE 'PdSolver|pd_[a-z_]*\(|PdBonds' "$f" && grep -qE 'MpmSolver|MpmGridView|p2g\(' "$f"; then
    fail "$f mixes MPM and peridynamics"
  fi
done

[ "$bad" = 0 ] && echo "layers: ok"
exit "$bad"
