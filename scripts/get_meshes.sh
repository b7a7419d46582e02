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
