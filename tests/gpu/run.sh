#!/usr/bin/env bash
# One-shot check of volfx on a machine with an NVIDIA GPU (tests/gpu/README.md): finds the
# OpenCL ICD, builds, compiles every kernel for the GPU, runs the kernel unit tests and
# volfxd there, compares a GPU frame with PoCL's CPU frame, runs the render benchmarks, and
# writes a markdown report. Every step has a time limit inside an overall budget (default
# 290 s); a step that fails or cannot run is reported and the next one runs.
#
#   tests/gpu/run.sh [--cpu] [--out DIR] [--build DIR] [--no-build] [--budget S] [--runs N]
#
#   --cpu        run everything on the CPU device instead (PoCL), to check this script on a
#                machine without a GPU
#   --out DIR    where the report (gpu-report.md), its logs and frames go; default $OUT when
#                set, else BUILD/gpu-report
#   --build DIR  the build tree (default build-gpu)
#   --no-build   use the build tree as it is
#   --budget S   overall time limit in seconds (default 290)
#   --runs N     runs per benchmark figure (default 5)
#
# Exit status: 0 when every step passed, 1 when one failed or could not run (the report says
# which), 2 for a bad command line.
set -uo pipefail
export LC_ALL=C

mode=gpu
build=build-gpu
do_build=1
out=
budget=290
runs=5
while [ $# -gt 0 ]; do
  case "$1" in
    --cpu) mode=cpu ;;
    --out) out=${2:?--out needs a directory}; shift ;;
    --build) build=${2:?--build needs a directory}; shift ;;
    --no-build) do_build=0 ;;
    --budget) budget=${2:?--budget needs seconds}; shift ;;
    --runs) runs=${2:?--runs needs a count}; shift ;;
    -h|--help) sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "tests/gpu/run.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done
