#!/usr/bin/env bash
# The generator's long run on a GPU machine, in one call of at most ~10 minutes: unpack the
# binary and the dataset cache, optionally time a few batch sizes, train until BUDGET seconds
# after the start (checkpointing), and leave the compact run folder and the logs in $OUT.
#
#   BUDGET=520 BATCHES="32 128" bash experiments/gpu_training/run.sh
#
# Expects, in STAGE (default .gpu, an ignored folder that travels with the call):
#   rangegan-mcap.xz    the x86-64 binary built with `--features wgpu`, stripped, xz'd
#   dataset.u16.xz      the dataset cache packed by pack_cache.py, xz'd
# and the run folder at RUN (default models/gan-run). Vulkan loaders: see README.md here.
# TRAIN_ARGS are passed to every `train` (e.g. "--sim-mix 4000:0.25" for a run that mixes in
# simulated scans: they are rebuilt there, deterministically, and do not travel back).
set -u
T0=$(date +%s)
STAGE=${STAGE:-.gpu}
RUN=${RUN:-models/gan-run}
OUT=${OUT:-gpu-out}
BUDGET=${BUDGET:-480}
BACKEND=${BACKEND:-wgpu}
mkdir -p "$OUT"
here=$(dirname "$0")
if ls .gl/*.deb >/dev/null 2>&1; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
fi
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
[ -f $icd ] && export VK_DRIVER_FILES=$icd
nvidia-smi -L || true
xz -d -T0 -c "$STAGE/dataset.u16.xz" > /tmp/dataset.u16 &&
  python3 "$here/pack_cache.py" unpack /tmp/dataset.u16 /tmp/dataset.bin || exit 3
xz -d -c "$STAGE/rangegan-mcap.xz" > /tmp/rg && chmod +x /tmp/rg || exit 4
rm -rf /tmp/run && cp -r "$RUN" /tmp/run
train() { # RUN_DIR MINUTES LOG
  /tmp/rg --quiet train "$1" --backend "$BACKEND" --cache /tmp/dataset.bin --max-minutes "$2" ${TRAIN_ARGS:-} > "$3" 2>&1
}
# The rate of the last log line written after line $2 (the run's own log goes back months).
last_rate() {
  tail -n +"$(( $2 + 1 ))" "$1/log.jsonl" | tail -1 | python3 -c "
import json, sys
t = sys.stdin.read().strip()
print(json.loads(t)['images_per_s'] if t else 'no log line in the time given')"
}
for b in ${BATCHES:-}; do # batch-size probes on copies of the run
  rm -rf /tmp/probe && cp -r /tmp/run /tmp/probe
  # A log line every step: at 64 x 512 a large batch may not reach ten steps in the minute.
  python3 -c "import json; p='/tmp/probe/config.json'; c=json.load(open(p)); c['batch_size']=$b; c['log_every_steps']=1; open(p,'w').write(json.dumps(c, indent=2))"
  n=$(wc -l < /tmp/probe/log.jsonl)
  train /tmp/probe "${PROBE_MINUTES:-1.5}" "$OUT/probe-$b.log"
  echo "batch $b: $(last_rate /tmp/probe "$n") images/s"
done | tee "$OUT/batches.txt"
# What `train` builds before it starts (the simulated scans) is built before the clock starts.
if [ -n "${TRAIN_ARGS:-}" ]; then
  s=$(date +%s); train /tmp/run 0 "$OUT/prepare.log"
  echo "prepared in $(( $(date +%s) - s )) s"
fi
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv -l 20 > "$OUT/gpu.csv" 2>&1 &
minutes=$(awk -v b="$BUDGET" -v e=$(( $(date +%s) - T0 )) 'BEGIN { printf "%.2f", (b - e) / 60 }')
n=$(wc -l < /tmp/run/log.jsonl)
train /tmp/run "$minutes" "$OUT/train.log"
echo "train exit $? after $(( $(date +%s) - T0 )) s; last: $(last_rate /tmp/run "$n") images/s"
# The discriminator's Adam state is left out: the committed checkpoint stays small.
tar -C /tmp --exclude opt_d.bpk --exclude sim.bin -cf "$OUT/run.tar" run
[ -f /tmp/run/sim.bin ] && sha256sum /tmp/run/sim.bin
ls -la "$OUT"
