#!/usr/bin/env bash
# The MS-Transformer demo's teacher settings chosen on the validation split (seq-06 of each
# scene held out of training): the teacher step alone of experiment=demo_ms_transformer per
# setting, two runs side by side on one thread each. A setting's runs land in
# OUT/<name>_s<seed>/ (finished ones are skipped: the script resumes);
# python experiments/ablation_teacher/ms_val_table.py OUT prints mean +- sd over the seeds.
#   bash experiments/ablation_teacher/ms_val_sweep.sh [OUT]
set -uo pipefail
OUT=${1:-outputs/ms_sweep}
ONLY=${ONLY:-}  # a regular expression: run only the settings whose name matches
BIN=${BIN:-.venv/bin}
mkdir -p "$OUT"
# name|overrides (each on top of experiment=demo_ms_transformer as it stands: 80 epochs,
# channel_gain 0.15 and scene_loss_weight 5, the chosen settings, overridden where a setting
# differs); seeds 0-2 for the first six and the last (tried for every seed's mark), seed 0
# alone for the rest
settings=(
  "no_gain|teacher.max_epochs=40 data.channel_gain=0.0 teacher.scene_loss_weight=1"
  "gain0.15|teacher.max_epochs=40 teacher.scene_loss_weight=1"
  "gain0.3|teacher.max_epochs=40 data.channel_gain=0.3 teacher.scene_loss_weight=1"
  "lr1e-3|teacher.max_epochs=40 data.channel_gain=0.0 teacher.optimizer.lr=1e-3 teacher.scene_loss_weight=1"
  "gain0.15_e60|teacher.max_epochs=60 teacher.scene_loss_weight=1"
  "gain0.15_e80|teacher.max_epochs=80 teacher.scene_loss_weight=1"
  "e25|teacher.max_epochs=25 data.channel_gain=0.0 teacher.scene_loss_weight=1"
  "e25_scene_loss5|teacher.max_epochs=25 data.channel_gain=0.0 teacher.scene_loss_weight=5"
  "e60|teacher.max_epochs=60 data.channel_gain=0.0 teacher.scene_loss_weight=1"
  "d128|teacher.max_epochs=40 data.channel_gain=0.0 teacher.model.latent_dim=128 teacher.model.feedforward=256 teacher.scene_loss_weight=1"
  "jitter0.5|teacher.max_epochs=40 data.channel_gain=0.0 data.color_jitter=[0.5,0.5,0.5,0.0] teacher.scene_loss_weight=1"
  "hue0.05|teacher.max_epochs=40 data.channel_gain=0.0 data.color_jitter=[0.7,0.7,0.7,0.05] teacher.scene_loss_weight=1"
  "lr4e-3|teacher.max_epochs=40 data.channel_gain=0.0 teacher.optimizer.lr=4e-3 teacher.scene_loss_weight=1"
  "gain0.15_e80_scene5|teacher.max_epochs=80 teacher.scene_loss_weight=5"
)
jobs=()
for i in "${!settings[@]}"; do
  name=${settings[$i]%%|*}
  overrides=${settings[$i]#*|}
  [[ -n "$ONLY" && ! "$name" =~ $ONLY ]] && continue
  seeds=(0)
  [ "$i" -lt 6 ] || [ "$i" -ge 13 ] && seeds=(0 1 2)
  for seed in "${seeds[@]}"; do
    jobs+=("$name"_s"$seed|seed=$seed $overrides")
  done
done
run() {
  local dir="$OUT/${1%%|*}"
  [ -f "$dir/metrics.json" ] && return
  # shellcheck disable=SC2086  # the overrides are separate words
  OMP_NUM_THREADS=1 "$BIN"/pae-train experiment=demo_ms_transformer 'stage.steps=[teacher]' \
    hydra.run.dir="$dir" ${1#*|} > "$dir.log" 2>&1
}
for ((i = 0; i < ${#jobs[@]}; i += 2)); do
  run "${jobs[$i]}" &
  [ $((i + 1)) -lt ${#jobs[@]} ] && run "${jobs[$((i + 1))]}" &
  wait
done
