#!/usr/bin/env bash
# A fluid shot on one node, with and without the farm (not run by ctest). Needs root: it brings
# up the private one-node Slurm cluster of tests/slurm/cluster.sh on 127.0.0.1.
#
#   tests/bench/bench_farm.sh [--bin build/bin] [--runs N] [--frames F] [-W W -H H]
#                             [--tasks T] [--cpus C] [--preset P]
#
# Measures, for frames 0..F-1 (default 240) of P (default paper-001-flow) at W x H (default
# 320 x 180), every process timed by a wrapper around volfx (wall, and the user + system CPU of
# volfx and its private volfxd):
#   1. one process: volfx batch -s 0 -e F-1 (all cores);
#   2. the farm: volfx-submit, a bake then an array of T tasks (default 4) of C CPUs (default
#      1) each, on the one node: wall from submission to the last task's end, the CPU of all
#      jobs, and the bake's and the tasks' own walls;
#   3. the same array without the bake (--no-bake: each task simulates from frame 0);
#   4. the first frame from a cold start: volfx batch of one frame with an empty kernel cache,
#      and with the cache volfxd --precompile filled (and the precompile itself).
# Every farm frame is checked byte for byte against the one-process frames. Prints the medians
# of N runs (default 3) as markdown tables.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
root=$(cd "$here/../.." && pwd)
bin=$root/build/bin runs=3 frames=240 width=320 height=180 tasks=4 cpus=1 preset=paper-001-flow
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) bin=$(cd "$2" && pwd); shift 2 ;;
    --runs) runs=$2; shift 2 ;;
    --frames) frames=$2; shift 2 ;;
    -W) width=$2; shift 2 ;;
    -H) height=$2; shift 2 ;;
    --tasks) tasks=$2; shift 2 ;;
    --cpus) cpus=$2; shift 2 ;;
    --preset) preset=$2; shift 2 ;;
    *) sed -n '2,/^set -e/p' "$0" | sed 's/^# \{0,1\}//;$d' >&2; exit 2 ;;
  esac
done
[ "$(id -u)" -eq 0 ] || { echo "bench_farm: needs root (it runs slurmd and munged)" >&2; exit 2; }
# shellcheck source=../slurm/cluster.sh
source "$root/tests/slurm/cluster.sh"

tmp=$(mktemp -d /tmp/volfx-bench-farm.XXXXXX)
chmod 755 "$tmp"
trap 'slurm_cluster_down "$tmp/slurm"; rm -rf "$tmp"' EXIT
trap 'exit 130' INT TERM
last=$((frames - 1))
chunk=$(((frames + tasks - 1) / tasks))
size=(-W "$width" -H "$height")

# A volfx that records each run as 'wall_s cpu_s ARGS' in $BENCH_TIMES (the CPU of volfx and
# every descendant it waited for, its volfxd included). volfx finds volfxd beside its real self.
mkdir -p "$tmp/wrap"
cat >"$tmp/wrap/volfx" <<EOF
#!/usr/bin/env python3
import os, resource, subprocess, sys, time
t0 = time.monotonic()
rc = subprocess.call(["$bin/volfx"] + sys.argv[1:])
wall = time.monotonic() - t0
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
with open(os.environ["BENCH_TIMES"], "a") as f:
    f.write("%.3f %.3f %s\n" % (wall, ru.ru_utime + ru.ru_stime, " ".join(sys.argv[1:])))
sys.exit(rc if rc >= 0 else 128 - rc)
EOF
chmod +x "$tmp/wrap/volfx"
ln -s "$bin/volfxd" "$tmp/wrap/volfxd"
export BENCH_TIMES=$tmp/times.txt VOLFX_BIN=$tmp/wrap
export VOLFX_POCL_CACHE=$tmp/pocl POCL_CACHE_DIR=$tmp/pocl
unset POCL_MAX_PTHREAD_COUNT

