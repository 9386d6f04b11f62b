#!/usr/bin/env python3
"""
The frame formats end to end (not run by ctest), over a real socket, medians of several runs:

  encode   the demo frame at 1280x720 rendered --runs times in png (the fast default), jpeg
           (quality 85), webp (quality 80) and lossless webp: the encoder's time (work_ms.encode,
           on the render worker's encoder) and the bytes. Targets: jpeg q85 in <= 3 ms with
           <= 1/5 of png's bytes.
  stream   a 640x360 subscription at 30 fps of the demo scene playing, --seconds long, in each
           of png, jpeg and webp: frames received per second and the bit rate. Target: jpeg
           under 4 Mbit/s.

    python3 tests/bench/bench_formats.py --bin build/bin encode --runs 9
    python3 tests/bench/bench_formats.py --bin build/bin stream --seconds 6 --runs 3
"""

import argparse
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402

CASES = [("png", {"format": "png"}), ("jpeg q85", {"format": "jpeg", "quality": 85}),
         ("webp q80", {"format": "webp", "quality": 80}),
         ("webp lossless", {"format": "webp", "quality": 100})]


def encode(srv, runs):
    c = srv.connect(timeout=120)
    print("| format (1280x720 demo) | encode ms (median) | bytes (median) |")
    print("| --- | ---: | ---: |")
    rows = {}
    for name, p in CASES:
        ms, sizes = [], []
        for _ in range(runs):
            r, data = c.ok("render", dict(p, width=1280, height=720))
            ms.append(r["work_ms"]["encode"])
            sizes.append(len(data))
        rows[name] = (statistics.median(ms), statistics.median(sizes))
        print("| %s | %.2f | %d |" % (name, rows[name][0], rows[name][1]))
    jpeg, png = rows["jpeg q85"], rows["png"]
    print("jpeg q85: %.2f ms (target <= 3), %.1f%% of png's bytes (target <= 20%%)"
          % (jpeg[0], 100.0 * jpeg[1] / png[1]))
    c.close()


def stream(srv, seconds, runs):
    c = srv.connect(timeout=120)
    c.ok("sim.play", {"rate": 60})
    print("| format (640x360, 30 fps, demo playing) | frames/s (median) | Mbit/s (median) |")
    print("| --- | ---: | ---: |")
    for name, p in CASES[:3]:
        fps, mbit = [], []
        for _ in range(runs):
            sid = c.ok("frames.subscribe", dict(p, width=640, height=360, fps=30))[0]["id"]
            # The first second warms up; then count.
            end_warm = time.monotonic() + 1.0
            while time.monotonic() < end_warm:
                c.recv_notification(timeout=30)
            n, nbytes, t0 = 0, 0, time.monotonic()
            while time.monotonic() - t0 < seconds:
                msg, att = c.recv_notification(timeout=30)
                if msg.get("method") == "frames":
                    n += 1
                    nbytes += len(att or b"")
            dt = time.monotonic() - t0
            c.ok("frames.unsubscribe", {"id": sid})
            fps.append(n / dt)
            mbit.append(nbytes * 8 / dt / 1e6)
        print("| %s | %.1f | %.2f |" % (name, statistics.median(fps), statistics.median(mbit)))
    c.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", choices=["encode", "stream"])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=5)
    a = ap.parse_args()
    with mock.Server(os.path.abspath(a.bin), "--scene", "demo") as srv:
        if a.case == "encode":
            encode(srv, a.runs)
        else:
            stream(srv, a.seconds, a.runs)


if __name__ == "__main__":
    main()
