#!/usr/bin/env bash
# The GPU rows of docs/results.md, in one run on a machine with one CUDA device and at least 8 cores:
# training steps on the GPU (torchdiffeq, compiled, compiled replayed as CUDA graphs) and on 2 of the
# same machine's cores (pinned, beside them), then the GPU tests and a profile of a GPU step.
#
#     bash scripts/gpu_benchmark.sh OUT [SECONDS]
#
# SECONDS (default 540) bounds the whole run: each part runs under its own limit, cut to what is
# left, and is killed 10 s after it (Lightning's SIGTERM handler lets a run outlive a plain timeout).
# Each part copies its results to OUT as it ends, so a run cut short keeps what it measured.
# OUT receives steps-gpu.json, steps-cpu2.json and the logs; merge the JSON files into
# results/speed/steps.json and run `python scripts/speed_benchmark.py table` to update the docs.
# Wheels in .whl/ (packages the machine lacks, e.g. jsonargparse) are installed into a temporary
# folder first; on a machine whose interpreter is `python3` only, a `python` that execs it is put on
# PATH (a script, not a symbolic link: a link to a virtual environment's interpreter loses the
# environment).
set -u
out=$1
deadline=$((SECONDS + ${2:-540}))
work=$(mktemp -d)
mkdir -p "$out"
export PYTHONUNBUFFERED=1
if ! command -v python >/dev/null; then
    mkdir -p "$work/bin" && printf '#!/bin/sh\nexec %s "$@"\n' "$(command -v python3)" >"$work/bin/python"
    chmod +x "$work/bin/python" && export PATH="$work/bin:$PATH"
fi
if compgen -G ".whl/*.whl" >/dev/null; then
    python -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$work/site" .whl/*.whl ||
        echo "gpu_benchmark.sh: the wheels in .whl/ do not install here (pip's reason above); going on without them" >&2
fi
export PYTHONPATH="$work/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
# Pin the two CPU runs and the GPU runs apart where the machine has the cores (and taskset) for it.
if ! command -v taskset >/dev/null || (($(nproc) < 16)); then taskset() { shift 2; "$@"; }; fi
limited() {  # limited SECONDS PLACE COMMAND...: on PLACE (cpu2 or gpu), at most SECONDS and never past the deadline
    local left=$((deadline - SECONDS - 15))
    local limit=$(($1 < left ? $1 : left)) place=$2
    shift 2
    ((limit > 0)) && "$place" timeout -k 10 "$limit" "$@"
}
cpu2() { taskset -c 2,3 env OMP_NUM_THREADS=2 CUDA_VISIBLE_DEVICES= TORCHINDUCTOR_CACHE_DIR="$work/inductor-cpu" "$@"; }
gpu() { taskset -c 4-15 env TORCHINDUCTOR_CACHE_DIR="$work/inductor-gpu" "$@"; }
steps=(python scripts/speed_benchmark.py steps --rounds 1 --out)
keep() { cp "$work/$1/steps.json" "$out/steps-$1.json" 2>/dev/null; }

{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; python -c "import torch; print(torch.__version__)"; } >"$out/machine.log" 2>&1

(
    limited 150 cpu2 "${steps[@]}" "$work/cpu2" --configs pendulum --label cpu2 --steps 30
    keep cpu2
    limited 200 cpu2 "${steps[@]}" "$work/cpu2" --configs reactdiff --label cpu2 --steps 20
    keep cpu2
) >"$out/cpu2.log" 2>&1 &

{  # reaction-diffusion first: its compile is the long part
    limited 270 gpu "${steps[@]}" "$work/gpu" --configs reactdiff --label gpu --steps 20 -- --trainer.accelerator=gpu
    keep gpu
    limited 150 gpu "${steps[@]}" "$work/gpu" --configs pendulum --label gpu --steps 30 \
        --solvers torchdiffeq compiled -- --trainer.accelerator=gpu
    keep gpu
} >"$out/gpu.log" 2>&1

limited 90 gpu python -m pytest -m gpu tests/test_gpu.py -q -n0 -p no:cacheprovider >"$out/pytest-gpu.log" 2>&1
limited 30 gpu python scripts/profile_step.py --config configs/pendulum.yaml --device cuda --steps 10 --trace 30 \
    >"$out/profile-gpu.log" 2>&1
wait
keep cpu2
keep gpu
