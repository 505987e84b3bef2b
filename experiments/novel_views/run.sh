#!/usr/bin/env bash
# Every figure of experiments/novel_views: the teacher with and without novel views against
# the demo's scene model (make demo first: outputs/demo), two runs side by side on one thread
# each; finished runs are skipped (the script resumes).
#   bash experiments/novel_views/run.sh [OUT]
#   pae-report --compare OUT/plain OUT/jitter0.25 --names plain,novel_views [--split val]
set -uo pipefail
OUT=${1:-outputs/nv_compare}
BIN=${BIN:-.venv/bin}
SM=outputs/demo/scene_model/checkpoints/last.ckpt
BASE=("scene_model_ckpt=$SM" "stage.steps=[teacher,scene_model]")
run() {  # DIR overrides...: one run of pae-train in DIR unless it finished
  local dir=$1
  shift
  [ -f "$dir/metrics.json" ] && return
  mkdir -p "$(dirname "$dir")"
  OMP_NUM_THREADS=1 "$BIN"/pae-train hydra.run.dir="$dir" "$@" > "$dir.log" 2>&1
}
# 1. the settings on val, seed 0 (the demo's settings spelled out for the group's defaults)
run "$OUT/plain/s0" experiment=demo "${BASE[@]}" seed=0 &
run "$OUT/default/s0" experiment=demo_novel_views "${BASE[@]}" seed=0 \
  teacher.novel_views.position_jitter_m=0.1 teacher.novel_views.orientation_jitter_deg=3 &
wait
run "$OUT/ratio1/s0" experiment=demo_novel_views "${BASE[@]}" seed=0 teacher.novel_views.ratio=1.0 \
  teacher.novel_views.position_jitter_m=0.1 teacher.novel_views.orientation_jitter_deg=3 &
run "$OUT/jitter0.25/s0" experiment=demo_novel_views "${BASE[@]}" seed=0 \
  teacher.novel_views.position_jitter_m=0.25 teacher.novel_views.orientation_jitter_deg=6 &
wait
# 2. the chosen setting and the plain teacher over seeds 1 and 2
for seed in 1 2; do
  run "$OUT/jitter0.25/s$seed" experiment=demo_novel_views "${BASE[@]}" seed=$seed \
    teacher.novel_views.position_jitter_m=0.25 teacher.novel_views.orientation_jitter_deg=6 &
  run "$OUT/plain/s$seed" experiment=demo "${BASE[@]}" seed=$seed &
  wait
done
# 3. the student on the novel-view teacher of seed 0 (group defaults): plain, trained on the
# views, retrieving among them too, both
NVT=$OUT/default/s0/teacher/checkpoints/last.ckpt
STUDENT=(experiment=demo 'stage.steps=[student]' "teacher_ckpt=$NVT" "scene_model_ckpt=$SM")
run "$OUT/student/plain" "${STUDENT[@]}" &
run "$OUT/student/views" "${STUDENT[@]}" student.novel_views=true &
wait
run "$OUT/student/store" "${STUDENT[@]}" student.store_novel_views=true &
run "$OUT/student/views_store" "${STUDENT[@]}" student.novel_views=true \
  student.store_novel_views=true &
wait
# 4. the MS-Transformer teacher (40 epochs, seed 0) with novel views from the scene models of
# the MS demo (pae-train experiment=demo_ms_transformer first); its plain twin is
# experiments/ablation_teacher's gain0.15_s0
run "$OUT/ms_transformer/s0" experiment=demo_ms_transformer 'stage.steps=[teacher]' \
  teacher.max_epochs=40 teacher.novel_views.enabled=true \
  scene_model_ckpt=outputs/demo_ms_transformer/scene_model/checkpoints/last.ckpt
