#!/usr/bin/env python3
"""
The particle fluid end to end (not run by ctest): simulate + render + deliver over a real
socket, for the water flows of the paper's Figs. 10-11 (presets paper-001-flow, 4096
particles, and paper-001-flow-16384). Two ways a client drives it, each from a fresh copy of
the preset, medians of several runs:

  lockstep   per frame, sim.step 1 (one 1/60 s step of the SPH fluid on the render worker)
             then render PNG and read it: the frame rate a client stepping the flow frame by
             frame sees, with the share of each part.
  stream     sim.play at 60 steps/s with a frames.subscribe at 240 fps: frames delivered per
             second while the server simulates by itself (fluid steps and renders share the
             one render worker; a play tick that finds a fluid step still running leaves the
             fluid behind the clock rather than queueing another).

    python3 tests/bench/bench_fluid_e2e.py --bin build/bin
    python3 tests/bench/bench_fluid_e2e.py --bin build/bin --sizes 128,256 --counts 4096

The paper gives the frame rates of its water flow images (GeForce 8800 GTX): Fig. 10, 4096
particles, 19 fps at 512²; Fig. 11, 16384 particles, 18 fps at 128² and 10 fps at 512².
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

PRESETS = {4096: "paper-001-flow", 16384: "paper-001-flow-16384"}
# (particles, size): the frame rate printed on the paper's Figs. 10-11.
PAPER = {(4096, 512): 19, (16384, 128): 18, (16384, 512): 10}
_names = iter(range(1 << 30))


def fresh(c, preset):
    name = "e2e%d" % next(_names)
    c.ok("scene.create", {"name": name, "preset": preset})
    return name


def lockstep(srv, preset, size, seconds):
    c = srv.connect(timeout=300, rcvbuf=8 << 20)
    s = fresh(c, preset)
    step_ms, frame_ms, work, fluid = [], [], [], []
    t_end = time.perf_counter() + seconds
    frames = 0
    t_first = None
    while time.perf_counter() < t_end or frames < 3:
        t0 = time.perf_counter()
        c.ok("sim.step", {"scene": s, "steps": 1}, timeout=300)
        t1 = time.perf_counter()
        r, att = c.ok("render", {"scene": s, "width": size, "height": size, "format": "png"},
                      timeout=300)
        t2 = time.perf_counter()
        if att is None or att[:4] != b"\x89PNG":
            raise SystemExit("render did not deliver a PNG")
        if t_first is None:  # The first frame warms the simulation up; not counted.
            t_first = t2
            continue
        frames += 1
        step_ms.append(1e3 * (t1 - t0))
        frame_ms.append(1e3 * (t2 - t1))
        wm = r.get("work_ms", {})
        work.append(wm.get("total", 0))
        fluid.append(wm.get("fluid", 0))
    fps = frames / (time.perf_counter() - t_first)
    c.ok("scene.delete", {"name": s})
    c.close()
    return {"fps": fps, "step": statistics.median(step_ms), "frame": statistics.median(frame_ms),
            "work": statistics.median(work), "fluid": statistics.median(fluid)}


def stream(srv, preset, size, seconds):
    c = srv.connect(timeout=300, rcvbuf=8 << 20)
    s = fresh(c, preset)
    sub, _ = c.ok("frames.subscribe", {"scene": s, "width": size, "height": size,
                                        "format": "png", "fps": 240, "repeat": True})
    c.ok("sim.play", {"scene": s, "rate": 60})
    frames, dt = streaming.receive_frames(c, seconds, timeout=300)
    c.send(c.request("sim.pause", {"scene": s}))
    c.send(c.request("frames.unsubscribe", {"id": sub["id"]}))
    c.close()
    c = srv.connect(timeout=300)
    c.ok("scene.delete", {"name": s})
    c.close()
    work = [p.get("work_ms", 0) for p, _ in frames]
    return {"fps": len(frames) / dt, "work": statistics.median(work) if work else 0,
            "dropped": frames[-1][0].get("dropped", 0) if frames else 0}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--sizes", default="128,256,512")
    ap.add_argument("--counts", default="4096,16384")
    ap.add_argument("--seconds", type=float, default=4)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    sizes = [int(x) for x in args.sizes.split(",")]
    counts = [int(x) for x in args.counts.split(",")]
    suite = mock.Suite("bench_fluid_e2e")  # The harness records into a suite; none is checked.
    suite.args = args
    rows = []
    with mock.Server(os.path.abspath(args.bin), "--log-level", "warn") as srv:
        for n in counts:
            for size in sizes:
                ls = [lockstep(srv, PRESETS[n], size, args.seconds) for _ in range(args.runs)]
                st = [stream(srv, PRESETS[n], size, args.seconds) for _ in range(args.runs)]
                med = {k: statistics.median(r[k] for r in ls) for k in ls[0]}
                rows.append((n, size, med, statistics.median(r["fps"] for r in st),
                             statistics.median(r["work"] for r in st)))
                print("  %d particles %d²: lockstep %.1f fps, stream %.1f fps" %
                      (n, size, med["fps"], rows[-1][3]), file=sys.stderr)
    print("`%s`" % " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]))
    print()
    print("| particles | size | lockstep FPS | sim.step ms | render+deliver ms | fluid pass ms "
          "| stream FPS | paper FPS |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for n, size, m, sfps, swork in rows:
        paper = PAPER.get((n, size))
        print("| %d | %d² | %.1f | %.1f | %.1f | %.1f | %.1f | %s |" %
              (n, size, m["fps"], m["step"], m["frame"], m["fluid"], sfps,
               "%d" % paper if paper else "–"))
    print()
    print("Medians of %d runs of %.0f s each, from a fresh copy of the preset (the flow starts "
          "at rest; the fluid spreads as it runs)." % (args.runs, args.seconds))


if __name__ == "__main__":
    main()
