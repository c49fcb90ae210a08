# Shared by run.sh and places.sh (sourced after they set BIN, REAL, SCENES, SCANS,
# ALL_SCENES and JOBS and cd into OUT): the binary, a log line, labelled real sequences as one
# recording, the ideal simulated scenes and the rendered training sets. Every function skips
# what already exists, so a killed run resumes.

started=$(date +%s)
log() { echo "[$(( $(date +%s) - started )) s] $*" >&2; }
rg() { "$BIN" --quiet "$@"; }

# real/NAME.mcap: the labelled scans of the semantickitti_mini SEQUENCEs, in that order.
import_sequences() { # NAME SEQUENCE...
  local name=$1; shift
  [ -f real/$name.mcap ] && return
  rm -rf real/${name}_bins && mkdir -p real/${name}_bins/velodyne real/${name}_bins/labels
  for s in "$@"; do
    for f in "$REAL"/semantickitti_mini/$s/velodyne/*.bin; do
      b=$(basename "$f" .bin)
      ln -s "$f" real/${name}_bins/velodyne/${s}_$b.bin
      ln -s "$REAL/semantickitti_mini/$s/labels/$b.label" real/${name}_bins/labels/${s}_$b.label
    done
  done
  rg import real/${name}_bins real/$name.mcap
}

# sim/A/sceneN.mcap: ALL_SCENES ideal scenes of SCANS HDL-64E scans each (config A).
simulate_scenes() {
  mkdir -p sim/A
  for s in $(seq 1 "$ALL_SCENES"); do
    [ -f sim/A/scene$s.mcap ] || rg simulate --scene "$s" --scans "$SCANS" --columns 512 --physics ideal sim/A/scene$s.mcap
  done
}

# sim/SET/sceneN.mcap: each scene of A (or of the set FROM names) rendered by `render ARGS`,
# draws seeded per scene.
render_set() { # SET ARGS...
  local c=$1 from=${FROM:-A}; shift; mkdir -p sim/$c
  for s in $(seq 1 "$ALL_SCENES"); do
    [ -f sim/$c/scene$s.mcap ] || echo "$s"
  done | xargs -r -P "$JOBS" -I{} "$BIN" --quiet --threads 1 render "$@" --seed {} sim/$from/scene{}.mcap sim/$c/scene{}.mcap
}
