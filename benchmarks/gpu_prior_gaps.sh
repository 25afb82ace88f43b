#!/usr/bin/env bash
# Issue 33 on a lent GPU machine (run from the repository root; results under $OUT): the embedded prior
# fine-tuned by CAT-K that keeps gaps (catk_avoid), with and without braking leaders (brake_leaders), four
# variants trained side by side on one GPU, then screened there on the 7 scoreable real scenes (2024 rules,
# collision-aware and plain sampling, the embedded prior in the same run). The checkpoints come back
# (export_checkpoint: weights and vocabularies, no optimizer state) for the full evaluation on the CPU.
# Carry: ["gpu_wheels", "gpu_scenes_ft", "gpu_real7"]:
#   gpu_scenes_ft/train.npz.xz  2,000 generated scenes (data/rl_train, seed 7001), benchmarks/scene_pack.py
#   gpu_scenes_ft/es.npz.xz     216 generated scenes with emergency stops (seed 2033, 0.6 per vehicle-minute)
#   gpu_real7                   the 7 scoreable shared real scenes (never trained on), copied (not linked) from ../shared
# Knobs: VARIANTS, TRAIN_DATA, TRAIN_S (time limit of each run), STEPS (its schedule), BATCH, LR, EVAL_ROLLOUTS, EVAL_S, DEVICE,
# INIT (the checkpoint every variant starts from; default the embedded prior). A variant's key=value pairs come
# last on the train command line, so they override the fixed ones (e.g. catk_top_k=0 for teacher forcing).
set -u
OUT=${OUT:-runs/gpu33}
TRAIN_S=${TRAIN_S:-290}
STEPS=${STEPS:-150}
BATCH=${BATCH:-16}
LR=${LR:-0.0001}
EVAL_ROLLOUTS=${EVAL_ROLLOUTS:-32}
EVAL_S=${EVAL_S:-200}
REAL=${REAL:-gpu_real7}
DEVICE=${DEVICE:-cuda}
TRAIN_DATA=${TRAIN_DATA:-"data=/tmp/train extra_data=/tmp/es extra_data_share=0.15"}  # or a token cache: data=DIR
VARIANTS=${VARIANTS:-"gaps_brake03:catk_avoid=true,brake_leaders=0.3 gaps:catk_avoid=true gaps_brake06:catk_avoid=true,brake_leaders=0.6 catk:catk_avoid=false"}
W=${WORK:-/tmp/work}  # logs, runs, checkpoints; $OUT gets a tar of the logs and one of each checkpoint (at most 8 files come back)
rm -rf "$W" && mkdir -p "$OUT" "$W/ckpt"
t0=$(date +%s)
WHEELS=${WHEELS-gpu_wheels}  # empty: the machine has the packages (a dry run on a CPU machine)
. benchmarks/gpu_common.sh
[ -n "$WHEELS" ] && gpu_packages "$WHEELS" "$W/setup.log"
export PYTHONPATH=/tmp/pk:$PWD
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader > "$W/gpu.txt" 2>&1
nproc >> "$W/gpu.txt"
gpu_unpack gpu_scenes_ft/train.npz.xz /tmp/train "$W/setup.log"
gpu_unpack gpu_scenes_ft/es.npz.xz /tmp/es "$W/setup.log"
echo "setup $(( $(date +%s) - t0 )) s" >> "$W/setup.log"

init=${INIT:-smart_marl/checkpoints/embedded/smart-1m-sumo.json}  # a variant may add an input it lacks (speed_change_input)
for v in $VARIANTS; do
    name=${v%%:*}
    extra=$(echo "${v#*:}" | tr ',' ' ')
    # shellcheck disable=SC2086
    OMP_NUM_THREADS=3 timeout $((TRAIN_S + 120)) python3 -m smart_marl.cli train --config smart-1m model.road_types=sumo \
        $TRAIN_DATA road_keep_radius_m=30 token_noise_topk=0 label_smoothing=0.1 \
        batch_size="$BATCH" lr="$LR" warmup_steps=10 max_steps="$STEPS" time_limit_s="$TRAIN_S" num_workers=1 val_every=0 \
        ckpt_every=25 log_every=5 'speed_trend_weights=[3.5,0.9,0.4]' catk_top_k=32 $extra progress=false tensorboard=false \
        --init "$init" --device "$DEVICE" --out "$W/runs/$name" > "$W/train_$name.log" 2>&1 &
done
wait
for v in $VARIANTS; do
    name=${v%%:*}
    cp "$W/runs/$name/train.csv" "$W/train_$name.csv" 2>/dev/null
    src=$W/runs/$name/checkpoints/final
    [ -f "$src.json" ] || src=$W/runs/$name/checkpoints/last  # a run stopped by the timeout: its last checkpoint
    python3 -c "import sys; from smart_marl.model.checkpoint import export_checkpoint; print(export_checkpoint(sys.argv[1], sys.argv[2]))" \
        "$src" "$W/ckpt/$name" >> "$W/export.log" 2>&1
    tar -C "$W/ckpt" -czf "$OUT/ckpt_$name.tgz" $(cd "$W/ckpt" && ls "$name".*)
done
echo "trained $(( $(date +%s) - t0 )) s" >> "$W/setup.log"

# screening: every variant and the embedded prior, collision-aware and plain, side by side
for name in embedded $(for v in $VARIANTS; do echo "${v%%:*}"; done); do
    ck=$([ "$name" = embedded ] && echo "$init" || echo "$W/ckpt/$name.json")
    for s in default plain; do
        flag=$([ "$s" = plain ] && echo --no-collision-avoidance || true)
        # shellcheck disable=SC2086
        OMP_NUM_THREADS=1 timeout "$EVAL_S" python3 -m smart_marl.cli eval --scenes "$REAL" --policy prior --checkpoint "$ck" \
            --device "$DEVICE" --rules 2024 --rollouts "$EVAL_ROLLOUTS" $flag --json > "$W/eval_${name}_$s.json" 2> "$W/eval_${name}_$s.err" &
    done
done
wait
echo "done $(( $(date +%s) - t0 )) s" >> "$W/setup.log"
tar -C "$W" -czf "$OUT/logs.tgz" --exclude=ckpt --exclude=runs .
cat "$W/setup.log" "$W/gpu.txt"
for f in "$W"/train_*.csv; do echo "$f: $(wc -l < "$f") rows"; tail -1 "$f" | cut -c1-160; done
for f in "$W"/eval_*.json; do echo "$f $(head -c 170 "$f")"; done
tail -n 3 "$W"/train_*.log
