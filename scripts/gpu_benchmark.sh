#!/usr/bin/env bash
# The GPU rows of docs/results.md, in one run on a machine with one CUDA device and at least 8 cores:
# training steps on the GPU (torchdiffeq, compiled, compiled replayed as CUDA graphs) and on 2 of the
# same machine's cores (pinned, beside them), then the GPU tests and a profile of a GPU step.
#
#     bash scripts/gpu_benchmark.sh OUT     (about 8 minutes: each part has its own time limit)
#
# OUT receives steps-gpu.json, steps-cpu2.json and the logs; merge the JSON files into
# results/speed/steps.json and run `python scripts/speed_benchmark.py table` to update the docs.
set -u
out=$1
work=$(mktemp -d)
mkdir -p "$out"
export PYTHONUNBUFFERED=1
command -v taskset >/dev/null || taskset() { shift 2; "$@"; }
cpu2() { taskset -c 2,3 env OMP_NUM_THREADS=2 CUDA_VISIBLE_DEVICES= TORCHINDUCTOR_CACHE_DIR="$work/inductor-cpu" "$@"; }
gpu() { taskset -c 4-15 env TORCHINDUCTOR_CACHE_DIR="$work/inductor-gpu" "$@"; }
steps=(python scripts/speed_benchmark.py steps --rounds 1 --out)
keep() { cp "$work/$1/steps.json" "$out/steps-$1.json" 2>/dev/null; }

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; python -c "import torch; print(torch.__version__)"; } >"$out/machine.log" 2>&1

(
    cpu2 timeout -k 10 180 "${steps[@]}" "$work/cpu2" --configs pendulum --label cpu2 --steps 30
    keep cpu2
    cpu2 timeout -k 10 270 "${steps[@]}" "$work/cpu2" --configs reactdiff --label cpu2 --steps 20
    keep cpu2
) >"$out/cpu2.log" 2>&1 &

{
    gpu timeout -k 10 220 "${steps[@]}" "$work/gpu" --configs pendulum --label gpu --steps 30 \
        --solvers torchdiffeq compiled compiled-cuda-graphs -- --trainer.accelerator=gpu
    keep gpu
    gpu timeout -k 10 150 "${steps[@]}" "$work/gpu" --configs reactdiff --label gpu --steps 20 -- --trainer.accelerator=gpu
    keep gpu
} >"$out/gpu.log" 2>&1

gpu timeout -k 10 80 python -m pytest -m gpu tests/test_gpu.py -q -p no:cacheprovider >"$out/pytest-gpu.log" 2>&1
gpu timeout -k 10 70 python scripts/profile_step.py --config configs/pendulum.yaml --device cuda --steps 10 --trace 30 \
    >"$out/profile-gpu.log" 2>&1
wait
keep cpu2
keep gpu
