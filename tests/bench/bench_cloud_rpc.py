#!/usr/bin/env python3
"""
The automaton cloud through the server, end to end (not run by ctest): the paper-003 preset
(Dobashi's rules, a wind-blown cloud) with its grid replaced by 64³, 128³ or 256³ (the voxel
and the metaball radius scaled so the cloud fills the same box), grown first for 40 steps per
64 cells of side so every grid shows the same grown cloud. Then, over a real socket:

  sim.step   round trips of sim.step 1: the render worker takes the automaton step, computes
             the metaball density and blends it in (SPEC 5.4); answered once the scene holds it.
  render     512² PNG renders of that cloud, read by the client: the volumes pass (work_ms)
             and the whole round trip.
  lockstep   per frame, sim.step 1 then a 512² PNG render read by the client: step + density
             + render + deliver, the figure issue 5's targets are about.
  stream     sim.play at 60 steps/s with frames.subscribe at 240 fps (512² PNG): frames
             delivered per second, and automaton steps taken per second, while the server
             simulates by itself.

Each figure is the median of --runs runs (a fresh scene each), each the median of its frames.
Beside the wall clock it reports the server process's CPU time (all threads) per frame, from
/proc, which the other work on a shared machine disturbs less; and the load average.

    python3 tests/bench/bench_cloud_rpc.py --bin build/bin
    python3 tests/bench/bench_cloud_rpc.py --bin build/bin --sides 64,128 --runs 5

Paper 003 (Kuromiya et al.) animates its 64³ cloud at 33.33 FPS on a VolumePro 500 board.
"""

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402
import streaming  # noqa: E402

SIZE = 512
TICK = os.sysconf("SC_CLK_TCK")
_names = iter(range(1 << 30))


def cpu_s(pid):
    """User + system CPU seconds of process 'pid', all threads."""
    with open("/proc/%d/stat" % pid) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def fresh(c, side):
    name = "cl%d" % next(_names)
    c.ok("scene.create", {"name": name, "preset": "paper-003"})
    c.ok("scene.set", {"scene": name, "patch": {"cloud": {
        "grid": [side, side, side], "voxel": 6.4 / side, "metaball_radius": 0}}}, timeout=600)
    c.ok("sim.step", {"scene": name, "steps": 40 * side // 64}, timeout=600)
    return name


def timed(pid, n, fn):
    """Runs fn() n times; returns (median wall ms, CPU ms per call, results)."""
    wall, out = [], []
    c0 = cpu_s(pid)
    for _ in range(n):
        t0 = time.perf_counter()
        out.append(fn())
        wall.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(wall), 1e3 * (cpu_s(pid) - c0) / n, out


def png(c, s):
    r, att = c.ok("render", {"scene": s, "width": SIZE, "height": SIZE, "format": "png"},
                  timeout=600)
    if att is None or att[:4] != b"\x89PNG":
        raise SystemExit("render did not deliver a PNG")
    return r.get("work_ms", {})


def one_run(srv, side, frames, seconds):
    c = srv.connect(timeout=600, rcvbuf=8 << 20)
    s = fresh(c, side)
    pid = srv.pid
    res = {}
    res["step"], res["step_cpu"], _ = timed(
        pid, frames, lambda: c.ok("sim.step", {"scene": s}, timeout=600))
    png(c, s)  # The first render of a new grid size builds the light grid's buffers.
    res["render"], res["render_cpu"], work = timed(pid, frames, lambda: png(c, s))
    res["volumes"] = statistics.median(w.get("volumes", 0) for w in work)

    def lock():
        c.ok("sim.step", {"scene": s}, timeout=600)
        return png(c, s)

    res["lock"], res["lock_cpu"], _ = timed(pid, frames, lock)
    # The stream: the server steps and renders by itself.
    sub, _ = c.ok("frames.subscribe", {"scene": s, "width": SIZE, "height": SIZE,
                                        "format": "png", "fps": 240, "repeat": True})
    f0 = c.ok("scene.get", {"scene": s, "path": "sim.frame"})[0]
    c.ok("sim.play", {"scene": s, "rate": 60})
    start = {}

    def first(params):
        start["cpu"], start["frame"] = cpu_s(pid), params.get("frame", f0)

    frames, dt = streaming.receive_frames(c, seconds, on_first=first)
    cpu = cpu_s(pid) - start["cpu"]
    c.send(c.request("sim.pause", {"scene": s}))
    c.send(c.request("frames.unsubscribe", {"id": sub["id"]}))
    c.close()
    res["stream_fps"] = len(frames) / dt
    res["stream_cpu"] = 1e3 * cpu / max(len(frames), 1)
    last = frames[-1][0] if frames else {}
    res["steps_per_s"] = (last.get("frame", start["frame"]) - start["frame"]) / dt
    c = srv.connect(timeout=600)
    c.ok("scene.delete", {"name": s})
    c.close()
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--sides", default="64,128,256")
    ap.add_argument("--frames", type=int, default=30, help="calls timed per measure and run")
    ap.add_argument("--seconds", type=float, default=4, help="length of each stream")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    suite = mock.Suite("bench_cloud_rpc")  # The harness records into a suite; none is checked.
    suite.args = args
    load0 = os.getloadavg()
    rows = []
    with mock.Server(os.path.abspath(args.bin), "--log-level", "warn") as srv:
        for side in [int(x) for x in args.sides.split(",")]:
            runs = [one_run(srv, side, args.frames, args.seconds) for _ in range(args.runs)]
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            rows.append((side, med))
            print("  %d³: lockstep %.1f ms (%.1f fps), %.1f CPU ms; stream %.1f fps" %
                  (side, med["lock"], 1e3 / med["lock"], med["lock_cpu"], med["stream_fps"]),
                  file=sys.stderr)
    load1 = os.getloadavg()
    print("`%s`" % " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]))
    print()
    print("| grid | sim.step ms (CPU) | render %d² ms (CPU) | volumes pass ms | step + render "
          "ms (CPU) | lockstep FPS | stream FPS | stream steps/s | stream CPU ms/frame |"
          % SIZE)
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for side, m in rows:
        print("| %d³ | %.1f (%.1f) | %.1f (%.1f) | %.1f | %.1f (%.1f) | %.1f | %.1f | %.0f | %.1f |"
              % (side, m["step"], m["step_cpu"], m["render"], m["render_cpu"], m["volumes"],
                 m["lock"], m["lock_cpu"], 1e3 / m["lock"], m["stream_fps"], m["steps_per_s"],
                 m["stream_cpu"]))
    print()
    print("Medians of %d runs (%d calls each; streams of %.0f s). Load average %.2f at the "
          "start, %.2f at the end (1 min)." % (args.runs, args.frames, args.seconds, load0[0],
                                               load1[0]))
    print("Paper 003: 64³ at 33.33 FPS on a VolumePro 500. Targets: 64³ ≥ 60 FPS, 128³ ≥ 30 FPS.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
