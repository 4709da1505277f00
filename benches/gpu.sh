#!/usr/bin/env bash
# The GPU check, run as it is on a machine with an NVIDIA GPU (CUDA toolkit and driver) and a
# Vulkan driver: builds `pipe` with the GPU backends, holds every compiled-in engine to the CPU
# reference (the parity tests), then runs the full-size bench once per GPU backend and prints the
# figures (per-stage wall time, CPU, peak RSS; mIoU, PQ, depth against the baselines).
#
#   bash benches/gpu.sh                 # both backends
#   BACKENDS=cuda bash benches/gpu.sh   # one
#   SUITE=quick bash benches/gpu.sh     # a smaller suite (minutes)
#
# Results: bench-results/gpu-<backend>/ (REPORT.md, report.html, results.parquet) and a summary
# at the end of the output. Exit code 1 if a build, a test or a bench fails.
set -euo pipefail
cd "$(dirname "$0")/.."

BACKENDS=${BACKENDS:-"cuda wgpu"}
SUITE=${SUITE:-full}
FEATURES=$(echo "$BACKENDS" | tr ' ' ',')
CACHE=${CACHE:-$PWD/.pipe-gpu}

echo "== machine"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || echo "(no nvidia-smi)"
nproc
free -g | head -2

echo "== build (features: $FEATURES)"
cargo build --release --features "$FEATURES"

echo "== parity: every engine against the CPU reference (features: $FEATURES)"
cargo test --release -p stages --features "$FEATURES" --lib model::parity

for b in $BACKENDS; do
    echo "== bench --suite $SUITE, train and render on $b"
    # Rendering follows the training engine when it is a GPU; named here all the same.
    ./target/release/pipe bench --suite "$SUITE" --cache "$CACHE" \
        --set train.backend="$b" --set render.backend="$b" \
        --out "bench-results/gpu-$b"
done

echo "== summary"
for b in $BACKENDS; do
    echo "--- $b: bench-results/gpu-$b/REPORT.md"
    sed -n '/^## /,$p' "bench-results/gpu-$b/REPORT.md" | head -80
done
