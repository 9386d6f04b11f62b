#!/usr/bin/env bash
# slurm.test_farm: the farm scripts (deploy/slurm/) against a real one-node Slurm cluster on
# 127.0.0.1, brought up in a private directory and torn down at exit.
#   1. a fluid shot submitted with volfx-submit (a precompile job, a bake, an array of 4 tasks)
#      equals, file for file and byte for byte, one `volfx batch` of the same frames;
#   2. a task requeued mid-chunk resumes: the frames it had finished keep their mtimes, the
#      rest are rendered, no partial file is left and every frame still equals the reference;
#   3. a bad preset fails the render tasks (FAILED, exit 1, the reason in each task's log), and
#      fails the bake, which cancels the array waiting for it.
# Needs root (slurmd, munged); otherwise it says so and exits 77, which ctest counts as
# skipped. Installs slurm-wlm and munge with apt when they are missing.
#   tests/slurm/test_farm.sh [--bin BUILD/bin] [--keep]
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
root=$(cd "$here/../.." && pwd)
bin=$root/build/bin keep=0 args=("$@")
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) bin=$(cd "$2" && pwd); shift 2 ;;
    --keep) keep=1; shift ;;
    *) echo "usage: $0 [--bin DIR] [--keep]" >&2; exit 2 ;;
  esac
done
submit=$root/deploy/slurm/volfx-submit

# Under a time limit of its own, shorter than ctest's TIMEOUT: its SIGTERM runs the cleanup
# below, which tears the cluster down, where ctest would kill the test outright.
if [ -z "${VOLFX_FARM_TIMED:-}" ]; then
  export VOLFX_FARM_TIMED=1
  exec timeout --kill-after=60 780 bash "$0" "${args[@]}"
fi

if [ "$(id -u)" -ne 0 ]; then
  echo "SKIP: slurm.test_farm runs slurmd and munged, which needs root"
  exit 77
fi
if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null || ! command -v sbatch >/dev/null; then
  echo "test_farm: installing slurm-wlm and munge"
  apt-get update -q >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends slurm-wlm munge >/dev/null
fi
# shellcheck source=cluster.sh
source "$here/cluster.sh"

t_start=$SECONDS
tmp=$(mktemp -d /tmp/volfx-farm.XXXXXX)
chmod 755 "$tmp"
cleanup() {
  local rc=$?
  slurm_cluster_down "$tmp/slurm"
  if [ $keep -eq 1 ]; then echo "test_farm: kept $tmp"; else rm -rf "$tmp"; fi
  return $rc
}
trap cleanup EXIT
trap 'echo "test_farm: stopped by a signal (or out of time)" >&2; exit 130' INT TERM

