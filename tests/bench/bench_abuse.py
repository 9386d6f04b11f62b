#!/usr/bin/env python3
"""
What hostile or careless clients cost volfxd: each case runs against a fresh server and
reports the server's peak resident memory above its start, and the latency of an innocent
authenticated client's scene.get (median and worst of the samples taken during the case).

    python3 tests/bench/bench_abuse.py --bin build/bin [--cases 1,2,3,4,9]

Cases (sizes scaled down from the ones first reported, so that a run takes a few minutes):
  1  token server: 10 sockets each send a batch of 400,000 1s in one line and never read
  2  one batch line of 6 renders at 2048² rgbaf32, never read
  3  16 subscriptions at 1024² rgbaf32 on one connection that never reads (12 s)
  4  12 connections, each with one unread 1920² rgbaf32 frame (59 MB, under the connection's
     output limit), sending blank lines (20 s)
  9  a reader taking a 2048² rgbaf32 frame (64 MiB, over the output limit) at 5 MB/s: whole,
     or cut off
"""

import argparse
import json
import os
import socket
import statistics
import sys
import threading
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "integration"))
import mock  # noqa: E402

MB = 1 << 20


class Watch:
    """Samples the server's RSS and an innocent client's scene.get latency in the background."""

    def __init__(self, srv, token=None):
        self.srv = srv
        self.c = srv.connect(timeout=60)
        if token:
            self.c.ok("auth", {"token": token})
        self.rss0 = srv.rss()
        self.peak = 0
        self.lat = []
        self.stop = False
        self.t = threading.Thread(target=self.run, daemon=True)
        self.t.start()

    def run(self):
        while not self.stop:
            r = self.srv.rss()
            if r:
                self.peak = max(self.peak, r - self.rss0)
            t0 = time.monotonic()
            try:
                self.c.ok("scene.get", {"path": "camera.fov_y"}, timeout=60)
                self.lat.append(time.monotonic() - t0)
            except Exception:
                self.lat.append(float("inf"))
            time.sleep(0.1)

    def done(self):
        self.stop = True
        self.t.join()
        lat = sorted(self.lat) or [float("nan")]
        return "peak RSS +%d MB, scene.get median %.1f ms, worst %.1f ms" % (
            self.peak // MB, 1000 * statistics.median(lat), 1000 * lat[-1])


def case1(binp):
    with mock.Server(binp, "--token", "tok") as srv:
        w = Watch(srv, "tok")
        socks = []
        line = b"[" + b",".join([b"1"] * 400000) + b"]\n"
        for _ in range(10):
            s = socket.create_connection((srv.host, srv.port))
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(line)
            socks.append(s)
        time.sleep(6)
        out = w.done()
        for s in socks:
            s.close()
        return out


def case2(binp):
    with mock.Server(binp) as srv:
        w = Watch(srv)
        c = srv.connect(timeout=120, rcvbuf=4096)
        c.send([c.request("render", {"width": 2048, "height": 2048, "format": "rgbaf32"}, id=i)
                for i in range(6)])
        time.sleep(10)
        out = w.done()
        c.close()
        return out


def case3(binp):
    with mock.Server(binp) as srv:
        w = Watch(srv)
        c = srv.connect(timeout=120, rcvbuf=4096)
        for i in range(16):
            c.send(c.request("frames.subscribe", {"width": 1024, "height": 1024,
                                                  "format": "rgbaf32", "fps": 30}, id=i))
        time.sleep(12)
        out = w.done()
        c.close()
        return out


def case4(binp):
    with mock.Server(binp) as srv:
        w = Watch(srv)
        hogs = []
        for _ in range(12):
            h = srv.connect(timeout=120, rcvbuf=4096)
            h.send(h.request("render", {"width": 1920, "height": 1920, "format": "rgbaf32"}))
            hogs.append(h)
        closed = 0
        t0 = time.monotonic()
        while time.monotonic() - t0 < 20:
            for h in hogs:
                try:
                    h.sock.sendall(b"\n")
                except OSError:
                    pass
            time.sleep(1)
        for h in hogs:
            try:
                h.sock.sendall(b"\n")
                h.sock.settimeout(0.01)
                h.sock.recv(1)
            except (OSError, socket.timeout):
                pass
        closed = sum(1 for h in hogs if h.sock.fileno() < 0)
        out = w.done()
        st = srv.connect().ok("stats", {})[0]
        for h in hogs:
            h.close()
        return out + ", %d connections open after 20 s" % (st.get("connections", 0) - 1)


def case9(binp):
    want = 2048 * 2048 * 16
    with mock.Server(binp) as srv:
        c = srv.connect(timeout=60, rcvbuf=65536)
        c.send(c.request("render", {"width": 2048, "height": 2048, "format": "rgbaf32"}))
        time.sleep(2)
        got, t0 = 0, time.monotonic()
        while got < want:
            try:
                chunk = c.sock.recv(65536)
            except OSError:
                break
            if not chunk:
                break
            got += len(chunk)
            time.sleep(len(chunk) / (5.0 * MB))
        return "%s: %.1f of %.1f MB in %.1f s" % (
            "whole" if got >= want else "cut off", got / MB, want / MB, time.monotonic() - t0)


CASES = {"1": case1, "2": case2, "3": case3, "4": case4, "9": case9}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--cases", default=",".join(CASES))
    a = ap.parse_args()
    binp = os.path.abspath(a.bin)
    for k in a.cases.split(","):
        print("case %s: %s" % (k, CASES[k](binp)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
