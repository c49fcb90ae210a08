#!/usr/bin/env bash
# Side-by-side timing of our generator (benches/generator_ops.rs, burn flex) and the reference
# PyTorch implementation (benches/reference_pytorch.py importing a checkout of
# kazuto1011/dusty-gan-v2), interleaved in one run: rounds alternate ours/theirs (the order
# flips every round), every round times every operation `REPS` times after one warm-up, and the
# table gives the median over all rounds. The 1/5/15-minute load averages are logged before
# every process.
#
#   bash benches/vs_pytorch.sh --reference /work/dusty-gan-v2 [--python /work/torchvenv/bin/python]
#        [--rounds 3] [--reps 3] [--ops fwd_b1,fwd_b8,fwdbwd_b1,fwdbwd_b8,inv_w_b1,pti_b1]
#        [--out DIR]
#
# Needs: torch (CPU) + numpy + pyyaml in --python; cargo (release bench build; set
# CARGO_TARGET_DIR to reuse an existing build, the first one compiles burn).
set -euo pipefail

REFERENCE=""
PYTHON=python3
ROUNDS=3
REPS=3
OPS=fwd_b1,fwd_b8,fwdbwd_b1,fwdbwd_b8,inv_w_b1,pti_b1
OUT=""
while [[ $# -gt 0 ]]; do
  case "$1" in
    --reference) REFERENCE=$2; shift 2 ;;
    --python) PYTHON=$2; shift 2 ;;
    --rounds) ROUNDS=$2; shift 2 ;;
    --reps) REPS=$2; shift 2 ;;
    --ops) OPS=$2; shift 2 ;;
    --out) OUT=$2; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
[[ -n "$REFERENCE" ]] || { echo "--reference DIR (checkout of kazuto1011/dusty-gan-v2) is required" >&2; exit 2; }

HERE=$(cd "$(dirname "$0")" && pwd)
ROOT=$(dirname "$HERE")
OUT=${OUT:-$(mktemp -d /tmp/vs_pytorch.XXXXXX)}
mkdir -p "$OUT"
RESULTS="$OUT/results.jsonl"
: > "$RESULTS"

cd "$ROOT"
cargo bench --bench generator_ops --no-run >&2

ours() {
  cargo bench -q --bench generator_ops -- --reps "$REPS" --ops "$OPS" 2>/dev/null | tail -n 1
}
theirs() {
  "$PYTHON" "$HERE/reference_pytorch.py" --reference "$REFERENCE" --reps "$REPS" --threads 2 --ops "$OPS" | tail -n 1
}
record() { # side round
  local load; load=$(cut -d' ' -f1-3 /proc/loadavg)
  echo "round $2: $1 (load $load)" >&2
  local line; line=$("$1")
  echo "{\"side\": \"$1\", \"round\": $2, \"load\": \"$load\", \"data\": $line}" >> "$RESULTS"
}

for r in $(seq 1 "$ROUNDS"); do
  if (( r % 2 == 1 )); then record ours "$r"; record theirs "$r"
  else record theirs "$r"; record ours "$r"; fi
done
echo "final load $(cut -d' ' -f1-3 /proc/loadavg)" >&2

"$PYTHON" - "$RESULTS" <<'EOF'
import json, statistics, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
d0 = rows[0]["data"]
ops = [k for k in d0 if isinstance(d0[k], list) and not k.endswith("_cpu")]
t = {s: {k: [] for k in d0 if isinstance(d0[k], list)} for s in ("ours", "theirs")}
meta = {}
for r in rows:
    meta[r["side"]] = r["data"]
    for k in t[r["side"]]:
        t[r["side"]][k] += r["data"][k]
med = statistics.median
batch = lambda op: 8 if op.endswith("b8") else 1
for s in ("ours", "theirs"):
    m = meta[s]
    print(f"{s}: {m['impl']}, {m['params']} params, {m['threads']} threads")
print("load averages (1/5/15 min) before each process: " + "; ".join(f"{r['side']} r{r['round']} {r['load']}" for r in rows))
print()
print("Seconds per call: wall median over all rounds (images/s), wall best (least disturbed call),")
print("and the median process CPU time (all threads) of the same calls.")
print()
print("| operation | ours median (img/s) | reference median (img/s) | ref / ours | ours best | reference best | ref / ours, best | ours CPU | reference CPU | ref / ours, CPU | calls |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for op in ops:
    a, b = med(t["ours"][op]), med(t["theirs"][op])
    am, bm = min(t["ours"][op]), min(t["theirs"][op])
    ac, bc = med(t["ours"][op + "_cpu"]), med(t["theirs"][op + "_cpu"])
    n = batch(op)
    print(f"| {op} | {a:.3f} ({n/a:.1f}) | {b:.3f} ({n/b:.2f}) | {b/a:.1f}x | {am:.3f} | {bm:.3f} | {bm/am:.1f}x | {ac:.3f} | {bc:.3f} | {bc/ac:.1f}x | {len(t['ours'][op])}+{len(t['theirs'][op])} |")
print(f"\nraw: {sys.argv[1]}")
EOF
