#!/usr/bin/env bash
# Set up a fresh Debian 12 machine (or a user's) for VESPRO: system libraries for
# MuJoCo's offscreen EGL rendering (Mesa, CPU), the Python package itself (with the
# benches' extra), then the tracker's compiled kernels, once (cached on disk).
set -euo pipefail
cd "$(dirname "$0")/.."
need=()
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libglib2.0-0; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  else
    echo "setup: please install these system packages: ${need[*]}" >&2
  fi
fi
python3 -m pip install -q --disable-pip-version-check -e '.[interop,view,bench]' 2>&1 | grep -v "Running pip as the 'root' user" || true
python3 -c "import vespro, servo, rtkit, cellsim"
python3 -m vespro.warmup
