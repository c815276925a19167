#!/usr/bin/env bash
# Installs the system packages the build needs (Debian): libhdf5-dev (DSRL HDF5 import/export), pkg-config, and
# the headless OpenGL that draws replayed episodes (libegl1 + libegl-mesa0 + libgl1-mesa-dri: MuJoCo renders
# Safety-Gymnasium through EGL on Mesa's software rasterizer);
# with --tests also what the tests need: chromium (the leaderboard page is checked in headless Chromium) and
# postgresql (the replica tests start their own server in a temporary folder; the package's cluster is not used)
# and openssl (they make that server's TLS certificates).
# Idempotent: does nothing when they are present.
set -euo pipefail
"$(dirname "$0")/ensure-dev-null.sh"
need=()
dpkg -s libhdf5-dev >/dev/null 2>&1 || need+=(libhdf5-dev)
dpkg -s pkg-config >/dev/null 2>&1 || need+=(pkg-config)
for package in libegl1 libegl-mesa0 libgl1-mesa-dri; do
  dpkg -s "$package" >/dev/null 2>&1 || need+=("$package")
done
if [ "${1:-}" = "--tests" ]; then
  dpkg -s chromium >/dev/null 2>&1 || need+=(chromium)
  dpkg -s postgresql >/dev/null 2>&1 || need+=(postgresql)
  dpkg -s openssl >/dev/null 2>&1 || need+=(openssl)
fi
if [ ${#need[@]} -eq 0 ]; then
  exit 0
fi
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
echo "installing system packages: ${need[*]}" >&2
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
