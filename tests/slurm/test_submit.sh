#!/usr/bin/env bash
# slurm.test_submit: the farm scripts' arithmetic and argument checks, without Slurm or root.
# volfx-submit --dry-run prints the sbatch calls it would make; volfx-task runs against a
# volfx that only records its arguments.
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
root=$(cd "$here/../.." && pwd)
submit=$root/deploy/slurm/volfx-submit
task=$root/deploy/slurm/volfx-task
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
fails=0
fail() {
  echo "test_submit: FAIL: $*" >&2
  fails=$((fails + 1))
}

# A volfx and volfxd that print what they were asked and the environment that matters.
mkdir -p "$tmp/bin"
cat >"$tmp/bin/volfx" <<'EOF'
#!/bin/sh
echo "ARGS $*"
echo "THREADS ${POCL_MAX_PTHREAD_COUNT:-unset} CACHE ${POCL_CACHE_DIR:-unset}"
case "$*" in *fail-me*) echo "volfx batch: frame 3: it broke" >&2; exit 1 ;; esac
EOF
cp "$tmp/bin/volfx" "$tmp/bin/volfxd"
chmod +x "$tmp/bin/volfx" "$tmp/bin/volfxd"
export VOLFX_BIN=$tmp/bin
unset VOLFX_POCL_CACHE POCL_CACHE_DIR POCL_MAX_PTHREAD_COUNT SLURM_CPUS_PER_TASK SLURM_CPUS_ON_NODE

# expect_exit CODE CMD...: the command exits CODE; its output is left in $tmp/out.
expect_exit() {
  local want=$1 rc=0
  shift
  "$@" >"$tmp/out" 2>&1 || rc=$?
  [ $rc -eq "$want" ] || fail "$*: exit $rc, expected $want: $(head -3 "$tmp/out")"
}
# expect_out TEXT: $tmp/out holds TEXT (a fixed string).
expect_out() { grep -qF -- "$1" "$tmp/out" || fail "expected '$1' in: $(cat "$tmp/out")"; }
expect_no() { ! grep -qF -- "$1" "$tmp/out" || fail "did not expect '$1' in: $(cat "$tmp/out")"; }

cd "$tmp"

# Usage errors: exit 2 with the usage text.
for args in "" "demo" "demo -s 0 -e 9" "demo -s 0 -o o/f_####.png" "demo -e 9 -o o/f_####.png" \
  "demo -s 9 -e 3 -o o/f_####.png" "demo -s x -e 3 -o o/f_####.png" "demo -s 0 -e 9 -o o/f.png" \
  "demo -s 0 -e 9 -o o/f_####.png --chunk 0" "demo -s 0 -e 9 -o o/f_####.png --chunk" \
  "demo -s 0 -e 9 -o o/f_####.png --max-running 0" "demo -s 0 -e 9 -o o/f_####.png -j 0" \
  "demo -s 0 -e 9 -o o/f_####.png --every -1" "demo -s 0 -e 9 -o o/f_####.png --bogus" \
  "demo other -s 0 -e 9 -o o/f_####.png" "demo -s 0 -e 9 -o o/f_####.png --no-bake --every 4" \
  "demo -s 0 -e 9 -o o/f_####.png --cpus 0"; do
  # shellcheck disable=SC2086
  expect_exit 2 "$submit" $args
  expect_out "usage: volfx-submit"
done
[ ! -e o ] || fail "a usage error created the output directory"
expect_exit 0 "$submit" --help
expect_out "usage: volfx-submit"

# 64 frames in chunks of 16: a bake every 16 frames, an array of 4 tasks behind it.
expect_exit 0 "$submit" paper-001-flow -s 0 -e 63 -o 'shots/a/f_####.png' -W 64 -H 48 --dry-run
expect_out "bake 1000"
expect_out "render 1001"
expect_out "--array=0-3 "
expect_out "--dependency=afterok:1000"
expect_out "--requeue"
expect_out "-e 63 -k 16 -o shots/a/bake"
expect_out "--bake shots/a/bake"
expect_out "--output=shots/a/logs/%x-%A_%a.log"
expect_out "scontrol release 1000"
# Throttle, step, options for sbatch, no bake.
expect_exit 0 "$submit" demo -s 10 -e 30 -j 3 --chunk 2 --max-running 2 --no-bake --partition p \
  --account=acc --cpus 4 --time 1:00:00 --sbatch=--qos=hi -o 'o/f_####.png' --dry-run
