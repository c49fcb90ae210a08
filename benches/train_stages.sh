#!/usr/bin/env bash
# Training images/s per coarse-to-fine grid, side by side: fresh runs from the shipped
# generator, one after another, then the median `images_per_s` of each run's log after its
# first 15 s. Run on quiet cores (pause a training run with SIGSTOP meanwhile).
#
#   bash benches/train_stages.sh [OUT_DIR]    (BIN, DATA, CACHE override the defaults)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-target/bench-train-stages}
BIN=${BIN:-$PWD/target/release/rangegan-mcap}
DATA=${DATA:-../shared/real_lidar}
CACHE=${CACHE:-$OUT/dataset.bin}
rm -rf "$OUT"/run_* && mkdir -p "$OUT"
run() {
  local name=$1 secs=$2; shift 2
  "$BIN" --quiet train "$OUT/run_$name" --data "$DATA" --validation-drive kitti_raw_drive_d \
    --cache "$CACHE" --init-from models/dusty2 \
    --max-minutes "$(python3 -c "print($secs / 60)")" "$@"
}
# Build the cache first so that no run's time includes it.
run warmup 1 --batch 8 --total-images 8 >/dev/null
run full_b8_halfD 150 --batch 8 --half-resolution-discriminator
run full_b8 60 --batch 8
run s3_b32 60 --batch 32 --stage 3:1M
run s3_b32_recon 60 --batch 32 --stage 3:1M --reconstruction 1
run s4_b32 60 --batch 32 --stage 4:1M
run s4_b32_recon 60 --batch 32 --stage 4:1M --reconstruction 1
python3 - "$OUT" <<'PY'
import json, statistics, sys, pathlib
for d in sorted(pathlib.Path(sys.argv[1]).glob("run_*")):
    if d.name == "run_warmup":
        continue
    lines = [json.loads(l) for l in open(d / "log.jsonl")]
    steady = [l["images_per_s"] for l in lines if l["elapsed_s"] > 15]
    third = max(len(steady) // 3, 1)
    print(f"{d.name[4:]:14} grid {lines[-1]['grid']}  median {statistics.median(steady):6.1f}"
          f"  first third {statistics.median(steady[:third]):6.1f}"
          f"  last third {statistics.median(steady[-third:]):6.1f}")
PY
