#!/usr/bin/env python3
"""
One sim.step of 100 steps of the paper-003 cloud at 64³ and 128³ through a real volfxd: the
call's time, median of 5 fresh scenes each.

    python3 tests/bench/bench_cloud_multistep.py build/bin
"""
import os
import statistics
import sys
import time
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "integration"))
import mock  # noqa: E402

binp = sys.argv[1] if len(sys.argv) > 1 else os.path.join("build", "bin")
with mock.Server(binp) as srv:
    c = srv.connect(timeout=300)
    for preset, grid in (("paper-003", [64, 64, 64]), ("paper-003", [128, 128, 128])):
        ts = []
        for r in range(5):
            name = "x%d%d" % (grid[0], r)
            c.ok("scene.create", {"name": name, "preset": preset})
            c.ok("scene.set", {"scene": name, "patch": {"cloud": {"grid": grid}}}, timeout=300)
            t0 = time.monotonic()
            c.ok("sim.step", {"scene": name, "steps": 100}, timeout=300)
            ts.append(time.monotonic() - t0)
            c.ok("scene.delete", {"name": name})
        print(preset, grid[0], "sim.step 100: median %.0f ms" % (1000 * statistics.median(ts)), ["%.0f" % (1000*t) for t in ts])
