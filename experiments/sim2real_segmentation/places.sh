#!/usr/bin/env bash
# The Sim2Real table on every labelled place: each SemanticKITTI sequence in
# semantickitti_mini (00-07, 09, 10; ten consecutive scans of one place each) is scored on
# its own, and pooled with a bootstrap interval over places and seeds (places.py).
#
#   experiments/sim2real_segmentation/places.sh [OUT]      (default OUT: target/sim2real)
#
# Nothing scored on a place learnt anything from that place:
# - A, E, Es and G train on simulated scans alone: their networks are the shipped ones
#   (models/segment/<config>/s<seed>, or OUT/runs/<config>-s<seed> from run.sh). E's and G's
#   ray drop comes from the generator, which was trained on unlabelled KITTI scans that
#   include sequences 01-06, 09 and 10 (not 00 and 07; places.py says which places each
#   config saw that way).
# - B, C and F take drop statistics from real scans, and the oracles train on real scans
#   (real_boxes also on the KITTI object scans of kitti_object_acdc, with their car and
#   pedestrian boxes as partial labels): they are trained once per fold of places, on the
#   other fold's sequences, and score only the places of their own fold.
# - real_boxes_lopo is real_boxes trained once per place, on every other place (one of
#   them validates), and scores that place alone: leave one place out.
#
# Settings (environment) as run.sh (STEPS, PATIENCE, VAL_EVERY, SEEDS, JOBS, RANGEGAN_BIN,
# REAL_LIDAR), FOLD_A / FOLD_B, the two folds of sequences, LOPO, the places whose
# leave-one-place-out networks are trained (default: all), FOLD_CONFIGS, the configs whose fold
# networks are trained (default: real real_boxes F C B; empty for none), and SHIPPED=1 to score the shipped
# networks (models/segment/places/<config>_from_<fold>/s<seed> and
# models/segment/places/real_boxes_lopo/<place>/s<seed>) instead of training them. Every step
# is skipped when its output exists, so a killed run resumes (a training from its
# checkpoint).
set -euo pipefail

OUT=${1:-target/sim2real}
BIN=${RANGEGAN_BIN:-target/release/rangegan-mcap}
REAL=${REAL_LIDAR:-../shared/real_lidar}
SCENES=${SCENES:-15}
SCANS=${SCANS_PER_SCENE:-40}
VAL_SCENES=${VAL_SCENES:-2}
STEPS=${STEPS:-2000}
PATIENCE=${PATIENCE:-6}
VAL_EVERY=${VAL_EVERY:-200}
SEEDS=${SEEDS:-"0"}
JOBS=${JOBS:-2}
FOLD_A=${FOLD_A:-"00 01 02 03 04"}
FOLD_B=${FOLD_B:-"05 06 07 09 10"}
SHIPPED=${SHIPPED:-0}
HERE=$(cd "$(dirname "$0")" && pwd)
MODELS=$(cd "$HERE/../.." && pwd)/models/segment

[ -x "$BIN" ] || { echo "no binary at $BIN: run cargo build --release first" >&2; exit 2; }
[ -d "$REAL/semantickitti_mini" ] || { echo "no labelled real scans under $REAL/semantickitti_mini" >&2; exit 2; }
export BIN=$(cd "$(dirname "$BIN")" && pwd)/$(basename "$BIN")
REAL=$(cd "$REAL" && pwd)
mkdir -p "$OUT" && cd "$OUT"
ALL_SCENES=$((SCENES + VAL_SCENES))
source "$HERE/common.sh"

# 1. Each place as a recording, and the real training data of each fold and of each place left
#    out.
mkdir -p places real
for s in $FOLD_A $FOLD_B; do
  [ -f places/$s.mcap ] || rg import "$REAL/semantickitti_mini/$s" places/$s.mcap
done
last() { echo "${@: -1}"; }
all_but_last() { echo "${@:1:$#-1}"; }
# fold a is scored by networks that learnt from fold b's places, and the other way round.
import_sequences from_b $FOLD_B
import_sequences from_b_fit $(all_but_last $FOLD_B)
import_sequences from_b_val $(last $FOLD_B)
import_sequences from_a $FOLD_A
import_sequences from_a_fit $(all_but_last $FOLD_A)
import_sequences from_a_val $(last $FOLD_A)
# Leave one place out: each place's networks fit the others but one, which validates (the
# last place, and for the last place the first).
PLACES=($FOLD_A $FOLD_B)
for p in "${PLACES[@]}"; do
  v=${PLACES[-1]}; [ "$p" = "$v" ] && v=${PLACES[0]}
  import_sequences lopo_${p}_fit $(printf '%s\n' "${PLACES[@]}" | grep -vx -e "$p" -e "$v")
  import_sequences lopo_${p}_val "$v"
