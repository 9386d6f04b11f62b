#!/usr/bin/env python3
"""
What one client may take from the others, against a real volfxd: before authentication a
connection gets small answers only (a batch is refused whole), wrong tokens are answered late
and a few close the connection, connections waiting to authenticate are capped and timed out;
a batch's renders take the same share of the render queue as pipelined lines; the server-wide
output budget refuses frames rather than growing and lets clients that wait for nothing go on;
subscribers that never read are bounded and closed; a slow but steady reader is not cut off;
--unix never replaces a file or a live server's socket.

    python3 tests/integration/test_budget.py --bin build/bin
"""

import json
import os
import socket
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_LIMIT, E_UNAUTHORIZED, Server  # noqa: E402

suite = mock.Suite("test_budget", timeout_s=420)
T = suite.test
MB = 1 << 20


def rpc(method, params=None, id=1):
    msg = {"jsonrpc": "2.0", "id": id, "method": method}
    if params is not None:
        msg["params"] = params
    return (json.dumps(msg) + "\n").encode()


@T
def before_auth(s):
    cfg = mock.config_file({"limits": {"auth_timeout_s": 2, "unauthenticated": 4}})
    with Server(s.bin, "--token", "tok", "--config", cfg) as srv:
        good = srv.connect()
        good.ok("auth", {"token": "tok"})
        rss0 = srv.rss()
        # A 1 MB line holding a batch of 1s gets one small error, not 500,000 answers.
        big = srv.connect(timeout=30)
        big.send_raw(b"[" + b",".join([b"1"] * 400000) + b"]\n")
        line = big.read_line(timeout=30)
        s.check(len(line) < 512, "a batch before auth gets one small answer", "%d bytes" % len(line))
        err = json.loads(line)
        s.eq((err.get("error") or {}).get("code"), E_UNAUTHORIZED, "and it is -32001")
        rss1 = srv.rss()
        s.check(rss1 - rss0 < 64 * MB, "the batch did not grow the server",
                "%d MB more" % ((rss1 - rss0) // MB))
        # Wrong tokens: each answered late, and the third closes the connection.
        w = srv.connect()
        t0 = time.monotonic()
        for i in range(3):
            e = w.err("auth", {"token": "nope%d" % i})
            s.eq(e.get("code"), E_UNAUTHORIZED, "wrong token %d is -32001" % (i + 1))
        took = time.monotonic() - t0
        s.check(took >= 0.25, "wrong tokens are answered after a delay", "%.3f s for 3" % took)
        s.check(w.expect_eof(timeout=3), "the third wrong token closes the connection")
        # The good connection is served throughout.
        s.eq(good.ok("scene.get", {"path": "camera.fov_y"})[0] is not None, True,
             "an authenticated client is served")
        # At most 4 connections wait to authenticate; the fifth is refused at once.
        waiting = [srv.connect() for _ in range(4)]
        time.sleep(0.2)
        fifth = srv.connect()
        line = fifth.read_line(timeout=5)
        err = json.loads(line).get("error") or {}
        s.eq(err.get("code"), E_LIMIT, "a fifth unauthenticated connection is refused")
        s.eq((err.get("data") or {}).get("path"), "unauthenticated", "naming the limit")
        s.check(fifth.expect_eof(timeout=3), "and closed")
        # They are closed after auth_timeout_s however they keep alive; then there is room.
        t0 = time.monotonic()
        for c in waiting:
            try:
                c.send_raw(b"\n")
            except OSError:
                pass
        closed = all(c.expect_eof(timeout=6) for c in waiting)
        s.check(closed, "unauthenticated connections are closed after auth_timeout_s",
                "%.1f s" % (time.monotonic() - t0))
        late = srv.connect()
        late.ok("auth", {"token": "tok"})
        s.eq(late.ok("stats", {})[0].get("unauthenticated"), 0, "stats counts none waiting")
        stats = good.ok("stats", {})[0]
        s.check(stats.get("connections", 99) <= 3, "their slots are free again", stats)


@T
def batch_render_share(s):
    """A batch of 40 renders takes at most the connection's share (16) of the render queue."""
    with Server(s.bin) as srv:
        a, watcher = srv.connect(timeout=120), srv.connect(timeout=120)
        frame = {"width": 160, "height": 120, "format": "png"}
        a.send([a.request("render", frame, id=i) for i in range(40)])
        deepest = 0
        t0 = time.monotonic()
        while time.monotonic() - t0 < 20:
            st = watcher.ok("stats", {})[0]
            deepest = max(deepest, st.get("render_queue", 0))
            if st.get("frames_rendered", 0) >= 40:
                break
            time.sleep(0.01)
        s.check(deepest <= 17, "the batch's renders wait their turn (queue depth)", deepest)
        resp, _ = a.recv_response(timeout=120)
        s.eq([r.get("id") for r in resp], list(range(40)), "the batch is answered whole, in order")


@T
def output_budget(s):
    """Clients that leave big frames unread spend the server's output budget: further big
    frames are refused with -32003, the server does not grow, and small requests go on."""
    cfg = mock.config_file({"limits": {"output_total_bytes": 24 * MB}})
    with Server(s.bin, "--config", cfg) as srv:
        watcher = srv.connect(timeout=60)
        rss0 = srv.rss()
        hogs = []
        frame = {"width": 1024, "height": 1024, "format": "rgba8"}  # 4 MiB each
        refused = 0
        for i in range(12):
            h = srv.connect(timeout=60, rcvbuf=4096)
            h.send(h.request("render", frame))
            hogs.append(h)
        time.sleep(3)
        stats = watcher.ok("stats", {})[0]
        total = (stats.get("memory") or {}).get("output_total_bytes", 0)
        s.check(total <= 24 * MB + 5 * MB, "the output total stays near its budget",
                "%d MB" % (total // MB))
        # A new big frame is refused while the budget is spent.
        probe = srv.connect(timeout=60)
        e = probe.call("render", frame)[0]
        refused = (e.get("error") or {}).get("code") == E_LIMIT
        s.check(refused, "a frame past the budget is refused with -32003", mock.short(e))
        t0 = time.monotonic()
        watcher.ok("scene.get", {"path": "camera"})
        s.check(time.monotonic() - t0 < 2, "a client waiting for nothing is served")
        s.check(srv.rss() - rss0 < 200 * MB, "the server did not grow with the unread frames",
                "%d MB" % ((srv.rss() - rss0) // MB))
        for h in hogs:
            h.close()
        time.sleep(0.5)
        probe2 = srv.connect(timeout=60)
        r, att = probe2.ok("render", frame)
        s.eq(len(att or b""), 4 * MB, "once they are gone, big frames are served again")


@T
def unread_subscriptions(s):
    """16 subscriptions of big frames that are never read stay within the output budget, and
    the connection is closed for not reading."""
    cfg = mock.config_file({"limits": {"output_total_bytes": 64 * MB}})
    with Server(s.bin, "--config", cfg) as srv:
        watcher = srv.connect(timeout=60)
        rss0 = srv.rss()
        sub = srv.connect(timeout=60, rcvbuf=4096)
        for i in range(16):
            sub.send(sub.request("frames.subscribe",
                                 {"width": 512, "height": 512, "format": "rgbaf32", "fps": 30},
                                 id=i))
        peak = 0
        t0 = time.monotonic()
        closed_at = None
        while time.monotonic() - t0 < 16:
            peak = max(peak, srv.rss() - rss0)
            st = watcher.ok("stats", {})[0]
            if st.get("subscriptions", 1) == 0:
                closed_at = time.monotonic() - t0
                break
            time.sleep(0.25)
        s.check(peak < 64 * MB + 160 * MB, "memory stays bounded by the output budget",
                "peak %d MB over the start" % (peak // MB))
        s.check(closed_at is not None and closed_at < 15,
                "the subscriber that never reads is closed", closed_at)


@T
def slow_steady_reader(s):
    """A reader taking a big answer at a steady 1.5 MB/s for over 10 s is not cut off."""
    with Server(s.bin) as srv:
        c = srv.connect(timeout=60, rcvbuf=65536)
        c.send(c.request("render", {"width": 1024, "height": 1024, "format": "rgbaf32"}))
        time.sleep(1)
        got = 0
        t0 = time.monotonic()
        want = 16 * MB
        ok = True
        while got < want + 100:
            try:
                chunk = c.sock.recv(65536)
            except OSError as e:
                ok = False
                s.fail("the slow reader was cut off", str(e))
                break
            if not chunk:
                ok = False
                break
            got += len(chunk)
            time.sleep(len(chunk) / (1.5 * MB))
            if got > want:
                break
        s.check(ok and got >= want, "the whole answer arrived",
                "%d of %d bytes in %.1f s" % (got, want, time.monotonic() - t0))
        s.check(time.monotonic() - t0 > 10, "and it took longer than the stall time",
                "%.1f s" % (time.monotonic() - t0))


@T
def unix_socket_path(s):
    d = tempfile.mkdtemp(prefix="volfx-unix-")
    path = os.path.join(d, "plain.txt")
    with open(path, "w") as f:
        f.write("keep me\n")
    p = subprocess.run([os.path.join(s.bin, "volfxd"), "--listen", "none", "--unix", path,
                        "--log-level", "warn"], capture_output=True, timeout=120)
    s.check(p.returncode != 0, "--unix on a regular file refuses to start", p.returncode)
    s.check(b"not a socket" in p.stderr, "and says why", p.stderr[-300:])
    with open(path) as f:
        s.eq(f.read(), "keep me\n", "the file is left alone")
    sock = os.path.join(d, "v.sock")
    first = Server(s.bin, "--unix", sock).start()
    try:
        p = subprocess.run([os.path.join(s.bin, "volfxd"), "--listen", "none", "--unix", sock,
                            "--log-level", "warn"], capture_output=True, timeout=120)
        s.check(p.returncode != 0, "a second server does not take a live socket", p.returncode)
        s.check(b"another server" in p.stderr, "and says why", p.stderr[-300:])
        u = socket.socket(socket.AF_UNIX)
        u.connect(sock)
        u.sendall(rpc("server.info"))
        s.check(b'"volfxd"' in u.recv(65536), "the first still serves on it")
        u.close()
    finally:
        first.kill()  # Killed, so that it leaves its socket behind.
    # A socket left by a killed server is stale: the next one takes its place.
    s.check(os.path.exists(sock), "the killed server left its socket")
    with Server(s.bin, "--unix", sock):
        u = socket.socket(socket.AF_UNIX)
        u.connect(sock)
        u.sendall(rpc("server.info"))
        s.check(b'"volfxd"' in u.recv(65536), "a stale socket is replaced")
        u.close()


if __name__ == "__main__":
    sys.exit(suite.main())
