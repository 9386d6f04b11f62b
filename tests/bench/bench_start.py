#!/usr/bin/env python3
"""
Daemon start to first frame (not run by ctest): the time from exec of volfxd to the first
rendered 512x512 PNG received by a client, with an empty PoCL kernel cache (cold: a fresh
POCL_CACHE_DIR per run) and with the cache a previous run filled (warm: the same directory).
Prints the medians of each as a markdown table with the command line, split into exec to the
`volfxd listening` line and that line to the frame received.

    python3 tests/bench/bench_start.py --bin build/bin
"""

import argparse
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402

TARGET_COLD_S = 1.0
TARGET_WARM_S = 0.1


def one_run(exe, cache_dir, size, extra):
    """Returns (exec->listening s, exec->frame s)."""
    data = tempfile.mkdtemp(prefix="volfx-bench-data-")
    env = dict(os.environ, POCL_CACHE_DIR=cache_dir)
    cmd = [exe, "--listen", "127.0.0.1:0", "--data", data] + extra
    log = tempfile.TemporaryFile()
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log,
                         env=env)
    try:
        host = port = None
        deadline = t0 + 120
        while True:
            line = p.stdout.readline()
            if not line:
                log.seek(0)
                raise SystemExit("volfxd exited before listening (status %s):\n%s" %
                                 (p.wait(), log.read().decode("utf-8", "replace")[-3000:]))
            m = mock.LISTEN_RE.search(line.decode("utf-8", "replace").rstrip("\n"))
            if m:
                host, port = m.group(1).strip("[]"), int(m.group(2))
                break
            if time.perf_counter() > deadline:
                raise SystemExit("no listening line within 120 s")
        t_listen = time.perf_counter() - t0
        c = mock.Conn(host, port, timeout=120)
        r, png = c.ok("render", {"width": size, "height": size, "format": "png"}, timeout=120)
        t_frame = time.perf_counter() - t0
        if mock.png_info(png or b"") != (size, size, 8, 6):
            raise SystemExit("the first frame is not a %dx%d PNG: %s" % (size, size, r))
        c.close()
        return t_listen, t_frame
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        shutil.rmtree(data, ignore_errors=True)


def fmt(xs):
    return "%.3f s" % statistics.median(xs), "%.3f-%.3f" % (min(xs), max(xs))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--scene", help="volfxd --scene for the main scene (default: its default)")
    a = ap.parse_args()
    exe = os.path.join(os.path.abspath(a.bin), "volfxd")
    extra = ["--scene", a.scene] if a.scene else []
    cold, warm = [], []
    warm_dir = None
    try:
        for i in range(a.runs):
            d = tempfile.mkdtemp(prefix="volfx-pocl-cold-")
            r = one_run(exe, d, a.size, extra)
            cold.append(r)
            print("  cold run %d: listening %.3f s, first frame %.3f s" % (i + 1, r[0], r[1]),
                  flush=True)
            if warm_dir is None:
                warm_dir = d
            else:
                shutil.rmtree(d, ignore_errors=True)
        for i in range(a.runs):
            r = one_run(exe, warm_dir, a.size, extra)
            warm.append(r)
            print("  warm run %d: listening %.3f s, first frame %.3f s" % (i + 1, r[0], r[1]),
                  flush=True)
    finally:
        if warm_dir:
            shutil.rmtree(warm_dir, ignore_errors=True)
    print()
    print("`%s`" % " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]))
    print()
    print("%d CPUs; medians of %d runs; %dx%d PNG from the main scene" %
          (os.cpu_count() or 0, a.runs, a.size, a.size))
    print()
    print("| cache | exec to listening | exec to first frame | range | target | met |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, runs, target in (("cold (empty POCL_CACHE_DIR)", cold, TARGET_COLD_S),
                               ("warm (same POCL_CACHE_DIR)", warm, TARGET_WARM_S)):
        lis = statistics.median(r[0] for r in runs)
        med, rng = fmt([r[1] for r in runs])
        print("| %s | %.3f s | %s | %s | <= %.3f s | %s |" %
              (name, lis, med, rng, target,
               "yes" if statistics.median(r[1] for r in runs) <= target else "no"))


if __name__ == "__main__":
    main()