expect_out "--array=0-3%2 " # frames 10, 13, ..., 28: 7 frames in 4 tasks
expect_out "--partition=p"
expect_out "--account=acc"
expect_out "--cpus-per-task=4"
expect_out "--time=1:00:00"
expect_out "--qos=hi"
expect_out "--first 10 --last 30 --step 3 --chunk 2"
expect_no "bake"
expect_out "render 1000"
# A precompile job in front: the bake waits for it, and only the first job is held.
expect_exit 0 "$submit" demo -s 0 -e 99 --every 10 --precompile -o 'o/f_####.png' --dry-run
expect_out "precompile 1000"
expect_out "bake 1001"
expect_out "render 1002"
expect_out "--array=0-6 "
expect_out "-k 10"
[ "$(grep -c -- --hold "$tmp/out")" -eq 1 ] || fail "more than one job held: $(cat "$tmp/out")"
expect_out "scontrol release 1000"

# volfx-task: the frame range of each array task, clamped to the last frame.
run_task() { # run_task TASK_ID ARGS...
  local id=$1
  shift
  SLURM_ARRAY_TASK_ID=$id expect_exit 0 "$task" render "$@"
}
run_task 0 --first 0 --last 63 --chunk 16 -- demo -o 'o/f_####.png'
expect_out "ARGS batch demo -o o/f_####.png -s 0 -e 15 -j 1"
run_task 3 --first 0 --last 63 --chunk 16 -- demo -o 'o/f_####.png'
expect_out "-s 48 -e 63 -j 1"
run_task 3 --first 5 --last 60 --chunk 16 -- demo -o 'o/f_####.png'
expect_out "-s 53 -e 60 -j 1"
run_task 1 --first 10 --last 30 --step 3 --chunk 2 -- demo -o 'o/f_####.png'
expect_out "-s 16 -e 19 -j 3"
run_task 3 --first 10 --last 30 --step 3 --chunk 2 -- demo -o 'o/f_####.png'
expect_out "-s 28 -e 30 -j 3"
run_task 4 --first 0 --last 63 --chunk 16 -- demo -o 'o/f_####.png'
expect_out "nothing to do"
expect_no "ARGS"
# Threads from the task's CPUs unless set; the kernel cache from --cache or VOLFX_POCL_CACHE.
SLURM_CPUS_PER_TASK=3 run_task 0 --first 0 --last 3 --chunk 4 -- demo -o 'o/f_####.png'
expect_out "THREADS 3 "
SLURM_CPUS_PER_TASK=3 POCL_MAX_PTHREAD_COUNT=1 run_task 0 --first 0 --last 3 --chunk 4 -- demo -o 'o/f_####.png'
expect_out "THREADS 1 "
VOLFX_POCL_CACHE=/x/pocl run_task 0 --first 0 --last 3 --chunk 4 -- demo -o 'o/f_####.png'
expect_out "CACHE /x/pocl"
run_task 0 --first 0 --last 3 --chunk 4 --cache /y -- demo -o 'o/f_####.png'
expect_out "CACHE /y"
# A failure: the command's status, its reason kept, a FAILED line last.
SLURM_ARRAY_TASK_ID=0 expect_exit 1 "$task" render --first 0 --last 3 --chunk 4 -- fail-me -o 'o/f_####.png'
expect_out "frame 3: it broke"
tail -n 1 "$tmp/out" | grep -q "FAILED: exit status 1" || fail "no FAILED line last: $(cat "$tmp/out")"
# Bad task arguments and a missing binary.
expect_exit 2 "$task" render --first 0 --last 3 -- demo
expect_exit 2 "$task" render --first 5 --last 3 --chunk 1 -- demo
expect_exit 2 "$task" nonsense
VOLFX_BIN=$tmp/none expect_exit 1 "$task" bake -- demo -e 3 -o b
expect_out "no volfx binary"
expect_exit 0 "$task" bake -- demo -e 3 -o b
expect_out "ARGS bake demo -e 3 -o b"
expect_exit 0 "$task" precompile --cache "$tmp/cache"
expect_out "ARGS --precompile"
expect_out "CACHE $tmp/cache"

if [ $fails -ne 0 ]; then
  echo "test_submit: $fails checks failed" >&2
  exit 1
fi
echo "test_submit: PASS"
