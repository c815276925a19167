#!/usr/bin/env bash
# Builds dsrl-train with candle's CUDA backend (`--features cuda`) on a machine without a system CUDA: the compiler,
# runtime, cuBLAS, cuRAND and NVRTC come from PyPI's nvidia-* wheels (CUDA 13.0, pinned together: nvvm 13.5 emits
# PTX 9.5, which ptxas 13.0 refuses) in a cached virtual environment. The kernels compile for one compute capability
# (90: H100 and H200). The binary needs a GPU driver at run time only; it loads libcuda.so.1 from the driver.
# Out of CI (~12 minutes of kernel compilation on 2 cores, ~2 GB of wheels); CI builds the default, CPU-only binary.
# Usage: scripts/build-cuda.sh [COMPUTE_CAP]   -> <target>/cuda/release/dsrl-train (stripped)
set -euo pipefail
cd "$(dirname "$0")/.."
cap=${1:-90}
env_dir=${DSRL_CUDA_ENV:-$HOME/.cache/dsrl/cuda-13.0}
target=${CARGO_TARGET_DIR:-target}/cuda
if [ ! -x "$env_dir/bin/python" ]; then
  echo "creating $env_dir for CUDA 13.0 from PyPI" >&2
  python3 -m venv "$env_dir"
fi
echo "installing CUDA 13.0 (nvcc, runtime, crt, cccl, nvvm, cuBLAS, NVRTC, cuRAND) into $env_dir" >&2
"$env_dir/bin/pip" install --quiet --disable-pip-version-check \
  "nvidia-cuda-nvcc==13.0.*" "nvidia-cuda-runtime==13.0.*" "nvidia-cuda-crt==13.0.*" "nvidia-cuda-cccl==13.0.*" \
  "nvidia-nvvm==13.0.*" "nvidia-cublas==13.0.*" "nvidia-cuda-nvrtc==13.0.*" nvidia-curand
site=$("$env_dir/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
export CUDA_ROOT=$site/nvidia/cu13
[ -x "$CUDA_ROOT/bin/nvcc" ] || { echo "no nvcc under $CUDA_ROOT: the wheels' layout changed" >&2; exit 1; }
# The wheels ship versioned libraries only (libcublas.so.13, ...); the linker wants the unversioned names. libcuda
# comes from the driver, which this machine may not have: link against a stub whose soname is the driver's.
links=$env_dir/link
mkdir -p "$links"
for lib in "$CUDA_ROOT"/lib/lib*.so.*; do
  base=$(basename "$lib")
  ln -sf "$lib" "$links/${base%%.so.*}.so"
done
# The stub defines every driver function of cudarc's bindings (cudarc links them; the driver's library answers them at
# run time, so the stub is never loaded).
cargo fetch --locked >&2
cudarc=$(ls -d "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/cudarc-0.19.* | tail -1)
echo "making a link-time stub libcuda.so (soname libcuda.so.1) from $cudarc's driver functions" >&2
grep -ohE "pub unsafe fn cu[A-Za-z0-9_]+" "$cudarc/src/driver/sys/mod.rs" | sort -u \
  | sed -E 's/pub unsafe fn (.*)/void \1(void) {}/' > "$links/stub.c"
cc -shared -fPIC -Wl,-soname,libcuda.so.1 -o "$links/libcuda.so" "$links/stub.c"
export PATH=$CUDA_ROOT/bin:$PATH CUDA_COMPUTE_CAP=$cap
export LIBRARY_PATH=$links:$CUDA_ROOT/lib${LIBRARY_PATH:+:$LIBRARY_PATH}
export RUSTFLAGS="${RUSTFLAGS:-} -L native=$links"
echo "building dsrl-train --features cuda for compute capability $cap into $target (the kernels take a while)" >&2
CARGO_TARGET_DIR=$target cargo build --release --locked -p dsrl-train --features cuda
strip "$target/release/dsrl-train"
echo "built $target/release/dsrl-train ($(du -h "$target/release/dsrl-train" | cut -f1)); run it on a GPU machine" \
  "with the driver's libcuda.so.1 and the wheels' libraries on LD_LIBRARY_PATH ($CUDA_ROOT/lib)" >&2
