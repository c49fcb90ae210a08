#!/usr/bin/env bash
# The Sim2Real segmentation experiment (the seed paper's Table 4 with our simulator):
# simulate labelled HDL-64E scans with ideal physics, render ray drop onto them in six ways,
# train one segmentation network per training set and seed with the same budget, train the
# real oracle on labelled real scans, and score every network on held-out real scans.
#
#   experiments/sim2real_segmentation/run.sh [OUT]      (default OUT: target/sim2real)
#
# Every network trains until its validation mean IoU flattens (PATIENCE validations without a
# new best, one every VAL_EVERY steps) or its STEPS budget (a cosine learning-rate decay over
# it) runs out, and exports the network that scored best on validation: VAL_SCENES more
# simulated scenes rendered like the training ones for A-G, SemanticKITTI sequence 06 for the
# real oracle (trained on 01-05, 09, 10 with scale and ray-drop augmentation; real_boxes adds
# the car and pedestrian boxes of the KITTI object scans in kitti_object_acdc as partial labels).
#
# Settings (environment): SCENES (15), VAL_SCENES (2), SCANS_PER_SCENE (40), STEPS (2000),
# PATIENCE (6), VAL_EVERY (200), WIDTHS (the network's default), SEEDS ("0 1"),
# CONFIGS ("A B C E Es F G real real_boxes": the training sets to render, train and score; after
# new generator weights, "E Es F G" reruns the ones that use them), JOBS (2 trainings at once, one thread
# each), RANGEGAN_BIN (target/release/rangegan-mcap), REAL_LIDAR (../shared/real_lidar). Every step is skipped when its output exists, so a
# killed run resumes where it stopped (a training resumes from its checkpoint).
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
WIDTHS=${WIDTHS:-}
SEEDS=${SEEDS:-"0 1"}
CONFIGS=${CONFIGS:-"A B C E Es F G real real_boxes"}
JOBS=${JOBS:-2}
HERE=$(cd "$(dirname "$0")" && pwd)

[ -x "$BIN" ] || { echo "no binary at $BIN: run cargo build --release first" >&2; exit 2; }
[ -d "$REAL/semantickitti_mini" ] || { echo "no labelled real scans under $REAL/semantickitti_mini" >&2; exit 2; }
export BIN=$(cd "$(dirname "$BIN")" && pwd)/$(basename "$BIN")
REAL=$(cd "$REAL" && pwd)
mkdir -p "$OUT" && cd "$OUT"
ALL_SCENES=$((SCENES + VAL_SCENES))
source "$HERE/common.sh"

# 1. Labelled real scans: the training sequences in one recording (the oracle's data and the
#    real side of B, C and F), the oracle's own split of them (fit and validation), and the
#    held-out sequences, never trained or tuned on.
mkdir -p real
import_sequences train 01 02 03 04 05 06 09 10
import_sequences oracle_fit 01 02 03 04 05 09 10
import_sequences oracle_val 06
for s in 00 07; do
  [ -f real/heldout_mini$s.mcap ] || rg import "$REAL/semantickitti_mini/$s" real/heldout_mini$s.mcap
done
[ -f real/heldout_ssv3.mcap ] || rg import "$REAL/semantickitti_ssv3" real/heldout_ssv3.mcap
# KITTI object scans: car and pedestrian boxes, partial labels for the second oracle.
[ -f real/oracle_boxes.mcap ] || rg import "$REAL/kitti_object_acdc" real/oracle_boxes.mcap
log "real recordings ready"

# 2. Config A: ideal simulated scans (no ray drop), many scenes; the last VAL_SCENES validate.
simulate_scenes
log "simulated $ALL_SCENES scenes x $SCANS scans"

# Whether CONFIGS holds config $1: only the sets it trains are rendered.
wants() { [[ " $CONFIGS " == *" $1 "* ]]; }

# 3. What diagnose finds between the simulator and the real training scans (config F).
if wants F || wants G; then
  [ -f diagnosis/fitted_physics.json ] || rg diagnose --sim sim/A/scene1.mcap --real real/train.mcap --report diagnosis --force
  # G keeps F's perturbations (range noise, mixed pixels, ...) and takes its ray drop from the GAN.
  python3 "$HERE/physics_without_drops.py" diagnosis/fitted_physics.json > diagnosis/perturbations_only.json
fi

# 4. The rendered training sets, one recording per scene; draws seeded per scene.
wants B && render_set B --raydrop global --real real/train.mcap
wants C && render_set C --raydrop pixel --real real/train.mcap
wants F && render_set F --physics diagnosis/fitted_physics.json
wants E && render_set E --raydrop gan
# Es: the same x_n sharpened so that its drops gather where it is highest (each scan's mean drop
# probability kept); the factor 8 brings the rendered validation scenes' drops inside surfaces
# (1.7 %) to the unlabelled KITTI training drives' (1.8 %; drop_by_class.py --surfaces).
wants Es && render_set Es --raydrop gan --drop-sharpness 8
if wants G; then
  render_set Fp --physics diagnosis/perturbations_only.json
  FROM=Fp render_set G --raydrop gan
fi
log "rendered the training sets of $CONFIGS"

# 5. One network per training set and seed, the same budget each, chosen on validation.
#    Scenes move into train/ and val/ folders of links so that a folder is a training set.
for c in A B C E Es F G; do
  wants $c || continue
  mkdir -p split/$c/train split/$c/val
  for s in $(seq 1 "$ALL_SCENES"); do
    part=train; [ "$s" -gt "$SCENES" ] && part=val
    ln -sf "$PWD/sim/$c/scene$s.mcap" split/$c/$part/scene$s.mcap
  done
done
mkdir -p runs
export STEPS PATIENCE VAL_EVERY WIDTHS
for c in $CONFIGS; do
  for seed in $SEEDS; do echo "$c $seed"; done
done | xargs -r -P "$JOBS" -L1 bash -c '
  c=$0; seed=$1
  if [ "$c" = real ]; then
    data=(real/oracle_fit.mcap --val real/oracle_val.mcap --augment)
  elif [ "$c" = real_boxes ]; then
    data=(real/oracle_fit.mcap real/oracle_boxes.mcap --val real/oracle_val.mcap --augment)
  else
    data=(split/$c/train --val split/$c/val)
  fi
  widths=(); [ -n "$WIDTHS" ] && widths=(--widths "$WIDTHS")
  "$BIN" --quiet --threads 1 segment train runs/$c-s$seed "${data[@]}" "${widths[@]}" \
    --steps "$STEPS" --patience "$PATIENCE" --val-every "$VAL_EVERY" --seed "$seed"
' 2>&1 | tee -a train_errors.log
log "trained $(ls runs | wc -l) networks"

# 6. Every network on the held-out real scans.
mkdir -p eval
for c in $CONFIGS; do for seed in $SEEDS; do
  run=runs/$c-s$seed name=$c-s$seed
  rg --json segment eval --model "$run/model" real/heldout_mini00.mcap real/heldout_mini07.mcap real/heldout_ssv3.mcap > eval/$name.json
done; done
python3 "$HERE/table.py" eval > table.md
# The picture needs every configuration's first network.
models=()
for c in A B C E F G real; do
  [ -d runs/$c-s0/model ] && models+=(--model runs/$c-s0/model)
done
if [ ${#models[@]} -eq 14 ]; then
  rg segment picture "${models[@]}" real/heldout_mini07.mcap figure.png --scan 5 --force
fi
log "done: $OUT/table.md, $OUT/figure.png"