log() { echo "test_farm: [$((SECONDS - t_start)) s] $*"; }
fail() {
  echo "test_farm: FAIL: $*" >&2
  local f
  for f in "$tmp"/*/logs/*.log; do
    [ -f "$f" ] || continue
    echo "----- $f" >&2
    tail -n 15 "$f" >&2
  done
  echo "----- slurmctld.log" >&2
  tail -n 20 "$tmp/slurm/slurmctld.log" >&2 2>/dev/null || true
  exit 1
}

# wait_idle SECONDS: until no job is queued or running.
wait_idle() {
  local deadline=$((SECONDS + $1))
  while [ -n "$(squeue -h -o %i)" ]; do
    [ $SECONDS -lt $deadline ] || { squeue >&2; fail "jobs still queued after $1 s"; }
    sleep 0.3
  done
}

# states ID: 'TASK STATE EXITCODE' for each job of job (or array) ID, from the last record
# that Slurm's job completion log holds for it; TASK is - for a job that is not an array.
states() {
  awk -v id="$1" '
    { delete f; for (i = 1; i <= NF; i++) { n = index($i, "="); if (n) f[substr($i, 1, n - 1)] = substr($i, n + 1) } }
    f["JobId"] == id || f["ArrayJobId"] == id {
      t = ("ArrayTaskId" in f) ? f["ArrayTaskId"] : "-"
      last[f["JobId"]] = t " " f["JobState"] " " f["ExitCode"]
    }
    END { for (j in last) print last[j] }' "$tmp/slurm/jobcomp.txt" | sort -n
}

# expect_states ID STATE COUNT: every job of ID ended in STATE, and there are COUNT of them.
expect_states() {
  local got n bad
  got=$(states "$1")
  n=$(printf '%s\n' "$got" | grep -c . || true)
  bad=$(printf '%s\n' "$got" | awk -v s="$2" 'NF && $2 != s' || true)
  [ "$n" -eq "$3" ] && [ -z "$bad" ] || fail "job $1: expected $3 x $2, got:"$'\n'"$got"
}

# same_frames DIR REF FIRST LAST: DIR holds exactly frames FIRST..LAST, each equal to REF's.
same_frames() {
  local f name n=0
  for ((f = $3; f <= $4; f++)); do
    name=f_$(printf %04d "$f").png
    [ -f "$1/$name" ] || fail "$1/$name is missing"
    cmp -s "$1/$name" "$2/$name" || fail "$1/$name differs from the one-process render $2/$name"
    n=$((n + 1))
  done
  local extra
  extra=$(find "$1" -maxdepth 1 -type f ! -name 'f_[0-9][0-9][0-9][0-9].png' | head -5)
  [ -z "$extra" ] || fail "stray files in $1: $extra"
  [ "$(find "$1" -maxdepth 1 -type f -name 'f_*.png' | wc -l)" -eq "$n" ] || fail "$1 has frames beyond $3..$4"
}

# Every run shares one kernel cache: the first compile fills it, the jobs find it warm.
export VOLFX_POCL_CACHE=$tmp/pocl
export POCL_CACHE_DIR=$VOLFX_POCL_CACHE
mkdir -p "$VOLFX_POCL_CACHE"
export VOLFX_BIN=$bin
preset=paper-001-flow size=(-W 64 -H 48) last=63 rq_last=239

log "starting a one-node cluster in $tmp/slurm"
slurm_cluster_up "$tmp/slurm" || fail "the cluster did not start"

log "one process: volfx batch $preset 0..$rq_last"
"$bin/volfx" batch "$preset" -s 0 -e "$rq_last" "${size[@]}" -o "$tmp/ref/f_####.png" ||
  fail "volfx batch of the reference failed"

# 1. bake + array, with a precompile job in front.
cd "$tmp"
log "farm: volfx-submit --precompile --chunk 16 (4 tasks)"
ids=$("$submit" "$preset" -s 0 -e "$last" -o "$tmp/farm/f_####.png" --chunk 16 --cpus 1 \
  --precompile "${size[@]}") || fail "volfx-submit failed"
echo "$ids"
pre=$(awk '$1 == "precompile" { print $2 }' <<<"$ids")
bake=$(awk '$1 == "bake" { print $2 }' <<<"$ids")
render=$(awk '$1 == "render" { print $2 }' <<<"$ids")
[ -n "$pre" ] && [ -n "$bake" ] && [ -n "$render" ] || fail "volfx-submit printed no job ids"
wait_idle 300
expect_states "$pre" COMPLETED 1
expect_states "$bake" COMPLETED 1
expect_states "$render" COMPLETED 4
[ -f "$tmp/farm/bake/bake.json" ] || fail "the bake wrote no bake.json"
same_frames "$tmp/farm" "$tmp/ref" 0 "$last"
for t in 0 1 2 3; do
  grep -q "done in" "$tmp/farm/logs/volfx-farm-${render}_$t.log" || fail "task $t's log has no end"
done
grep -q "compiled into $VOLFX_POCL_CACHE" "$tmp/farm/logs/volfx-farm-precompile-$pre.log" ||
  fail "the precompile job did not compile into the shared cache"
log "farm: 64 frames from 4 tasks equal the one-process render"

# The same submission again finds the bake complete and every frame done: nothing rewritten.
find "$tmp/farm" -maxdepth 1 -name 'f_*.png' -printf '%f %T@\n' | sort >"$tmp/farm-before.txt"
ids=$("$submit" "$preset" -s 0 -e "$last" -o "$tmp/farm/f_####.png" --chunk 16 --cpus 1 "${size[@]}") ||
  fail "volfx-submit failed"
render=$(awk '$1 == "render" { print $2 }' <<<"$ids")
wait_idle 120
expect_states "$render" COMPLETED 4
find "$tmp/farm" -maxdepth 1 -name 'f_*.png' -printf '%f %T@\n' | sort | cmp -s - "$tmp/farm-before.txt" ||
  fail "submitting a finished shot again rewrote frames"
log "farm: a second submission of the finished shot rewrote nothing"

# 2. requeue one task in the middle of its chunk: one task renders a longer shot of 240 frames
# on one CPU, re-simulating from frame 0 (no bake), so that its chunk lasts long enough.
log "requeue: one task of $((rq_last + 1)) frames, requeued once some frames are written"
ids=$("$submit" "$preset" -s 0 -e "$rq_last" -o "$tmp/rq/f_####.png" --chunk $((rq_last + 1)) --cpus 1 --no-bake \
  "${size[@]}") || fail "volfx-submit failed"
render=$(awk '$1 == "render" { print $2 }' <<<"$ids")
deadline=$((SECONDS + 120))
until [ "$(find "$tmp/rq" -maxdepth 1 -name 'f_*.png' 2>/dev/null | wc -l)" -ge 8 ]; do
  [ $SECONDS -lt $deadline ] || fail "the requeue task wrote no frames in 120 s"
  sleep 0.05
done
scontrol requeue "${render}_0" || fail "scontrol requeue ${render}_0 refused"
# Until the first run is gone: the task pending again, no batch of it left running.
deadline=$((SECONDS + 60))
until [ "$(squeue -h -j "$render" -o %t 2>/dev/null)" = PD ]; do
  [ $SECONDS -lt $deadline ] || fail "the requeued task did not return to pending"
  sleep 0.1
done
done_before=$(find "$tmp/rq" -maxdepth 1 -name 'f_*.png' | wc -l)
[ "$done_before" -lt $((rq_last + 1)) ] || fail "the task finished all frames before the requeue landed"
find "$tmp/rq" -maxdepth 1 -name 'f_*.png' -printf '%f %T@\n' | sort >"$tmp/rq-before.txt"
log "requeue: $done_before frames were done when the requeue stopped the task"
wait_idle 300
expect_states "$render" COMPLETED 1
find "$tmp/rq" -maxdepth 1 -name 'f_*.png' -printf '%f %T@\n' | sort |
  join - "$tmp/rq-before.txt" | awk '$2 != $3 { print; bad = 1 } END { exit bad }' ||
  fail "frames finished before the requeue were written again (name, mtime now, mtime before)"
partial=$(find "$tmp/rq" -name '*.part*' | head -5)
[ -z "$partial" ] || fail "partial files left: $partial"
same_frames "$tmp/rq" "$tmp/ref" 0 "$rq_last"
rq_log=$tmp/rq/logs/volfx-rq-${render}_0.log
grep -q "restart 1" "$rq_log" || fail "the task's log does not show its second run"
log "requeue: the rerun kept the $done_before finished frames and completed the rest"

# 3. a bad preset: the render tasks fail with the reason in their logs; a failed bake cancels
# the array behind it.
log "failure: a preset that does not exist"
ids=$("$submit" no-such-preset -s 0 -e 3 -o "$tmp/bad/f_####.png" --chunk 2 --no-bake "${size[@]}") ||
  fail "volfx-submit failed"
render=$(awk '$1 == "render" { print $2 }' <<<"$ids")
ids=$("$submit" no-such-preset -s 0 -e 3 -o "$tmp/badbake/f_####.png" --chunk 2 "${size[@]}") ||
  fail "volfx-submit failed"
bake2=$(awk '$1 == "bake" { print $2 }' <<<"$ids")
render2=$(awk '$1 == "render" { print $2 }' <<<"$ids")
wait_idle 120
expect_states "$render" FAILED 2
[ "$(states "$render" | awk '{ print $3 }' | sort -u)" = 1:0 ] || fail "the failed tasks' exit code is not 1:0"
for t in 0 1; do
  f=$tmp/bad/logs/volfx-bad-${render}_$t.log
  grep -q "no-such-preset" "$f" || fail "task $t's log does not name the preset: $(cat "$f")"
  grep -q "FAILED: exit status 1" "$f" || fail "task $t's log does not say it failed: $(cat "$f")"
done
expect_states "$bake2" FAILED 1
grep -q "no-such-preset" "$tmp/badbake/logs/volfx-badbake-bake-$bake2.log" || fail "the bake's log does not name the preset"
states "$render2" | grep -q . && ! states "$render2" | grep -qv CANCELLED ||
  fail "the array behind a failed bake was not cancelled: $(states "$render2")"
[ -z "$(find "$tmp/bad" "$tmp/badbake" -name 'f_*')" ] || fail "a failed job left frames"
log "failure: FAILED with the reason in the logs, the array behind the bake cancelled"

# 4. usage errors: exit 2 and a usage text, nothing submitted.
for args in "$preset -s 5 -e 3 -o x/f_####.png" "$preset -s 0 -o x/f_####.png" \
  "-s 0 -e 3 -o x/f_####.png" "$preset -s 0 -e 3 -o x/f.png" "$preset -s 0 -e 3 -o x/f_####.png --chunk 0"; do
  # shellcheck disable=SC2086
  if "$submit" $args >"$tmp/usage.out" 2>&1; then rc=0; else rc=$?; fi
  [ $rc -eq 2 ] && grep -q "^usage:" "$tmp/usage.out" || fail "volfx-submit $args: exit $rc, $(cat "$tmp/usage.out")"
done
[ -z "$(squeue -h -o %i)" ] || fail "a usage error submitted a job"

log "PASS"
