#!/usr/bin/env bash
# Fine-tuning at scale on a lent GPU machine, as one script (run from the repository root; results under $OUT).
# What travels: gpu_wheels/ (see gpu_session.sh) and gpu_scenes_ft/{train,heldout}.npz.xz, made here with
#   python benchmarks/scene_pack.py pack data/rl_train --out gpu_scenes_ft/train.npz.xz --count 2000
#   python benchmarks/scene_pack.py pack data/rl_heldout --out gpu_scenes_ft/heldout.npz.xz
#   python benchmarks/scene_pack.py pack ../shared/data/{womd_tfrecord,nocturne_json,scenarionet/waymo,smart_pkl} \
#       --out gpu_scenes_ft/real.npz.xz
# Steps: unpack both into scene caches; one fine-tuning run of the scale config on the first N generated scenes
# (generated scenes only), NUM_ENVS scenes stepped together on the GPU, for TRAIN_S seconds of training; then the
# reference (prior top-3) and the fine-tuned policy on the first 200 held-out generated scenes x EVAL_SEEDS seeds and
# on the real held-out scenes x REAL_SEEDS seeds, then the expert and the full softmax, on the GPU, until the script's
# deadline (each row is cached as it finishes, so a row that did not finish is left out).
# EXTRA: more key=value overrides for the run and its evaluation (e.g. 'shield=["collision","offroad"] reference_top_k=16');
# SKIP_REF=1 leaves the reference's rows out; CORE_BENCH="256,1024" first times the env's core on the GPU at those numbers
# of scenes, without and with the shield (benchmarks/env_throughput_core.py).
set -u
OUT=${OUT:-runs/gpu_ft}
DEADLINE=$((SECONDS + ${TOTAL_S:-560}))
N=${N:-2000}
RUN=${RUN:-/tmp/gen}
DEV=${DEV:-cuda}
mkdir -p "$OUT" "$RUN"
left() { local t=$((DEADLINE - SECONDS)); echo $((t > 1 ? t : 1)); }  # (timeout 0 would mean no limit)
. benchmarks/gpu_common.sh
gpu_packages gpu_wheels "$OUT/setup.log"
export PYTHONPATH=/tmp/pk:$PWD PYTHONUNBUFFERED=1
{ nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; nproc; } >> "$OUT/setup.log" 2>&1
gpu_unpack gpu_scenes_ft/train.npz.xz /tmp/train "$OUT/setup.log"
gpu_unpack gpu_scenes_ft/heldout.npz.xz /tmp/heldout "$OUT/setup.log"
read -r -a EXTRA_OVER <<< "${EXTRA:-}"
if [ -n "${CORE_BENCH:-}" ]; then
  for flag in "" --shield; do
    timeout "${T_CORE:-60}" python3 benchmarks/env_throughput_core.py --device cuda --threads 8 --scenes /tmp/train \
        --num-scenes "$CORE_BENCH" --steps 16 --repeats 2 $flag >> "$OUT/core_throughput.jsonl" 2>> "$OUT/core_throughput.err"
    echo "core bench [$flag] rc=$? at ${SECONDS}s" >> "$OUT/core_throughput.err"
  done
fi
COMMON=(--train /tmp/train --heldout /tmp/heldout --sizes "$N" --run-dir "$RUN" --threads "${THREADS:-8}")
OVER=(device="$DEV" num_envs="${NUM_ENVS:-512}" frames_per_batch="${FRAMES:-8192}" minibatch_size="${MB:-512}"
      prior_cache_size="${CACHE:-2048}" iterations=100000 time_limit_s="${TRAIN_S:-330}" checkpoint_every="${CKPT:-20}" tensorboard=false torch_threads="${THREADS:-8}" "${EXTRA_OVER[@]}")
timeout "$(left)" python3 benchmarks/finetune_generalisation.py "${COMMON[@]}" --only train "${OVER[@]}" \
    > "$OUT/train.jsonl" 2> "$OUT/train.err"
echo "train rc=$? at ${SECONDS}s" >> "$OUT/train.err"
tar czf "$OUT/policy.tgz" -C "$RUN" "train_$N/checkpoints/policy_last.json" "train_$N/checkpoints/policy_last.safetensors" \
    "train_$N/run.json" "train_$N/config.json" 2>> "$OUT/train.err"
gpu_unpack gpu_scenes_ft/real.npz.xz /tmp/real "$OUT/setup.log"
# the fine-tuned policy and the reference on both held-out sets first (the real one first: it is quicker), then the expert
# and the full softmax
EVAL=(device="$DEV" num_envs="${EVAL_ENVS:-800}" frames_per_batch=8192 "${EXTRA_OVER[@]}")
SKIP=(); [ -n "${SKIP_REF:-}" ] && SKIP=(--skip-reference)
for rows in "" "expert (log),prior full softmax"; do
  for set in real generated; do
    timeout "$(left)" python3 benchmarks/finetune_generalisation.py "${COMMON[@]}" --real-heldout /tmp/real \
        --only "eval-$set" --rows "$rows" --eval-scenes "${EVAL_SCENES:-200}" --eval-seeds "${EVAL_SEEDS:-8}" \
        --real-seeds "${REAL_SEEDS:-48}" "${SKIP[@]}" "${EVAL[@]}" >> "$OUT/eval.jsonl" 2>> "$OUT/eval.err"
    echo "eval $set [$rows] rc=$? at ${SECONDS}s" >> "$OUT/eval.err"
  done
done
tar czf "$OUT/eval.tgz" -C "$RUN" $(cd "$RUN" && ls eval_*.json 2>/dev/null) 2>> "$OUT/eval.err"