done
# The KITTI object scans with car and pedestrian boxes (partial labels), for real_boxes.
[ -f real/boxes.mcap ] || rg import "$REAL/kitti_object_acdc" real/boxes.mcap
log "places and folds imported"

if [ "$SHIPPED" != 1 ]; then
# 2. The ideal simulated scenes (shared with run.sh), the diagnosis of each fold's real
#    scans, and B, C and F rendered from each fold's statistics.
simulate_scenes
for f in a b; do
  real=real/from_$f.mcap
  [ -f diagnosis_from_$f/fitted_physics.json ] || rg diagnose --sim sim/A/scene1.mcap --real $real --report diagnosis_from_$f --force
  render_set B_from_$f --raydrop global --real $real
  render_set C_from_$f --raydrop pixel --real $real
  render_set F_from_$f --physics diagnosis_from_$f/fitted_physics.json
done
log "rendered B, C and F from each fold"

# 3. B, C, F and the oracle per fold and seed.
for c in B C F; do for f in a b; do
  mkdir -p split/${c}_from_$f/train split/${c}_from_$f/val
  for s in $(seq 1 "$ALL_SCENES"); do
    part=train; [ "$s" -gt "$SCENES" ] && part=val
    ln -sf "$PWD/sim/${c}_from_$f/scene$s.mcap" split/${c}_from_$f/$part/scene$s.mcap
  done
done; done
mkdir -p runs
export STEPS PATIENCE VAL_EVERY
LOPO=${LOPO-"${PLACES[*]}"}
FOLD_CONFIGS=${FOLD_CONFIGS-"real real_boxes F C B"}
{ for seed in $SEEDS; do for p in $LOPO; do echo "real_boxes_lopo $p $seed"; done; done
  for c in $FOLD_CONFIGS; do for f in a b; do for seed in $SEEDS; do echo "$c $f $seed"; done; done; done; } |
  xargs -r -P "$JOBS" -L1 bash -c '
  c=$0; f=$1; seed=$2   # f: the fold (a, b), or for real_boxes_lopo the place left out
  run=runs/${c}_from_$f-s$seed
  case $c in
    real_boxes_lopo) run=runs/${c}_$f-s$seed
      data=(real/lopo_${f}_fit.mcap real/boxes.mcap --val real/lopo_${f}_val.mcap --augment) ;;
    real) data=(real/from_${f}_fit.mcap --val real/from_${f}_val.mcap --augment) ;;
    real_boxes) data=(real/from_${f}_fit.mcap real/boxes.mcap --val real/from_${f}_val.mcap --augment) ;;
    *) data=(split/${c}_from_$f/train --val split/${c}_from_$f/val) ;;
  esac
  "$BIN" --quiet --threads 1 segment train "$run" "${data[@]}" \
    --steps "$STEPS" --patience "$PATIENCE" --val-every "$VAL_EVERY" --seed "$seed"
' 2>&1 | tee -a places_train_errors.log
log "trained the fold and left-out-place networks"
fi

# 4. Every network on every place it may score: eval/places/CONFIG-sSEED/PLACE.json.
score() { # CONFIG SEED MODEL PLACE...
  local c=$1 seed=$2 model=$3; shift 3
  mkdir -p eval/places/$c-s$seed
  for s in "$@"; do
    local out=eval/places/$c-s$seed/$s.json
    [ -f "$out" ] || rg --json segment eval --model "$model" places/$s.mcap > "$out"
  done
}
for seed in $SEEDS; do
  for c in A E Es G; do
    model=runs/$c-s$seed/model
    [ -d "$model" ] || model=$MODELS/$c/s$seed
    [ -d "$model" ] && score $c $seed "$model" $FOLD_A $FOLD_B
  done
  for c in B C F real real_boxes; do
    for f in a b; do
      model=runs/${c}_from_$f-s$seed/model
      [ "$SHIPPED" = 1 ] && model=$MODELS/places/${c}_from_$f/s$seed
      [ -d "$model" ] || continue
      if [ $f = a ]; then score $c $seed "$model" $FOLD_B; else score $c $seed "$model" $FOLD_A; fi
    done
  done
  for p in "${PLACES[@]}"; do
    model=runs/real_boxes_lopo_$p-s$seed/model
    [ "$SHIPPED" = 1 ] && model=$MODELS/places/real_boxes_lopo/$p/s$seed
    [ -d "$model" ] && score real_boxes_lopo $seed "$model" $p
  done
done
python3 "$HERE/places.py" eval/places > places.md
log "done: $OUT/places.md"
