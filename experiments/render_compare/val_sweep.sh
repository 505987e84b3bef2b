#!/usr/bin/env bash
# Every render-and-compare setting re-derived on the validation split of the demo's
# checkpoints (make demo first): one setting at a time beside the defaults, refiner settings
# through pae-eval on the demo's scene model, scene-model settings by refitting it from the
# demo's teacher. Each run's figures land in OUT/<setting>/metrics.json (finished runs are
# skipped: the script resumes); python experiments/render_compare/table.py OUT prints them.
#   bash experiments/render_compare/val_sweep.sh [OUT]
set -uo pipefail
OUT=${1:-outputs/render_compare_val}
DEMO=outputs/demo
BIN=${BIN:-.venv/bin}
mkdir -p "$OUT"
refiner=(
  "blur_sigma_px=0.5" "blur_sigma_px=1.0" "final_reference_size=32" "final_reference_size=48"
  "final_fov_scale=1.3" "reference_size=16" "levels=2" "levels=4" "hypotheses=1"
  "hypotheses=8" "rounds=0" "rounds=10" "polish_steps=5" "polish_steps=20"
  "min_overlap=0.2" "highpass_sigma_px=4.0" "trim_sigma=2.0"
)
# the callback's own settings (step_from_val replaces position_sigma_m and
# orientation_sigma_deg by fractions of the teacher's val error)
callback=("step_from_val.position=0.5" "step_from_val.orientation=0.8" "accept_margin=0.0")
# several overrides of one setting are joined by "+"
scene_model=(
  "model.auto_scale.margin_floor_m=1.0" "model.auto_scale.margin_floor_m=3.0"
  "model.num_voxels=1000000" "max_epochs=12"
  "appearance=image+appearance_lr=0.01" "fit_trim=0.1"
)
# a run folder is named by its setting, "=" written "_" (Hydra reads "=" in a value as a key)
for setting in defaults "${refiner[@]}"; do
  dir="$OUT/${setting//=/_}"
  [ -f "$dir/metrics.json" ] && continue
  extra=()
  [ "$setting" != defaults ] && extra=("render_compare.refiner.$setting")
  "$BIN/pae-eval" "scene_model_ckpt=$DEMO/scene_model/checkpoints/last.ckpt" \
    render_compare.oracle=false "${extra[@]}" "hydra.run.dir=$dir" \
    >"$dir.log" 2>&1 || echo "$setting failed (log $dir.log)"
done
for setting in "${callback[@]}"; do
  dir="$OUT/render_compare.${setting//=/_}"
  [ -f "$dir/metrics.json" ] && continue
  "$BIN/pae-eval" "scene_model_ckpt=$DEMO/scene_model/checkpoints/last.ckpt" \
    render_compare.oracle=false "render_compare.$setting" "hydra.run.dir=$dir" \
    >"$dir.log" 2>&1 || echo "$setting failed (log $dir.log)"
done
for setting in "${scene_model[@]}"; do
  dir="$OUT/scene_model.${setting//=/_}"
  [ -f "$dir/metrics.json" ] && continue
  IFS=+ read -ra parts <<<"$setting"
  "$BIN/pae-train" experiment=demo "stage.steps=[scene_model]" \
    "teacher_ckpt=$DEMO/teacher/checkpoints/last.ckpt" render_compare.oracle=false \
    "${parts[@]/#/scene_model.}" "hydra.run.dir=$dir" >"$dir.log" 2>&1 \
    || echo "$setting failed (log $dir.log)"
done
