#!/usr/bin/env bash
# The checks of issue 32 that need a GPU, as one script for a lent GPU machine (run from the repository root;
# results under $OUT). That machine has torch with CUDA but not TorchRL or PettingZoo and no network: their
# wheels for its Python go in gpu_wheels/ (pip download --no-deps --only-binary=:all: --python-version 3.12
# torchrl==0.14.1 tensordict==0.14.3 orjson pyvers importlib_metadata hoptorch pettingzoo==1.27.0 gymnasium==1.4.0
# farama-notifications), the scenes in SCENES (a few shards of a generated scene cache).
#   1. tests/test_env_device.py: both faces on device="cuda" (check_env_specs; every returned tensor on the GPU)
#   2. benchmarks/env_throughput.py --device cuda: the PettingZoo env and the TorchRL env side by side
#   3. smart-marl finetune on device="cuda" (the scale config, 256 scenes stepped together, a few iterations)
set -u
OUT=${OUT:-runs/gpu}
SCENES=${SCENES:-gpu_scenes}
mkdir -p "$OUT"
. benchmarks/gpu_common.sh
gpu_packages gpu_wheels "$OUT/pip.log"
export PYTHONPATH=/tmp/pk:$PWD
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader > "$OUT/gpu.txt" 2>&1
timeout "${T_TESTS:-90}" python3 -m pytest -q -p no:cacheprovider tests/test_env_device.py > "$OUT/test_env_device.txt" 2>&1
echo "tests rc=$?" >> "$OUT/test_env_device.txt"
timeout "${T_BENCH:-150}" python3 benchmarks/env_throughput.py --device cuda --threads 8 --scenes "$SCENES" \
    --num-scenes "${NUM_SCENES:-256,1024}" --steps 16 --repeats 2 > "$OUT/env_throughput_cuda.jsonl" 2> "$OUT/env_throughput_cuda.err"
echo "bench rc=$?" >> "$OUT/env_throughput_cuda.err"
# (the Python API: `smart-marl finetune` is registered through the installed package's entry points)
timeout "${T_FT:-150}" python3 - "$SCENES" "$OUT" > "$OUT/finetune_cuda.log" 2>&1 <<PY
import json, os, sys
from agents.finetune import finetune, load_finetune_config
scenes, out = sys.argv[1], sys.argv[2]
over = [f'scenes=["{scenes}"]', "num_scenes=${FT_SCENES:-48}", "num_envs=${FT_ENVS:-256}", "frames_per_batch=${FT_FRAMES:-4096}",
        "minibatch_size=${FT_MB:-1024}", "iterations=${FT_ITERS:-4}", "eval_episodes=0", "device=${FT_DEVICE:-cuda}",
        "tensorboard=false", "checkpoint_every=100", f"out_dir={os.path.join(out, 'ft')}"]
finetune(load_finetune_config("scale", over), on_iteration=lambda row: print(json.dumps({"device": "${FT_DEVICE:-cuda}", **row}), flush=True))
PY
echo "finetune rc=$?" >> "$OUT/finetune_cuda.log"
rm -rf "$OUT/ft"
