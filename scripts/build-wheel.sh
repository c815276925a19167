#!/usr/bin/env bash
# Builds the Python package's release wheel: one abi3 wheel (CPython 3.9 and later) for this platform, tagged
# manylinux_2_34 after maturin checks the extension's symbol versions (client/python/pyproject.toml). It links only
# libc, libm and libgcc_s: no libhdf5, no libpython, nothing to compile where it is installed.
#
#   scripts/build-wheel.sh [OUT=dist]       # prints the wheel's path and sha256
#   pip install dist/dsrl_client-*.whl      # on any glibc >= 2.34 x86-64 machine, without Rust
#
# Publishing (not done from here): upload the wheels of each platform with `maturin upload` (or twine) to PyPI, or
# attach them to a release; users then `pip install dsrl-client`. Building for older systems needs this script run
# in a manylinux_2_28 container (quay.io/pypa/manylinux_2_28_x86_64) with compatibility set to manylinux_2_28.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-dist}
[ -x .venv/bin/maturin ] || { echo "no .venv/bin/maturin: run scripts/setup-python.sh first" >&2; exit 1; }
mkdir -p "$out"
echo "building the release wheel (the Rust client, optimized: minutes on 2 cores)" >&2
.venv/bin/maturin build --release -m client/python/Cargo.toml -i .venv/bin/python -o "$out" >&2
wheel=$(ls -t "$out"/dsrl_client-*-abi3-manylinux_*.whl | head -1)
echo "$wheel $(sha256sum "$wheel" | cut -d' ' -f1)"
