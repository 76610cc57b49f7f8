#!/usr/bin/env bash
# The JAX kernels and the pipeline on an accelerator and on the same machine's CPUs, in one run, so that
# the two can be compared as ratios (figures in benchmarks/README.md, "Accelerator").
#
# Usage, from the repository root on a machine whose python has jax with CUDA and the project's
# dependencies (meshio and pytetwild are not needed here):
#     bash benchmarks/bench_device.sh [PYTHON [PARTS]]   # default: python3 "truss pipeline"; logs also go to $OUT
# Runs: the truss benchmark at 103,823 nodes (47^3) and 857,375 nodes (95^3) on the accelerator, the
# 47^3 one on the CPU (JAX_PLATFORMS=cpu), then the whole pipeline on a 40-sphere RVE both ways.
set -uo pipefail
TIMEFORMAT="# wall %R s"
py=${1:-python3}
parts=${2:-truss pipeline}
out=${OUT:-/tmp/jaxmesh_device}
mkdir -p "$out"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
{
    date -u +"# %Y-%m-%d %H:%M UTC"
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
    echo "# $(nproc) CPU cores, $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 2^20}' /proc/meminfo)"
    "$py" -c "import jax; print('# jax', jax.__version__, jax.devices())"
} 2>&1 | tee "$out/machine.log"

run() {  # name, then the command
    local name=$1
    shift
    echo "## $name"
    { time "$@"; } 2>&1 | tee "$out/$name.log"
}

if [[ " $parts " == *" truss "* ]]; then
    run truss_gpu_47 "$py" benchmarks/bench_truss.py --n 47 --steps 20 --repeat 3
    run truss_cpu_47 env JAX_PLATFORMS=cpu "$py" benchmarks/bench_truss.py --n 47 --steps 20 --repeat 3
    run truss_gpu_95 "$py" benchmarks/bench_truss.py --n 95 --steps 20 --repeat 3
fi
if [[ " $parts " == *" pipeline "* ]]; then
    rve=(--n 40 --volume-fraction 0.35 --radius 0.08 0.015 --min-gap 0.02 --grid 64 --iis 0.05 --nb-el 1)
    run pipeline_gpu "$py" benchmarks/bench_pipeline.py "${rve[@]}"
    run pipeline_cpu env JAX_PLATFORMS=cpu "$py" benchmarks/bench_pipeline.py "${rve[@]}"
fi
