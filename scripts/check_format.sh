#!/usr/bin/env bash
# Checks that every C++ source git tracks is formatted by the repository's .clang-format (run by
# ctest as format.check; Debian's clang-format 14, installed by scripts/install_deps.sh).
# `scripts/check_format.sh --fix` formats them in place.
set -uo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
command -v clang-format >/dev/null || { echo "format: clang-format not found (scripts/install_deps.sh installs it)"; exit 1; }
files=$(git ls-files '*.cpp' '*.hpp' '*.h' 2>/dev/null || find core sparse_grid kernels solvers io apps bench tests -name '*.[ch]pp')
if [ "${1:-}" = "--fix" ]; then
  clang-format -i --style=file $files
  exit 0
fi
bad=0
for f in $files; do
  if ! clang-format --style=file "$f" | cmp -s - "$f"; then
    echo "format: $f differs from .clang-format (scripts/check_format.sh --fix)"
    bad=1
  fi
done
[ "$bad" = 0 ] && echo "format: ok ($(echo $files | wc -w) files)"
exit "$bad"
