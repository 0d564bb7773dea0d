#!/usr/bin/env bash
# The GPU checks of issue 20, in one run on a machine with CUDA (an H100 or H200): the GPU
# kernels' tests (compiled, against the CPU kernels) and bench_optimize's cases on the GPU, then
# the same machine's CPU figures beside them, and a profile of an iteration. About 5 minutes.
#
#   benchmarks/gpu_check.sh [OUT_DIR]      (PYTHON=python3 by default; logs and JSON in OUT_DIR)
#
# Each benchmark case runs on its own, so that one failing case still leaves the others' figures.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-outputs/gpu_check}
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
status=0

{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    lscpu | grep -m1 "Model name"
    echo "CPUs: $(nproc)"
    "$py" -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__)"
} 2>&1 | tee "$out/machine.txt"

echo "== GPU kernel tests"
timeout 200 "$py" -m pytest tests/test_gpu_kernels.py tests/test_kernels.py -q \
    -p no:cacheprovider 2>&1 | tail -15 | tee "$out/tests.log" || status=1

bench() {  # bench NAME SECONDS ARGS...: one bench_optimize run, its log and JSON under $out
    local name=$1 limit=$2
    shift 2
    echo "== bench $name"
    timeout "$limit" "$py" benchmarks/bench_optimize.py --repeats 1 --json "$out/$name.json" "$@" \
        2>&1 | tee "$out/$name.log" || status=1
}
bench gpu-near-eye 200 --device cuda --cases near-eye nominal nominal-torch
bench gpu-large 90 --device cuda --large --cases large
bench gpu-seed 60 --device cuda --cases seed-28
bench cpu 120 --device cpu --cases near-eye nominal seed-28
echo "== profile"
(cd benchmarks && timeout 90 "$py" profile_iteration.py --device cuda --cases near-eye nominal \
    seed-28) > "$out/profile.log" 2>&1 || status=1
echo "== CUDA graph probe"
timeout 90 "$py" benchmarks/probe_cuda_graph.py 2>&1 | tee "$out/graph.log" || status=1
exit $status
