#!/usr/bin/env bash
# The GPU checks of issue 20, in one run on a machine with CUDA (an H100 or H200): the GPU
# kernels' tests (compiled, against the CPU kernels), where an iteration waits for the GPU,
# bench_optimize's cases on the GPU, the whole design job on the GPU (twice: the first compiles
# the kernel variants the job uses), the kernels' block sizes, a CUDA graph of an iteration
# and the large case; with GPU_CHECK_CPU=1 the same machine's CPU figures too. About 7
# minutes; the steps run in order of worth, so a run cut short still leaves the first ones'
# figures.
#
#   benchmarks/gpu_check.sh [OUT_DIR]      (PYTHON=python3 by default; logs and JSON in OUT_DIR)
#
# The project need not be installed: the checkout is put on PYTHONPATH (its dependencies must
# be importable; see benchmarks/README.md for a machine without a package index).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-outputs/gpu_check}
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
status=0

{
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    lscpu | grep -m1 "Model name"
    echo "CPUs: $(nproc)"
    "$py" -c "import torch, triton, numba; print('torch', torch.__version__, 'triton', \
triton.__version__, 'numba', numba.__version__)"
} 2>&1 | tee "$out/machine.txt"

# Numba compiles the CPU kernels once (cached beside the sources): in the background, while
# the GPU tests run, so that the CPU figures and the design job do not wait for it.
timeout 300 "$py" -m aperture_fab.pipeline.warm > "$out/warm.log" 2>&1 &

step() {  # step NAME SECONDS COMMAND...: one step, its output in $out/NAME.log
    local name=$1 limit=$2
    shift 2
    echo "== $name ($(date +%T))"
    timeout "$limit" "$@" 2>&1 | tee "$out/$name.log" || status=1
}
step tests 100 "$py" -m pytest tests/test_gpu_kernels.py -q -p no:cacheprovider -x
step syncs 45 "$py" benchmarks/profile_iteration.py --device cuda --syncs --iterations 3 \
    --cases nominal near-eye
step gpu 90 "$py" benchmarks/bench_optimize.py --repeats 1 --json "$out/gpu.json" \
    --device cuda --cases near-eye nominal seed-28
step design-first 150 "$py" benchmarks/bench_end_to_end.py --design-args "--device cuda" \
    --json "$out/design-first.json"
step design 120 "$py" benchmarks/bench_end_to_end.py --design-args "--device cuda" \
    --json "$out/design.json"
step blocks 60 "$py" benchmarks/probe_gpu_blocks.py --case near-eye
step graph 30 "$py" benchmarks/probe_cuda_graph.py
step gpu-large 40 "$py" benchmarks/bench_optimize.py --repeats 1 --json "$out/large.json" \
    --device cuda --large --cases large
wait
if [ -n "${GPU_CHECK_CPU:-}" ]; then  # the same machine's CPU figures (bench_optimize)
    step cpu 70 "$py" benchmarks/bench_optimize.py --repeats 1 --json "$out/cpu.json" \
        --device cpu --cases near-eye nominal
fi
exit $status