median() { sort -g | awk '{ v[NR] = $1 } END { printf "%.2f\n", NR % 2 ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }
now() { date +%s.%N; }

slurm_cluster_up "$tmp/slurm" >/dev/null
"$bin/volfxd" --precompile >/dev/null

# 1. one process
: >"$tmp/one.txt"
for ((r = 1; r <= runs; r++)); do
  rm -rf "$tmp/one" && : >"$BENCH_TIMES"
  "$tmp/wrap/volfx" batch "$preset" -s 0 -e "$last" "${size[@]}" -o "$tmp/one/f_####.png" >/dev/null 2>&1
  cat "$BENCH_TIMES" >>"$tmp/one.txt"
  echo "bench_farm: one process, run $r: $(cut -d' ' -f1,2 "$BENCH_TIMES") (wall s, cpu s)" >&2
done

# 2 and 3. the farm on the one node, with and without the bake
farm_run() { # farm_run NAME [volfx-submit options...]: one submission, timed; appends to NAME.txt
  local name=$1 t0 t1 out=$tmp/$1
  shift
  rm -rf "$out" && : >"$BENCH_TIMES"
  t0=$(now)
  (cd "$tmp" && "$root/deploy/slurm/volfx-submit" "$preset" -s 0 -e "$last" -o "$out/f_####.png" \
    --chunk "$chunk" --cpus "$cpus" "${size[@]}" "$@" >/dev/null 2>&1)
  while [ -n "$(squeue -h -o %i)" ]; do sleep 0.1; done
  t1=$(now)
  local f
  for ((f = 0; f <= last; f++)); do
    cmp -s "$out/f_$(printf %04d $f).png" "$tmp/one/f_$(printf %04d $f).png" ||
      { echo "bench_farm: $name frame $f differs from the one-process frame" >&2; exit 1; }
  done
  awk -v wall="$(echo "$t1 - $t0" | bc)" '
    $3 == "bake" { bake = $1 }
    $3 == "batch" { n++; if ($1 > tmax) tmax = $1; if (tmin == "" || $1 < tmin) tmin = $1 }
    { cpu += $2 }
    END { printf "%.3f %.3f %.3f %.3f %.3f\n", wall, cpu, bake + 0, tmin, tmax }' "$BENCH_TIMES" >>"$tmp/$name.txt"
  echo "bench_farm: $name: $(tail -n 1 "$tmp/$name.txt") (wall, cpu, bake wall, task wall min, max)" >&2
}
: >"$tmp/baked.txt"
: >"$tmp/nobake.txt"
for ((r = 1; r <= runs; r++)); do
  farm_run baked
  farm_run nobake --no-bake
done

# 4. the cold first frame
: >"$tmp/cold.txt"
: >"$tmp/warm.txt"
: >"$tmp/precompile.txt"
for ((r = 1; r <= runs; r++)); do
  rm -rf "$tmp/cold-cache" "$tmp/f1" && : >"$BENCH_TIMES"
  POCL_CACHE_DIR=$tmp/cold-cache "$tmp/wrap/volfx" batch "$preset" -s 0 -e 0 "${size[@]}" -o "$tmp/f1/f_####.png" >/dev/null 2>&1
  cut -d' ' -f1,2 "$BENCH_TIMES" >>"$tmp/cold.txt"
  rm -rf "$tmp/pre-cache" "$tmp/f1" && : >"$BENCH_TIMES"
  t0=$(now)
  POCL_CACHE_DIR=$tmp/pre-cache "$bin/volfxd" --precompile >/dev/null
  echo "$(now) - $t0" | bc >>"$tmp/precompile.txt"
  POCL_CACHE_DIR=$tmp/pre-cache "$tmp/wrap/volfx" batch "$preset" -s 0 -e 0 "${size[@]}" -o "$tmp/f1/f_####.png" >/dev/null 2>&1
  cut -d' ' -f1,2 "$BENCH_TIMES" >>"$tmp/warm.txt"
  echo "bench_farm: first frame, run $r: cold $(tail -n 1 "$tmp/cold.txt"), precompiled $(tail -n 1 "$tmp/warm.txt")" >&2
done

col() { awk -v c="$1" '{ print $c }' "$2" | median; }
cat <<EOF

$preset, frames 0..$last at ${width}x$height, $(nproc) CPUs ($(lscpu | sed -n 's/^Model name: *//p' | head -1)), median of $runs runs.
Farm: one Slurm node, $tasks tasks of $chunk frames, $cpus CPU(s) each (POCL_MAX_PTHREAD_COUNT=$cpus), at most $(($(nproc) / cpus)) at once.

| run | wall s | CPU s (user + sys) |
| --- | ---: | ---: |
| one process: \`volfx batch $preset -s 0 -e $last -W $width -H $height\` | $(col 1 "$tmp/one.txt") | $(col 2 "$tmp/one.txt") |
| farm: bake + $tasks-task array (\`volfx-submit ... --chunk $chunk --cpus $cpus\`) | $(col 1 "$tmp/baked.txt") | $(col 2 "$tmp/baked.txt") |
| farm without bake (\`--no-bake\`, each task simulates from frame 0) | $(col 1 "$tmp/nobake.txt") | $(col 2 "$tmp/nobake.txt") |

| farm part | with bake | without bake |
| --- | ---: | ---: |
| bake job wall s (\`volfx bake -e $last -k $chunk\`) | $(col 3 "$tmp/baked.txt") | - |
| fastest task wall s | $(col 4 "$tmp/baked.txt") | $(col 4 "$tmp/nobake.txt") |
| slowest task wall s | $(col 5 "$tmp/baked.txt") | $(col 5 "$tmp/nobake.txt") |

| first frame (\`volfx batch $preset -s 0 -e 0 -W $width -H $height\`) | wall s | CPU s |
| --- | ---: | ---: |
| empty kernel cache (fresh POCL_CACHE_DIR) | $(col 1 "$tmp/cold.txt") | $(col 2 "$tmp/cold.txt") |
| cache filled by \`volfxd --precompile\` | $(col 1 "$tmp/warm.txt") | $(col 2 "$tmp/warm.txt") |
| \`volfxd --precompile\` itself | $(median <"$tmp/precompile.txt") | |
EOF
