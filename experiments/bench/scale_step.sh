#!/usr/bin/env bash
# The 7-Scenes-size scene-model step of `pae-bench --only render_compare_scale`, run by hand
# so that its folder stays for a look: writes the bench's dataset and cheapest teacher under
# ROOT once, then runs the step under `/usr/bin/time -v` (wall, user and system seconds, page
# faults, peak RSS in ROOT/step_TAG.log).
#   experiments/bench/scale_step.sh ROOT TAG [store]
# store: decode every image into ROOT/image_store first (`pae-data store`, once) and let the
# step read it (data.image_store). THP_MEM_ALLOC_ENABLE=0 in the environment: no huge pages.
set -euo pipefail
root=$1 tag=$2 store=${3:-}
python=${PYTHON:-.venv/bin/python}
export PYTHONPATH=${PYTHONPATH:-src}
if [ ! -d "$root/data" ]; then
  "$python" -c "from pathlib import Path; from pae.bench.scale import write_scale_dataset; \
print(write_scale_dataset(Path('$root/data')))"
fi
data=(data=seven_scenes "data.root=$root/data"
  "data.scenes=[chess,fire,heads,office,pumpkin,redkitchen,stairs]" callbacks=minimal
  +trainer.enable_progress_bar=false)
if [ -n "$store" ]; then
  if [ ! -d "$root/image_store" ]; then
    "$python" -m pae.data_cli store "$root/data/labels/all_train.csv" \
      "$root/data/labels/all_test.csv" "$root/data" --store "$root/image_store"
  fi
  data+=("data.image_store=$root/image_store")
fi
if [ ! -f "$root/teacher/checkpoints/last.ckpt" ]; then
  "$python" -m pae.train stage=teacher teacher=posenet backbone=small_cnn teacher.max_epochs=1 \
    +trainer.limit_train_batches=2 +trainer.limit_val_batches=1 +trainer.limit_test_batches=1 \
    "hydra.run.dir=$root/teacher" "${data[@]}" > "$root/teacher.log" 2>&1
fi
rm -rf "$root/step_$tag"
/usr/bin/time -v "$python" -m pae.train stage=render_compare \
  "teacher_ckpt=$root/teacher/checkpoints/last.ckpt" scene_model.max_epochs=1 \
  scene_model.batches_per_epoch=20 +trainer.limit_val_batches=4 "hydra.run.dir=$root/step_$tag" \
  "${data[@]}" > "$root/step_$tag.log" 2>&1
grep -E "Elapsed|User time|System time|Maximum resident|Minor" "$root/step_$tag.log"
