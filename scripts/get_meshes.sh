#!/usr/bin/env bash
# Extracts the armadillo, bunny and Chinese dragon meshes (OFF) from Debian's libcgal-demo package
# (its data.tar.gz) into DEST (default: scenes/meshes). Installs the package if it is missing.
# Safe to run again.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
dest="${1:-$root/scenes/meshes}"
tarball=/usr/share/doc/libcgal-dev/data.tar.gz
if [ ! -f "$tarball" ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO=sudo
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends libcgal-demo
fi
mkdir -p "$dest"
tar xzf "$tarball" -C "$dest" --strip-components=2 \
  data/meshes/armadillo.off data/meshes/bunny00.off data/meshes/ChineseDragon-10kv.off
echo "get_meshes.sh: armadillo.off bunny00.off ChineseDragon-10kv.off in $dest"

# Tetrahedral meshes for the peridynamics scenes (TetGen, Debian package tetgen): a glass plate
# 0.4 x 0.012 x 0.4 m (scenes/pd_glass_press.json, PD paper Fig. 15), about 55k tetrahedra.
if command -v tetgen >/dev/null 2>&1; then
  if [ ! -f "$dest/glass_plate.1.ele" ]; then
    cat > "$dest/glass_plate.off" <<'MESH'
OFF
8 12 0
0 0 0
0 0 0.4
0 0.012 0
0 0.012 0.4
0.4 0 0
0.4 0 0.4
0.4 0.012 0
0.4 0.012 0.4
3 0 1 3
3 0 3 2
3 4 6 7
3 4 7 5
3 0 4 5
3 0 5 1
3 2 3 7
3 2 7 6
3 0 2 6
3 0 6 4
3 1 5 7
3 1 7 3
MESH
    tetgen -Qpq1.4a1e-7 "$dest/glass_plate.off"
  fi
  echo "get_meshes.sh: glass_plate.1.node/.ele (TetGen) in $dest"
else
  echo "get_meshes.sh: tetgen not installed (scripts/install_deps.sh installs it): no tetrahedral meshes" >&2
fi
