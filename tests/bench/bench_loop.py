#!/usr/bin/env python3
"""
How long the server's loop thread is kept from other clients by one client's heavy request
(not run by ctest). SPEC §3: the event loop never blocks. Client A sends one request; client B,
meanwhile, sends server.info after server.info, one at a time, until A's answer starts to
arrive. The figures are B's longest round trip while A waited (the loop's longest stall, plus
B's own round trip) and A's time to the first byte of its answer. Requests:

  cloud 256³      scene.set enabling a 256³ Dobashi cloud grown 2 steps at seeding
  fluid 2^20      scene.set of a fluid.initial block of 2^20 particles among 40 objects
  cells base64    cloud.get_cells of 256³ cloud cells as base64 (22 MB of text)
  particles b64   fluid.get_particles of 2^20 positions as base64 (16 MB of text)
  cells           cloud.get_cells of the same cells as an attachment (16 MiB)

Each figure is the median of --runs runs.

    python3 tests/bench/bench_loop.py --bin build/bin
    python3 tests/bench/bench_loop.py --bin build/bin --runs 5
"""

import argparse
import os
import select
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402

OBJECTS = [{"shape": "box", "position": [-4 + 0.2 * i, 7, 4], "scale": [0.1, 0.1, 0.1]}
           for i in range(40)]


def block(count):
    return [{"origin": [-4, 0.01, -4], "spacing": 0.01, "nx": 512, "nz": 512, "count": count}]


def stall(a, b, method, params):
    """Sends one request on A; returns (B's longest round trip, A's time to first byte), ms."""
    t0 = time.monotonic()
    a.send(a.request(method, params))
    worst = 0.0
    while True:
        t = time.monotonic()
        b.ok("server.info")
        worst = max(worst, time.monotonic() - t)
        if select.select([a.sock], [], [], 0)[0]:
            break
    first = time.monotonic() - t0
    resp, _ = a.recv_response(timeout=600)
    if "result" not in resp:
        raise SystemExit("%s failed: %s" % (method, mock.short(resp)))
    return worst * 1e3, first * 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    cfg = mock.config_file({"limits": {"particles": 1 << 20}})
    with mock.Server(args.bin, "--config", cfg) as srv:
        a = srv.connect(timeout=600)
        b = srv.connect()
        rows = {}

        def run(name, method, params_of, before=None):
            got = []
            for i in range(args.runs):
                if before:
                    before(i)
                got.append(stall(a, b, method, params_of(i)))
            rows[name] = (statistics.median(g[0] for g in got),
                          statistics.median(g[1] for g in got))

        a.ok("scene.create", {"name": "c"})
        run("cloud 256³", "scene.set", lambda i: {"scene": "c", "patch": {"cloud": {
            "enabled": True, "grid": [256, 256, 256], "rules": "dobashi", "p_ext": 0.01,
            "seed": 100 + i, "init": {"steps": 2}}}})
        run("cells base64", "cloud.get_cells",
            lambda i: {"scene": "c", "field": "cld", "encoding": "base64"})
        run("cells", "cloud.get_cells", lambda i: {"scene": "c", "field": "cld"})
        a.ok("scene.create", {"name": "f"})
        a.ok("scene.set", {"scene": "f", "patch": {"objects": OBJECTS, "fluid": {
            "max_particles": 1 << 20, "bounds": {"min": [-5, 0, -5], "max": [5, 8, 5]}}}})
        run("fluid 2^20", "scene.set", lambda i: {"scene": "f", "path": "fluid.initial",
                                                   "value": block((1 << 20) - i)})
        run("particles b64", "fluid.get_particles", lambda i: {"scene": "f", "encoding": "base64"})

    print("| request | longest server.info round trip meanwhile, ms | time to its answer, ms |")
    print("| --- | ---: | ---: |")
    for name, (worst, first) in rows.items():
        print("| %s | %.1f | %.0f |" % (name, worst, first))
    print("\nMedians of %d runs; load average %.2f. Command: %s" % (
        args.runs, os.getloadavg()[0], " ".join(["python3"] + sys.argv)))


if __name__ == "__main__":
    main()
