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
  /tmp/rg --quiet train "$1" --backend "$BACKEND" --cache /tmp/dataset.bin --max-minutes "$2" > "$3" 2>&1
}
last_rate() { tail -1 "$1/log.jsonl" | python3 -c "import json,sys; d=json.loads(sys.stdin.read()); print(d['images_per_s'], d['grid'])"; }
for b in ${BATCHES:-}; do # batch-size probes on copies of the run
  rm -rf /tmp/probe && cp -r /tmp/run /tmp/probe
  python3 -c "import json; p='/tmp/probe/config.json'; c=json.load(open(p)); c['batch_size']=$b; open(p,'w').write(json.dumps(c, indent=2))"
  train /tmp/probe 1 "$OUT/probe-$b.log"
  echo "batch $b: $(last_rate /tmp/probe) images/s"
done | tee "$OUT/batches.txt"
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv -l 20 > "$OUT/gpu.csv" 2>&1 &
minutes=$(awk -v b="$BUDGET" -v e=$(( $(date +%s) - T0 )) 'BEGIN { printf "%.2f", (b - e) / 60 }')
train /tmp/run "$minutes" "$OUT/train.log"
echo "train exit $? after $(( $(date +%s) - T0 )) s; last: $(last_rate /tmp/run) images/s"
# The discriminator's Adam state is left out: the committed checkpoint stays small.
tar -C /tmp --exclude opt_d.bpk -cf "$OUT/run.tar" run
ls -la "$OUT"
