#!/usr/bin/env bash
# One module for any swarm, with the defaults at a user's budget: models trained on 3, 4 and 5
# carriers (three files, and the scene set quad3-5), zero-shot on 6 and 8; quad3 models fine-tuned
# on 80 quad6 trajectories; every model against holding the initial state, per step and per
# state group (docs/evidence/quadrotor.md, "One module for any swarm").
# Every step is skipped when its output exists (rerun after an interruption; rm -r "$OUT" to redo).
#   OUT=/tmp/sizes bash benchmarks/studies/quadrotor/sizes.sh
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
OUT=${OUT:-/tmp/mpnode-quadrotor-sizes}  # data, models, logs, eval reports
TRAIN=${TRAIN:-10}                       # minutes per training (the budget of the claim)
FINETUNE=${FINETUNE:-5}                  # minutes per fine-tuning
SEEDS=${SEEDS:-"3121 3122"}              # training seeds: a quad3 source and its fine-tuning per seed
LOCK=${LOCK:-}                           # a lock file every timed run holds (a shared machine), or none
WORKERS=${WORKERS:-2}
mkdir -p "$OUT"
cd "$OUT"

gen() { [ -f "$2" ] || mpnode generate "$1" -o "$2" --trajectories "$3" --seed "$4" --workers "$WORKERS"; }
gen quad3 q3_train.h5 500 3101
gen quad4 q4_train.h5 300 3102
gen quad5 q5_train.h5 300 3103
gen quad6 q6_ft_1.h5 80 3104                  # the fine-tuning sets: one per seed
gen quad6 q6_ft_2.h5 80 3111
gen quad6 q6_test.h5 200 3105                 # fresh test data, seeds no training file uses
gen quad8 q8_test.h5 200 3106
gen quad3 q3_test.h5 100 3107

timed() {  # timed MODEL mpnode ARGS...: the run, holding $LOCK, with the load before and after it
  local model=$1; shift
  [ -f "$model" ] && return
  local run=("$@" -o "$model")
  [ -n "$LOCK" ] && run=(flock "$LOCK" "${run[@]}")
  echo "before $(uptime)" > "$model.load"
  "${run[@]}" > "$model.out"
  echo "after $(uptime)" >> "$model.load"
}
ev() {  # ev MODEL DATA: mpnode eval's report as JSON beside the model
  local json="${1%.h5}.$(basename "$2" .h5).json"
  [ -f "$json" ] || mpnode eval "$1" "$2" --json --reference-sample 0 > "$json"
}

first=${SEEDS%% *}
timed multi.h5 mpnode train q3_train.h5 q4_train.h5 q5_train.h5 --time-limit "$TRAIN" --seed "$first"
timed swarm.h5 mpnode train quad3-5 --time-limit "$TRAIN" --seed "$first"
k=0
for s in $SEEDS; do
  k=$((k + 1))
  timed "source_$s.h5" mpnode train q3_train.h5 --time-limit "$TRAIN" --seed "$s"
  timed "finetuned_$s.h5" mpnode finetune "source_$s.h5" "q6_ft_$k.h5" --time-limit "$FINETUNE" --seed "$s"
done
timed finetuned_multi.h5 mpnode finetune multi.h5 q6_ft_1.h5 --time-limit "$FINETUNE" --seed "$first"
timed kept_norm.h5 mpnode finetune "source_$first.h5" q6_ft_1.h5 --time-limit "$FINETUNE" --seed "$first" --keep-norm

for m in multi.h5 swarm.h5 source_*.h5; do
  ev "$m" q6_test.h5
  ev "$m" q8_test.h5
done
for m in source_*.h5; do ev "$m" q3_test.h5; done
for m in finetuned_*.h5 kept_norm.h5; do ev "$m" q6_test.h5; done
python "$HERE/sizes_table.py" "$OUT" | tee table.md
