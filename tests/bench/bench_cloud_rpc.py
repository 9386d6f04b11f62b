#!/usr/bin/env python3
"""
The cloud through the server (not run by ctest): sim.step on a scene with a growing cloud,
answered once the render worker has taken the automaton step, computed the density and blended
it in (SPEC 5.4), for 64³, 128³ and 256³ grids; then the same with a 512² render of the scene
after each step (the renderer's cloud pass, where it has one, draws the new density). Medians
of the round trips over a real socket, so they include the queueing and the answer.

    python3 tests/bench/bench_cloud_rpc.py --bin build/bin --steps 30
"""

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--sides", default="64,128,256")
    args = ap.parse_args()
    print("# sim.step round trip with a growing cloud (ms, median of %d); preset paper-003 with "
          "the grid replaced" % args.steps)
    print("%-6s %12s %18s" % ("grid", "sim.step", "sim.step+render"))
    with mock.Server(args.bin) as srv:
        c = srv.connect(timeout=600)
        for side in [int(x) for x in args.sides.split(",")]:
            name = "b%d" % side
            c.ok("scene.create", {"name": name, "preset": "paper-003"})
            voxel = 6.4 / side
            c.ok("scene.set", {"scene": name, "patch": {"cloud": {
                "grid": [side, side, side], "voxel": voxel, "metaball_radius": 0}}},
                timeout=600)
            # Grow for a while first, so the density pass has a cloud to sum.
            c.ok("sim.step", {"scene": name, "steps": side // 4}, timeout=600)
            times, both = [], []
            for _ in range(args.steps):
                t0 = time.monotonic()
                c.ok("sim.step", {"scene": name}, timeout=600)
                times.append((time.monotonic() - t0) * 1e3)
            for _ in range(args.steps):
                t0 = time.monotonic()
                c.ok("sim.step", {"scene": name}, timeout=600)
                c.ok("render", {"scene": name, "width": 512, "height": 512, "format": "rgba8"},
                     timeout=600)
                both.append((time.monotonic() - t0) * 1e3)
            print("%-6d %12.2f %18.2f" % (side, statistics.median(times),
                                           statistics.median(both)))
            c.ok("scene.delete", {"name": name})
    return 0


if __name__ == "__main__":
    sys.exit(main())