case "$budget$runs" in *[!0-9]*) echo "tests/gpu/run.sh: --budget and --runs take whole numbers" >&2; exit 2 ;; esac

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$root"
case "$build" in /*) ;; *) build=$root/$build ;; esac
[ -n "$out" ] || out=${OUT:-$build/gpu-report}
mkdir -p "$out/logs" || { echo "tests/gpu/run.sh: cannot create $out" >&2; exit 2; }
out=$(cd "$out" && pwd)
report=$out/gpu-report.md
work=$(mktemp -d "${TMPDIR:-/tmp}/volfx-gpu.XXXXXX")
started=$SECONDS
deadline=$((SECONDS + budget))
failed=0
steps=()    # "name|status|seconds|note" rows of the step table
missing=()  # what could not be done, one sentence each
servers=()  # pids of the volfxd this script started

cleanup() {
  local pid
  for pid in "${servers[@]}"; do kill -TERM "$pid" 2>/dev/null; done
  rm -rf "$work"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

say() { printf '[gpu-check %3ds] %s\n' $((SECONDS - started)) "$*"; }
left() { echo $((deadline - SECONDS)); }

# step NAME LIMIT CMD...: runs CMD with its output in logs/NAME.log, for at most LIMIT seconds
# and never past the budget; records the outcome. Returns CMD's status (124 on time-out).
step() {
  local name=$1 limit=$2 rest t0 rc status
  shift 2
  rest=$(($(left) - 5))
  if [ "$rest" -lt 5 ]; then
    steps+=("$name|skipped|0|out of time")
    missing+=("$name: not run, the ${budget} s budget was spent")
    failed=1
    return 125
  fi
  [ "$limit" -le "$rest" ] || limit=$rest
  say "$name (at most ${limit} s)"
  t0=$SECONDS
  timeout --kill-after=5 "$limit" "$@" >"$out/logs/$name.log" 2>&1
  rc=$?
  case $rc in
    0) status=ok ;;
    124|137) status="timed out after ${limit} s" ;;
    *) status="FAILED (status $rc)" ;;
  esac
  [ $rc -eq 0 ] || failed=1
  steps+=("$name|$status|$((SECONDS - t0))|logs/$name.log")
  return $rc
}

# skip NAME WHY: records a step that could not run.
skip() {
  steps+=("$1|skipped|0|$2")
  missing+=("$1: $2")
  failed=1
  say "$1 skipped: $2"
}

# ---------------------------------------------------------------------------------------------
# The machine and its OpenCL drivers

export POCL_CACHE_DIR=$work/pocl-cache     # a cold kernel cache: compile times are real
export CUDA_CACHE_PATH=$work/cuda-cache    # the same for NVIDIA's compiled-program cache
machine=$work/machine.md
{
  echo "- host: $(uname -n), $(uname -sr), $(nproc) CPUs ($(grep -m1 'model name' /proc/cpuinfo 2>/dev/null | cut -d: -f2- | sed 's/^ //'))"
  if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null |
      sed 's/^/- GPU (nvidia-smi): /'
  else
    echo "- nvidia-smi: not installed"
  fi
} >"$machine"
command -v nvidia-smi >/dev/null 2>&1 || [ "$mode" = cpu ] || missing+=("nvidia-smi is not installed: no GPU facts from the driver")

# The OpenCL ICD: the loader reads /etc/OpenCL/vendors (or $OCL_ICD_VENDORS). Where NVIDIA's
# OpenCL library is present without its .icd file (some containers), a private vendors
# directory names it, with the other vendors' files beside it.
vendors=${OCL_ICD_VENDORS:-/etc/OpenCL/vendors}
nvidia_icd=
if [ -f "$vendors/nvidia.icd" ]; then
  nvidia_icd="$vendors/nvidia.icd ($(cat "$vendors/nvidia.icd"))"
else
  lib=$( (ldconfig -p 2>/dev/null | awk '/libnvidia-opencl\.so\.1/ {print $NF; exit}') )
  for d in /usr/lib/x86_64-linux-gnu /usr/lib64 /usr/lib /usr/local/nvidia/lib64; do
    [ -n "$lib" ] || [ ! -e "$d/libnvidia-opencl.so.1" ] || lib=$d/libnvidia-opencl.so.1
  done
  if [ -n "$lib" ]; then
    mkdir -p "$work/vendors"
    cp "$vendors"/*.icd "$work/vendors/" 2>/dev/null
    echo "$lib" >"$work/vendors/nvidia.icd"
    export OCL_ICD_VENDORS=$work/vendors
    nvidia_icd="none in $vendors; made one for $lib (OCL_ICD_VENDORS)"
  fi
fi
{
  echo "- OpenCL vendors ($vendors): $(cd "$vendors" 2>/dev/null && ls -- *.icd 2>/dev/null | tr '\n' ' ' || echo none)"
  echo "- NVIDIA ICD: ${nvidia_icd:-not found}"
  loader=$( (ldconfig -p 2>/dev/null | awk '/libOpenCL\.so\.1/ {print $NF; exit}') )
  echo "- OpenCL loader: ${loader:-not found by ldconfig}"
} >>"$machine"
if [ -z "$nvidia_icd" ] && [ "$mode" = gpu ]; then
  missing+=("no NVIDIA OpenCL ICD (nvidia.icd or libnvidia-opencl.so.1): the GPU cannot be used")
fi
if command -v clinfo >/dev/null 2>&1; then
  timeout 30 clinfo -l >"$out/logs/clinfo.log" 2>&1
  { echo "- clinfo -l:"; echo; sed 's/^/      /' "$out/logs/clinfo.log"; echo; } >>"$machine"
else
  echo "- clinfo: not installed" >>"$machine"
fi

# ---------------------------------------------------------------------------------------------
# The build

bin=$build/bin
units=(test_render test_render_fluid test_render_fluid_sim test_render_volume test_render_waves)
benches=(bench_render bench_render_volume bench_render_fluid bench_render_sph bench_render_waves)
if [ $do_build -eq 1 ]; then
  need=()
  for tool in cmake cc pkg-config make; do command -v $tool >/dev/null 2>&1 || need+=("$tool"); done
  for pc in libuv libcjson libpng zlib; do
    command -v pkg-config >/dev/null 2>&1 && ! pkg-config --exists $pc && need+=("$pc (pkg-config)")
  done
  [ -f /usr/include/CL/cl.h ] || [ -f /usr/local/include/CL/cl.h ] || need+=("CL/cl.h (opencl-headers)")
  if [ ${#need[@]} -gt 0 ]; then
    skip build "missing ${need[*]}"
  else
    step configure 120 cmake -S "$root" -B "$build" -DCMAKE_BUILD_TYPE=Release &&
      step build 240 cmake --build "$build" -j "$(nproc)" --target volfxd volfx_cli "${units[@]}" "${benches[@]}"
  fi
fi
if [ ! -x "$bin/volfxd" ]; then
  skip binaries "no $bin/volfxd: nothing else can run"
fi

# ---------------------------------------------------------------------------------------------
# The device: every kernel (the fluid's too) compiled for it, from a cold cache

device_name=
if [ -x "$bin/volfxd" ]; then
  if step precompile 120 "$bin/volfxd" --device $mode --precompile; then
    device_name=$(sed -n 's/^volfxd: kernels for \(.*\) compiled into .* in \([0-9]*\) ms$/\1/p' "$out/logs/precompile.log")
    compile_ms=$(sed -n 's/^volfxd: kernels for .* in \([0-9]*\) ms$/\1/p' "$out/logs/precompile.log")
  else
    missing+=("the $mode device did not open or its kernels did not compile: $(tail -1 "$out/logs/precompile.log" | cut -c1-300)")
  fi
fi

# ---------------------------------------------------------------------------------------------
# The kernel unit tests on the device (VOLFX_DEVICE picks it for them)

unit_rows=()
if [ -n "$device_name" ]; then
  for t in "${units[@]}"; do
    if [ ! -x "$build/tests/$t" ]; then
      skip "$t" "not built"
      continue
    fi
    VOLFX_DEVICE=$mode step "$t" 120 "$build/tests/$t"
    summary=$(grep -E '^[0-9]+ checks, [0-9]+ fail' "$out/logs/$t.log" | tail -1)
    unit_rows+=("$t|${summary:-no summary line}")
  done
fi

# ---------------------------------------------------------------------------------------------
# volfxd on the device: start, server.info, a 960x540 demo frame, and the same frame from
# PoCL's CPU device to compare

# serve DEVICE NAME: starts volfxd on DEVICE; sets 'port' (empty on failure).
serve() {
  local device=$1 name=$2 i
  port=
  mkdir -p "$work/data-$name"
  "$bin/volfxd" --device "$device" --listen 127.0.0.1:0 --data "$work/data-$name" --scene demo \
    >"$work/$name.out" 2>"$out/logs/volfxd-$name.log" &
  servers+=($!)
  for ((i = 0; i < 1200 && $(left) > 5; i++)); do
    port=$(sed -n 's/^volfxd listening on 127\.0\.0\.1:\([0-9]*\)$/\1/p' "$work/$name.out")
    [ -z "$port" ] || return 0
    kill -0 "${servers[-1]}" 2>/dev/null || break
    sleep 0.1
  done
  return 1
}

# stop_server: stops the last volfxd started, waiting for it.
stop_server() {
  local pid=${servers[-1]}
  kill -TERM "$pid" 2>/dev/null
  wait "$pid" 2>/dev/null
  unset 'servers[-1]'
}

# frame PORT FILE FORMAT: renders the demo frame, the median work time of 5 into 'frame_ms'.
frame() {
  local port=$1 file=$2 format=$3 i times=()
  for i in 1 2 3 4 5; do
    "$bin/volfx" --port "$port" render -o "$file" -W 960 -H 540 --format "$format" >"$work/render.txt" 2>&1 || return 1
    times+=("$(sed -n 's/.*"total":\([0-9.]*\).*/\1/p' "$work/render.txt")")
  done
  frame_ms=$(printf '%s\n' "${times[@]}" | sort -g | sed -n 3p | xargs printf '%.1f')
}

