#!/usr/bin/env bash
# Pass-through benchmark: `rangegan-mcap convert` against the bare mcap crate
# reading and rewriting the same file, alternating runs, in one go.
# Usage: bash benches/passthrough.sh [SIZE_MB] [RUNS]   (default 1200 MB, 3 runs)
# Prints wall seconds, MB/s and peak RSS per run (GNU time), then medians.
set -euo pipefail
cd "$(dirname "$0")/.."
size=${1:-1200}; runs=${2:-3}
dir=$(mktemp -d /tmp/rangegan-bench.XXXX); trap 'rm -rf "$dir"' EXIT
cargo build --release --quiet --bin rangegan-mcap --example bare_mcap_copy --example make_recording
bin=target/release
$bin/examples/make_recording "$dir/in.mcap" "$size"
$bin/examples/make_recording "$dir/small.mcap" $((size / 4))
bytes=$(stat -c %s "$dir/in.mcap")
echo "input: $bytes bytes; small input: $(stat -c %s "$dir/small.mcap") bytes"
measure() { # name, command...
  local name=$1; shift
  /usr/bin/time -f "%e %M" -o "$dir/t" "$@" >/dev/null 2>&1
  read -r secs kb <"$dir/t"
  printf '%-28s %8.2f s %8.1f MB/s %8.0f MB peak RSS\n' "$name" "$secs" "$(echo "$bytes / 1000000 / $secs" | bc -l)" "$(echo "$kb / 1024" | bc -l)"
  echo "$name $secs $kb" >>"$dir/all"
}
for r in $(seq "$runs"); do
  measure "bare mcap copy" $bin/examples/bare_mcap_copy "$dir/in.mcap" "$dir/bare.mcap"
  measure "rangegan-mcap convert" $bin/rangegan-mcap convert "$dir/in.mcap" "$dir/ours.mcap" --force --quiet
done
# Peak memory must not grow with the file: the same conversion on a quarter-size input.
/usr/bin/time -f "%e %M" -o "$dir/t" $bin/rangegan-mcap convert "$dir/small.mcap" "$dir/small.out.mcap" --force --quiet
read -r _ kb_small <"$dir/t"
echo "medians:"
for name in "bare mcap copy" "rangegan-mcap convert"; do
  grep "^$name " "$dir/all" | awk -v b="$bytes" -v n="$name" '{print $(NF-1), $NF}' | sort -n |
    awk -v b="$bytes" -v n="$name" '{s[NR]=$1; m[NR]=$2} END {i=int((NR+1)/2); printf "  %-24s %.2f s  %.1f MB/s  %.0f MB peak\n", n, s[i], b/1e6/s[i], m[i]/1024}'
done
echo "  convert peak RSS on the quarter-size input: $((kb_small / 1024)) MB"
