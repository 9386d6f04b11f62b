#!/usr/bin/env bash
# volfx quick start.
#   ./run.sh          install missing packages, build, render out/demo.png, run volfxd on
#                     127.0.0.1:7878 with the demo scene, and its browser viewer on
#                     http://127.0.0.1:8080/, until Ctrl-C
#   ./run.sh test     install, build, run the whole test suite (ctest)
#   ./run.sh asan     the same suite in a separate AddressSanitizer + UBSan build
set -euo pipefail
cd "$(dirname "$0")"

# slurm-wlm and munge: the render-farm test brings up a private one-node Slurm cluster.
# libsystemd-dev: volfxd's readiness notification; systemd: systemd-analyze and systemd-sysusers,
# which check deploy/volfxd.service and deploy/volfx.sysusers.conf (no systemd needs to run).
# libwebsockets-dev and libwebsockets-evlib-uv: the --http viewer on volfxd's libuv loop;
# chromium, chromium-driver and python3-selenium: the viewer's test in a headless browser;
# python3-pytest: the test of volfx.testing's pytest plugin; libturbojpeg0-dev and libwebp-dev:
# the jpeg and webp frame formats.
packages=(build-essential cmake pkg-config libuv1-dev libcjson-dev libpng-dev zlib1g-dev
          ocl-icd-opencl-dev opencl-headers pocl-opencl-icd python3 slurm-wlm munge
          libsystemd-dev systemd libwebsockets-dev libwebsockets-evlib-uv chromium
          chromium-driver python3-selenium python3-pytest libturbojpeg0-dev libwebp-dev)

install_missing() {
  local missing=()
  for p in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  [ ${#missing[@]} -eq 0 ] && return 0
  echo "run.sh: installing ${missing[*]}"
  local sudo=()
  [ "$(id -u)" -eq 0 ] || sudo=(sudo)
  "${sudo[@]}" apt-get update -q
  DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}"
}

build() { # build DIR [cmake args...]
  local dir=$1; shift
  cmake -S . -B "$dir" -DCMAKE_BUILD_TYPE=RelWithDebInfo "$@" >/dev/null
  cmake --build "$dir" -j "$(nproc)"
}

run_tests() { # run_tests DIR [ctest args...]
  local dir=$1; shift
  (cd "$dir" && ctest --output-on-failure --timeout 900 -j 1 "$@")
}

mode=${1:-run}
install_missing
case "$mode" in
  test)
    build build
    run_tests build
    ;;
  asan)
    build build-asan -DVOLFX_SANITIZE=ON
    # A small quarantine, so that freed frames do not read as growth in the memory-bound tests.
    export ASAN_OPTIONS=detect_leaks=1:abort_on_error=0:detect_odr_violation=0:quarantine_size_mb=16
    export UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
    export LSAN_OPTIONS=suppressions=$PWD/tests/lsan.supp:print_suppressions=0
    # LeakSanitizer stops the world at exit with a ptrace tracer, which now and then crashes
    # ("Tracer caught signal 11") while PoCL's worker threads are still alive, after every
    # check passed. A test that fails is run once more; a real leak or error fails both times.
    run_tests build-asan --repeat until-pass:2
    ;;
  run)
    build build
    mkdir -p out data
    log=$(mktemp)
    build/bin/volfxd --listen 127.0.0.1:7878 --http 127.0.0.1:8080 --scene demo --data data >"$log" &
    pid=$!
    trap 'kill -INT $pid 2>/dev/null; wait $pid; rm -f "$log"' INT TERM
    for _ in $(seq 1 300); do
      grep -q "listening" "$log" && break
      kill -0 $pid 2>/dev/null || { echo "run.sh: volfxd failed to start"; exit 1; }
      sleep 0.05
    done
    cat "$log"
    build/bin/volfx render -o out/demo.png -W 960 -H 540
    echo "run.sh: wrote out/demo.png; volfxd is serving on 127.0.0.1:7878 and the viewer on" \
         "http://127.0.0.1:8080/ (Ctrl-C stops it)"
    wait $pid
    ;;
  *)
    echo "usage: ./run.sh [test|asan]" >&2
    exit 2
    ;;
esac
