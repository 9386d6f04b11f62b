#!/usr/bin/env bash
# Render-farm job: renders frames FIRST..LAST of a scene preset on this node, stepping the
# simulation between frames, with a private volfxd. Usage:
#   deploy/farm-render.sh PRESET FIRST LAST OUTDIR [WIDTH HEIGHT]
# Frames are written as OUTDIR/frame_NNNNNN.png. Exits non-zero on the first failure.
set -euo pipefail
preset=$1 first=$2 last=$3 outdir=$4 width=${5:-1920} height=${6:-1080}
bin=${VOLFX_BIN:-$(dirname "$0")/../build/bin}
mkdir -p "$outdir"
log=$(mktemp)
"$bin/volfxd" --listen 127.0.0.1:0 --scene "$preset" --log-level warn >"$log" &
pid=$!
trap 'kill $pid 2>/dev/null || true; rm -f "$log"' EXIT
for _ in $(seq 1 600); do
  grep -q listening "$log" && break
  kill -0 $pid || { echo "farm-render: volfxd did not start" >&2; exit 1; }
  sleep 0.05
done
port=$(sed -n 's/.*listening on .*:\([0-9]*\)$/\1/p' "$log")
script=$(mktemp)
{
  [ "$first" -gt 0 ] && echo "step $first"
  for ((f = first; f <= last; f++)); do
    printf 'render -o %s/frame_%06d.png -W %d -H %d\n' "$outdir" "$f" "$width" "$height"
    [ "$f" -lt "$last" ] && echo "step 1"
  done
} >"$script"
"$bin/volfx" --port "$port" script "$script"
rm -f "$script"
"$bin/volfx" --port "$port" shutdown >/dev/null
wait $pid
echo "farm-render: frames $first..$last of $preset in $outdir"