e2e=
if [ -n "$device_name" ] && [ -x "$bin/volfx" ]; then
  say "volfxd on the $mode device"
  t0=$SECONDS
  if serve $mode dev; then
    "$bin/volfx" --port "$port" info >"$out/logs/info.log" 2>&1
    if frame "$port" "$out/demo-$mode.png" png && frame "$port" "$work/dev.rgba" rgba8; then
      start_line=$(grep -m1 'ready in' "$out/logs/volfxd-dev.log" | sed 's/.*\] //')
      e2e="- volfxd: ${start_line:-started}; demo frame 960x540 in ${frame_ms} ms of work (median of 5): demo-$mode.png"
      steps+=("volfxd|ok|$((SECONDS - t0))|logs/volfxd-dev.log, logs/info.log")
    else
      steps+=("volfxd|FAILED (render)|$((SECONDS - t0))|logs/volfxd-dev.log")
      failed=1
    fi
    stop_server
  else
    steps+=("volfxd|FAILED (no listening line)|$((SECONDS - t0))|logs/volfxd-dev.log")
    missing+=("volfxd did not start on the $mode device")
    failed=1
  fi
  # The reference frame from PoCL's CPU device.
  if [ -f "$work/dev.rgba" ] && [ "$(left)" -gt 60 ]; then
    t0=$SECONDS
    if serve cpu ref && frame "$port" "$work/ref.rgba" rgba8; then
      stop_server
      if cmp -s "$work/dev.rgba" "$work/ref.rgba"; then
        e2e+=$'\n'"- the $mode frame equals PoCL's CPU frame byte for byte"
      elif command -v python3 >/dev/null 2>&1; then
        e2e+=$'\n'"- against PoCL's CPU frame: $(python3 - "$work/dev.rgba" "$work/ref.rgba" <<'EOF'
