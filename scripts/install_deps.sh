#!/usr/bin/env bash
# Installs every build/test dependency of Amalgam from Debian packages.
# Safe to run any number of times: apt-get skips what is already installed.
#   scripts/install_deps.sh           build/test dependencies (what CI installs)
#   scripts/install_deps.sh --render  also Blender (scripts/render_blender.sh, the render smoke
#                                     test); opt-in because it is large and CI does not need it
set -euo pipefail

RENDER=0
for a in "$@"; do
  case "$a" in
    --render) RENDER=1 ;;
    *) echo "install_deps.sh: unknown option '$a' (only --render)" >&2; exit 2 ;;
  esac
done

PKGS=(
  build-essential cmake ninja-build pkg-config
  libopenvdb-dev libboost-iostreams-dev libtbb-dev libimath-dev libblosc-dev zlib1g-dev
  libeigen3-dev nlohmann-json3-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  libcgal-demo tetgen
  clang-format             # format.check (scripts/check_format.sh): Debian 12 ships clang-format 14
  clang libclang-rt-14-dev libomp-dev  # the clang sanitizer + libFuzzer build (scripts/build_sanitized.sh):
                                       # compiler-rt's ASan/UBSan/libFuzzer, LLVM's OpenMP (clang's -fopenmp)
  libtrilinos-kokkos-dev   # the optional Kokkos exec backend (Kokkos 3.4.1, Serial space)
  libopenmpi-dev openmpi-bin libtrilinos-zoltan-dev  # distributed runs: MPI ranks, Zoltan partitioning
  python3                  # tests/dup_part_id.py (a hostile per-rank checkpoint), bench/*.py
)
# Debian 12's blender 3.4.1: headless Cycles renders of surfaced frames (no OpenImageDenoise).
[ "$RENDER" -eq 1 ] && PKGS+=(blender)

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null 2>&1 && SUDO="sudo" || { echo "install_deps.sh: need root or sudo to run apt-get" >&2; exit 1; }
fi

missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install_deps.sh: all ${#PKGS[@]} packages already installed"
  exit 0
fi

echo "install_deps.sh: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
echo "install_deps.sh: done"
