#!/usr/bin/env bash
# Issues 32 and 33 side by side on one lent GPU machine (run from the repository root; results under $OUT, at
# most 8 files): gpu_finetune.sh goes on training the shipped policy (init=embedded, its recipe: the shield, the
# prior's top 16, the motion head, a collision at -3) and evaluates it on the real held-out scenes; gpu_prior_gaps.sh
# trains the prior teacher-forced on a token cache (no tokenizing on the machine), with and without the speed-change
# input, and screens both next to the embedded prior on the 7 scoreable real scenes. They share the GPU and its 16
# cores; the wheels and scene sets are installed and unpacked once first (gpu_common.sh).
# Measured cost of sharing (2026-11-27, H200): the policy run's iterations took 50-56 s while the prior runs trained,
# 5-6 s after (alone: ~6 s); the prior runs made 25-31 scenes/s each. Give an environment run the machine to itself.
# Carry: ["gpu_wheels", "gpu_scenes_ft", "gpu_real7", "gpu_tok"] (gpu_tok/tok_stop_plain: the first 896 scenes of
# data/tok_stop_plain, token_cache.json cut to its first 112 shards).
# DRY=1 shrinks everything for a run on a CPU machine (with PATH holding the project's python3).
set -u
OUT=${OUT:-runs/gpu_both}
R=/tmp/side_by_side
rm -rf "$R" && mkdir -p "$R" "$OUT"
. benchmarks/gpu_common.sh
if [ -n "${DRY:-}" ]; then
    FT=(DEV=cpu N=64 NUM_ENVS=8 FRAMES=256 MB=128 CACHE=64 THREADS=1 TRAIN_S=20 TOTAL_S=160 EVAL_ENVS=8 EVAL_SCENES=4
        EVAL_SEEDS=1 REAL_SEEDS=1)
    PG=(DEVICE=cpu WHEELS= TRAIN_S=20 STEPS=4 BATCH=2 EVAL_ROLLOUTS=2 EVAL_S=90 REAL=gpu_real7)
else
    gpu_packages gpu_wheels "$R/setup.log"
    FT=(TRAIN_S="${FT_TRAIN_S:-260}" TOTAL_S="${FT_TOTAL_S:-470}")
    PG=(TRAIN_S="${PG_TRAIN_S:-250}" STEPS="${PG_STEPS:-1000}" EVAL_S="${PG_EVAL_S:-170}")
fi
for s in train heldout real es; do gpu_unpack "gpu_scenes_ft/$s.npz.xz" "/tmp/$s" "$R/setup.log" & done
wait
echo "setup ${SECONDS} s" >> "$R/setup.log"
env "${FT[@]}" OUT="$R/ft" RUN=/tmp/gen SKIP_REF=1 \
    EXTRA='shield=["collision","offroad"] reference_top_k=16 actor_head=motion beta=0.01 init=embedded reward.collision=-3' \
    bash benchmarks/gpu_finetune.sh > "$R/ft.log" 2>&1 &
env "${PG[@]}" OUT="$R/pg" WORK=/tmp/pg_work TRAIN_DATA=data=gpu_tok/tok_stop_plain \
    VARIANTS='input:catk_top_k=0,num_workers=2,model.speed_change_input=true,lr_scale={"motion_net.speed_change":10} ctrl:catk_top_k=0,num_workers=2' \
    bash benchmarks/gpu_prior_gaps.sh > "$R/pg.log" 2>&1 &
wait
echo "both done ${SECONDS} s" >> "$R/setup.log"
tar -C "$R" -czf "$OUT/ft.tgz" ft ft.log setup.log
cp "$R"/pg/* "$R/pg.log" "$OUT/"
cat "$R/setup.log"; tail -n 4 "$R/ft/train.err" "$R/ft/eval.err"; tail -n 25 "$R/pg.log"