import sys
a, b = (open(p, "rb").read() for p in sys.argv[1:3])
if len(a) != len(b):
    print("sizes differ (%d and %d bytes)" % (len(a), len(b)))
    sys.exit()
d = [abs(x - y) for x, y in zip(a, b)]
px = [max(d[i:i + 4]) for i in range(0, len(d), 4)]
print("mean channel difference %.3f / 255, largest %d; %.2f %% of pixels differ by more than "
      "2 / 255" % (sum(d) / len(d), max(d), 100.0 * sum(1 for v in px if v > 2) / len(px)))
EOF
)"
      else
        e2e+=$'\n'"- the $mode frame differs from PoCL's CPU frame (no python3 to measure by how much)"
      fi
      steps+=("cpu-reference|ok|$((SECONDS - t0))|logs/volfxd-ref.log")
    else
      [ -z "$port" ] || stop_server
      steps+=("cpu-reference|not available|$((SECONDS - t0))|logs/volfxd-ref.log")
      missing+=("no frame from PoCL's CPU device to compare with (pocl-opencl-icd missing?)")
    fi
  fi
fi

# ---------------------------------------------------------------------------------------------
# The render benchmarks on the device, most telling first

if [ -n "$device_name" ]; then
  bench() { # bench NAME LIMIT ARGS...
    local name=$1 limit=$2
    shift 2
    if [ -x "$bin/$name" ]; then
      step "$name" "$limit" "$bin/$name" "$@"
    else
      skip "$name" "not built"
    fi
  }
  bench bench_render 60 --runs "$runs" --no-startup --device $mode
  bench bench_render_volume 90 --runs "$runs" --device $mode
  bench bench_render_fluid 90 --runs "$runs" --device $mode
  VOLFX_DEVICE=$mode bench bench_render_sph 90 $((runs < 11 ? 11 : runs))
  bench bench_render_waves 60 --runs "$runs" --device $mode
fi

# ---------------------------------------------------------------------------------------------
# The report

{
  echo "# volfx GPU check ($mode mode)"
  echo
  echo "$(date -u '+%Y-%m-%d %H:%M UTC'), commit $(git -C "$root" rev-parse --short HEAD 2>/dev/null || echo unknown), $((SECONDS - started)) s of a ${budget} s budget; \`tests/gpu/run.sh$([ "$mode" = cpu ] && echo ' --cpu')\`."
  echo
  echo "## Machine"
  echo
  cat "$machine"
  echo "- OpenCL device used: ${device_name:-none}${compile_ms:+ (every kernel compiled from a cold cache in $compile_ms ms)}"
  echo
  echo "## Steps"
  echo
  echo "| step | result | s | details |"
  echo "| --- | --- | ---: | --- |"
  for row in "${steps[@]}"; do
    IFS='|' read -r name status secs note <<<"$row"
    echo "| $name | $status | $secs | $note |"
  done
  echo
  if [ ${#missing[@]} -gt 0 ]; then
    echo "## Not done"
    echo
    for m in "${missing[@]}"; do echo "- $m"; done
    echo
  fi
  if [ ${#unit_rows[@]} -gt 0 ]; then
    echo "## Kernel unit tests on the device (VOLFX_DEVICE=$mode)"
    echo
    echo "| test | checks |"
    echo "| --- | --- |"
    for row in "${unit_rows[@]}"; do
      IFS='|' read -r name summary <<<"$row"
      echo "| $name | $summary |"
    done
    echo
    for t in "${units[@]}"; do
      [ -f "$out/logs/$t.log" ] && grep -q 'CHECK(' "$out/logs/$t.log" || continue
      echo "First failed checks of $t:"
      echo
      grep -m 5 'CHECK(' "$out/logs/$t.log" | cut -c1-300 | sed 's/^/    /'
      echo
    done
  fi
  if [ -n "$e2e" ]; then
    echo "## volfxd"
    echo
    echo "$e2e"
    echo
  fi
  shown=0
  for b in "${benches[@]}"; do
    [ -s "$out/logs/$b.log" ] || continue
    [ $shown -eq 1 ] || { echo "## Benchmarks"; echo; shown=1; }
    echo "### $b"
    echo
    cat "$out/logs/$b.log"
    echo
  done
} >"$report"

say "report: $report ($([ $failed -eq 0 ] && echo 'every step passed' || echo 'some steps failed or were skipped'))"
exit $failed
