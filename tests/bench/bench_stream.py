#!/usr/bin/env python3
"""
End-to-end frame delivery (not run by ctest): a subscribed client reading frames as fast as the
server pushes them, over a real socket. Frames per second delivered, the server's render time
per frame, and how many were dropped, medians of several runs.

    python3 tests/bench/bench_stream.py --bin build/bin --waves 10 --size 512
    python3 tests/bench/bench_stream.py --bin build/bin --waves 10 --size 512 --png-level 0
    python3 tests/bench/bench_stream.py --bin build/bin --preset demo --size 512

--waves N replaces the scene with the thesis' set-up (paper 000: eye (0,0,300), D = (1,0,0),
a = 60, b = 30) holding N waves spread across the view, objects off; --preset uses a preset as
it is. --png-level asks for that zlib level (the server's default, -1, is level 1 without
filtering; 0 stores the rows uncompressed). The median server time per frame is split into the
render (every pass but encoding) and the PNG encoding, which runs on its own thread.
The subscription asks for `repeat`, so the unchanged scene is rendered again at every tick
(a paused scene otherwise sends its first frame only).
"""

import argparse
import os
import statistics
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402
import streaming  # noqa: E402


def thesis_waves(n):
    waves = []
    for i in range(n):
        x = -90 + 180 * (i % 5) / 4.0
        y = 45 if i < 5 else -45
        waves.append({"center": [x - 40, y if n > 1 else 0, 0], "direction": [1, 0, 0],
                      "a": 60, "b": 30, "length": 80, "radius": 60, "softening": 1.5,
                      "clamp": 300, "color": [0.4, 0.8, 1.6]})
    return {"camera": {"eye": [0, 0, 300], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 45,
                       "near": 1, "far": 2000},
            "objects": [], "waves": waves}


def one_run(srv, args):
    c = srv.connect(timeout=60, rcvbuf=8 << 20)
    params = {"width": args.size, "height": args.size, "format": "png", "fps": 240,
              "png_level": args.png_level, "repeat": True}
    if args.waves:
        params["layers"] = ["waves"]
    sub, _ = c.ok("frames.subscribe", params)
    frames, dt = streaming.receive_frames(c, args.seconds, timeout=60)
    work = [p.get("work_ms", 0) for p, _ in frames]
    enc = [(p.get("passes") or {}).get("encode", 0) for p, _ in frames]
    nbytes = [len(att or b"") for _, att in frames]
    c.send(c.request("frames.unsubscribe", {"id": sub["id"]}))
    c.close()
    return (len(frames) / dt, statistics.median(work), frames[-1][0].get("dropped", 0),
            statistics.median(enc), statistics.median(nbytes))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--waves", type=int, default=0)
    ap.add_argument("--preset", default="demo")
    ap.add_argument("--seconds", type=float, default=4)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--png-level", type=int, default=-1)
    args = ap.parse_args()
    suite = mock.Suite("bench_stream")  # The harness records into a suite; none is checked.
    suite.args = args
    with mock.Server(os.path.abspath(args.bin), "--scene", args.preset,
                     "--log-level", "warn") as srv:
        if args.waves:
            c = srv.connect()
            c.ok("scene.set", {"patch": thesis_waves(args.waves)})
            c.close()
        runs = [one_run(srv, args) for _ in range(args.runs)]
    fps = statistics.median(r[0] for r in runs)
    work = statistics.median(r[1] for r in runs)
    enc = statistics.median(r[3] for r in runs)
    size = statistics.median(r[4] for r in runs)
    what = "%d waves" % args.waves if args.waves else "preset %s" % args.preset
    print("`%s`" % " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]))
    print()
    print("| frames | delivered (median of %d runs) | server work per frame: all (encode) | "
          "PNG bytes | dropped per run |" % args.runs)
    print("| --- | ---: | ---: | ---: | ---: |")
    print("| %s, %d² PNG level %d, subscribed at 240 fps | %.1f fps | %.2f ms (%.2f) | %.0f | %s |" %
          (what, args.size, args.png_level, fps, work, enc, size,
           ", ".join(str(r[2]) for r in runs)))


if __name__ == "__main__":
    main()
