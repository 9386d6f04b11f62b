#!/usr/bin/env python3
"""
Load and resource behaviour of a real volfxd: many concurrent clients, clients that vanish
mid-render, a subscriber that never reads (latest frame wins: memory stays bounded and other
clients are served), the output limit as backpressure, and the connection limit.

    python3 tests/integration/test_load.py --bin build/bin
"""

import json
import os
import socket
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import Server, png_info, short  # noqa: E402

suite = mock.Suite("test_load", timeout_s=560)
suite.server_args = []
T = suite.test

N_CLIENTS = 200


@T
def many_clients(s):
    n = N_CLIENTS
    start = threading.Barrier(n + 1, timeout=120)
    done = threading.Barrier(n + 1, timeout=300)
    leave = threading.Barrier(n + 1, timeout=120)
    errors = []
    lat = []
    busy = [0]
    lock = threading.Lock()

    def client(i):
        c = None
        try:
            c = mock.Conn(s.srv.host, s.srv.port, timeout=120)
        except Exception as e:
            with lock:
                errors.append("client %d: connect: %s: %s" % (i, type(e).__name__, e))
        try:
            start.wait()
        except threading.BrokenBarrierError:
            pass
        try:
            if c is not None:
                t0 = time.monotonic()
                r, _ = c.ok("server.info", {})
                if r.get("name") != "volfxd":
                    raise mock.CheckError("server.info: %s" % short(r))
                # -32002 (render queue full, 64 jobs by default) is a documented answer to
                # 200 simultaneous renders: a client retries it, as the message says.
                for attempt in range(200):
                    resp, a = c.call("render", {"width": 64, "height": 64, "t": i})
                    if resp.get("error", {}).get("code") != mock.E_BUSY:
                        break
                    with lock:
                        busy[0] += 1
                    time.sleep(0.02 + 0.01 * min(attempt, 20))
                r = resp.get("result")
                if not isinstance(r, dict) or r.get("t") != i or \
                        png_info(a or b"") != (64, 64, 8, 6):
                    raise mock.CheckError("render: %s" % short(resp))
                with lock:
                    lat.append(time.monotonic() - t0)
        except Exception as e:
            with lock:
                errors.append("client %d: %s: %s" % (i, type(e).__name__, e))
        finally:
            for b in (done, leave):
                try:
                    b.wait()
                except threading.BrokenBarrierError:
                    pass
            if c:
                c.close()

    threads = [threading.Thread(target=client, args=(i,), daemon=True) for i in range(n)]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    try:
        start.wait()
    except threading.BrokenBarrierError:
        pass
    try:
        done.wait()
    except threading.BrokenBarrierError:
        s.fail("all clients finish within 300 s")
    with s.srv.connect() as c:
        st, _ = c.ok("stats", {})
    s.check(st.get("connections", 0) >= n + 1, "stats counts %d open connections" % (n + 1),
            short(st.get("connections")))
    try:
        leave.wait()
    except threading.BrokenBarrierError:
        pass
    for t in threads:
        t.join(30)
    el = time.monotonic() - t0
    s.check(not errors, "%d concurrent clients all served (server.info + 64x64 render)" % n,
            "%d failed; first: %s" % (len(errors), errors[:3]))
    if lat:
        lat.sort()
        print("    %d clients in %.1f s; per-client latency p50 %.0f ms, max %.0f ms; "
              "%d busy answers retried" % (n, el, 1000 * lat[len(lat) // 2], 1000 * lat[-1],
                                           busy[0]))
    time.sleep(0.5)
    with s.srv.connect() as c:
        st, _ = c.ok("stats", {})
    s.check(st.get("connections", 99) <= 2, "connections released after the clients close",
            short(st.get("connections")))


@T
def vanishing_clients(s):
    rss0 = s.srv.rss()
    for i in range(5):
        c = s.srv.connect()
        c.send({"jsonrpc": "2.0", "method": "render", "id": 1,
                "params": {"width": 1024, "height": 1024}})
        c.close()
    # Several more that reset the connection instead of closing it.
    for i in range(3):
        c = s.srv.connect()
        c.send({"jsonrpc": "2.0", "method": "render", "id": 1,
                "params": {"width": 1024, "height": 1024, "format": "rgbaf32"}})
        c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        c.close()
    with s.srv.connect(timeout=120) as c:
        t0 = time.monotonic()
        r, _ = c.ok("server.info", {})
        s.check(time.monotonic() - t0 < 2, "server.info answered while abandoned renders run",
                "%.2f s" % (time.monotonic() - t0))
        r, a = c.ok("render", {"width": 64, "height": 64}, timeout=120)
        s.eq(png_info(a or b""), (64, 64, 8, 6), "renders after clients vanished mid-render")
        time.sleep(0.3)
        st, _ = c.ok("stats", {})
        s.check(st.get("connections") == 1, "vanished connections are gone from stats",
                short(st.get("connections")))
        s.check((st.get("memory") or {}).get("output_queued_bytes", 1 << 40) < 8 << 20,
                "no output kept for vanished connections", short(st.get("memory")))
    rss1 = s.srv.rss()
    print("    RSS %.1f MB -> %.1f MB" % (rss0 / 1e6, rss1 / 1e6))


@T
def slow_subscriber(s):
    srv = s.srv
    with srv.connect(timeout=60) as w:
        w.ok("scene.create", {"name": "slow", "preset": "demo"})
        w.ok("sim.play", {"scene": "slow", "rate": 60})
        w.ok("render", {"scene": "slow", "width": 512, "height": 512}, timeout=60)  # warm up
    rss0 = srv.rss()
    sub = srv.connect(timeout=30, rcvbuf=16384)
    r, _ = sub.ok("frames.subscribe", {"scene": "slow", "width": 512, "height": 512,
                                       "fps": 60, "format": "png"})
    sid = r.get("id")
    other = srv.connect(timeout=30)

    def renders():
        passes = (other.ok("stats", {})[0].get("passes") or {})
        return (passes.get("objects") or {}).get("count", 0)

    renders0 = renders()
    lats, rss_max, queued_max = [], rss0, 0
    t0 = time.monotonic()
    while time.monotonic() - t0 < 10:
        a = time.monotonic()
        try:
            info, _ = other.ok("server.info", {})
        except Exception as e:
            s.fail("server.info answered while a subscriber does not read", str(e))
            break
        lats.append(time.monotonic() - a)
        st, _ = other.ok("stats", {})
        queued_max = max(queued_max, (st.get("memory") or {}).get("output_queued_bytes", 0))
        rss_max = max(rss_max, srv.rss() or 0)
        time.sleep(0.1)
    elapsed = time.monotonic() - t0
    stalled_renders = renders() - renders0
    lats.sort()
    growth = rss_max - rss0
    print("    server.info x%d: p50 %.1f ms, max %.1f ms; RSS %.1f MB -> max %.1f MB; "
          "output queued max %.2f MB" % (len(lats), 1000 * lats[len(lats) // 2],
                                         1000 * lats[-1], rss0 / 1e6, rss_max / 1e6,
                                         queued_max / 1e6))
    s.check(lats and lats[-1] < 2.0, "server.info latency < 2 s beside a stalled subscriber",
            "max %.2f s" % (lats[-1] if lats else -1))
    s.check(growth < 150e6, "RSS grows less than 150 MB with a stalled 60 fps subscriber",
            "grew %.1f MB" % (growth / 1e6))
    s.check(queued_max < 16 << 20, "output queued stays bounded (latest frame wins)",
            "%.1f MB" % (queued_max / 1e6))
    # After a second of waiting, no more frames are rendered for it (about 60 before that).
    s.check(stalled_renders < 200, "a subscriber that stopped reading costs few renders",
            "%d renders in %.1f s at 60 fps" % (stalled_renders, elapsed))
    # The subscriber starts reading: it is still connected and has been told about drops.
    max_dropped = 0
    got = 0
    t1 = time.monotonic()
    try:
        while time.monotonic() - t1 < 10:
            msg, att = sub.recv_notification(timeout=10)
            p = msg.get("params", {})
            got += 1
            max_dropped = max(max_dropped, p.get("dropped", 0))
            if max_dropped > 0 and got >= 3:
                break
        s.check(max_dropped > 0, "frames notifications report dropped > 0 to a slow reader",
                "%d frames read, dropped %d" % (got, max_dropped))
        r, _ = sub.ok("frames.unsubscribe", {"id": sid}, timeout=30)
        due = 60 * (time.monotonic() - t0)
        print("    subscriber: sent %s, dropped %s over %.1f s at 60 fps (~%d due)" %
              (r.get("sent"), r.get("dropped"), time.monotonic() - t0, due))
        s.check(r.get("dropped", 0) > 0, "unsubscribe reports dropped frames", short(r))
        total = r.get("sent", 0) + r.get("dropped", 0)
        s.check(total >= 0.5 * 60 * elapsed,
                "sent + dropped counts every frame rendered or due", "%s, %.0f due" %
                (short(r), 60 * elapsed))
    except (mock.Closed, OSError) as e:
        s.fail("a slow subscriber is not disconnected (latest frame wins)", str(e))
    sub.close()
    other.close()


@T
def output_backpressure(s):
    """limits.output_bytes (here 1 MiB) is backpressure: one answer larger than it goes out
    whole, a client that pipelines and reads slowly gets every answer in order while the
    server holds about the limit for it, and only a connection that stops reading altogether is
    closed, after 10 s, without disturbing the others."""
    path = mock.config_file({"limits": {"output_bytes": 1 << 20}})
    frame = {"width": 256, "height": 256, "format": "rgbaf32", "layers": ["objects"]}
    with Server(s.bin, "--config", path) as srv:
        c = srv.connect()
        r, a = c.ok("render", dict(frame, width=512, height=512))
        s.eq(len(a or b""), 512 * 512 * 16, "a 4 MiB frame over a 1 MiB limit comes whole")
        s.eq(c.ok("server.info", {})[0].get("name"), "volfxd", "and the connection goes on")
        # Eight pipelined 1 MiB frames, read at about 4 MB/s.
        n = 8
        for i in range(n):
            c.send(c.request("render", dict(frame, t=i)))
        watcher = srv.connect()
        got, queued = [], 0
        while len(got) < n:
            line = c.read_line(60)
            msg = mock.loads(line.decode())
            size = msg.get("result", {}).get("attachment", {}).get("bytes", 0)
            while len(c.buf) < size:
                c._fill(60)
                time.sleep(0.016)
                mem = watcher.ok("stats", {})[0].get("memory") or {}
                queued = max(queued, mem.get("output_queued_bytes", 0))
            del c.buf[:size]
            got.append(msg.get("result", {}).get("t"))
        s.eq(got, list(range(n)), "eight pipelined frames answered in order to a slow reader")
        s.check(queued <= (2 << 20) + (1 << 18), "the server held about the limit for it",
                "%d bytes queued at most" % queued)
        s.eq(c.ok("server.info", {})[0].get("name"), "volfxd", "the slow reader is still served")
        # Other big answers count too: twenty 1 MiB cloud densities pipelined, not read for a
        # while, then read: all arrive, in order, while the server held about the limit.
        c.ok("scene.create", {"name": "cells", "preset": "paper-003"})
        for i in range(20):
            c.send(c.request("cloud.get_cells", {"scene": "cells", "field": "density"}, id=100 + i))
        time.sleep(1.5)
        held = (watcher.ok("stats", {})[0].get("memory") or {}).get("output_queued_bytes", 0)
        s.check(held <= (3 << 20), "pipelined densities: the server holds about the limit",
                "%d bytes queued" % held)
        ids = []
        for i in range(20):
            msg, att = c.recv_response(timeout=60)
            ids.append(msg.get("id"))
        s.eq(ids, list(range(100, 120)), "and every density arrives, in order")
        # A client that stops reading: closed after 10 s with its output over the limit.
        stuck = mock.Conn(srv.host, srv.port, rcvbuf=65536)
        for i in range(n):
            stuck.send(stuck.request("render", frame))
        t0 = time.monotonic()
        s.eq(watcher.ok("server.info", {})[0].get("name"), "volfxd", "others are served meanwhile")
        time.sleep(12)
        closed = False
        try:
            while True:
                stuck._fill(5)
        except mock.Closed:
            closed = True
        except socket.timeout:
            pass
        s.check(closed, "a client that does not read is closed", "%.1f s" % (time.monotonic() - t0))
        s.check("is not reading" in srv.log_text(), "the log says why")
        mem = watcher.ok("stats", {})[0].get("memory") or {}
        s.check(mem.get("output_queued_bytes", 1 << 40) < 1 << 20, "its output is freed",
                short(mem))


@T
def render_queue_share(s):
    """One connection's render requests take at most 16 places in the shared render queue; the
    rest wait unread. A client that pipelines 80 renders therefore has only about 16 of them
    rendered when another client's render, sent after them, is answered (FIFO would make it
    80), and still gets all 80, in order."""
    with s.srv.connect(timeout=120) as a, s.srv.connect(timeout=120) as b, \
            s.srv.connect(timeout=120) as watcher:
        def renders():
            passes = watcher.ok("stats", {})[0].get("passes") or {}
            return (passes.get("objects") or {}).get("count", 0)

        a.ok("scene.create", {"name": "share", "preset": "demo"})
        frame = {"scene": "share", "width": 192, "height": 192, "format": "png"}
        base = renders()
        a.send_raw(b"".join((mock.dumps(a.request("render", frame, id=i)) + "\n").encode()
                            for i in range(80)))
        time.sleep(0.05)
        at_send = renders() - base
        b.ok("render", frame, timeout=120)
        before_b = renders() - base - 1
        # Those rendered while b's request was on its way do not count: on a fast machine the
        # pipeline has already rendered a few by then. What b waits for is the queue's share.
        s.check(before_b - at_send <= 24,
                "another client's render waited for few of the pipelined ones",
                "%d of the 80 were rendered by then, %d of them after b sent its render" %
                (before_b, before_b - at_send))
        ids = [a.recv_response(timeout=120)[0].get("id") for _ in range(80)]
        s.eq(ids, list(range(80)), "and the pipelining client still gets all 80, in order")


def _limit_server(s, n):
    """Starts a server with a connection limit of 'n' by a flag if --help names one, else by
    a config file in a few plausible formats. Returns a started Server or None."""
    help_text = mock.volfxd_help(s.bin)
    tries = []
    for flag in ("--max-connections", "--connections", "--connection-limit"):
        if flag in help_text:
            tries.append(("flag %s" % flag, [flag, str(n)], None))
    d = mock.tempfile.mkdtemp(prefix="volfx-cfg-")
    for label, text in (("JSON limits.connections", json.dumps({"limits": {"connections": n}})),
                        ("JSON connections", json.dumps({"connections": n})),
                        ("key = value", "connections = %d\n" % n),
                        ("INI [limits]", "[limits]\nconnections = %d\n" % n)):
        path = os.path.join(d, "volfxd-%d.conf" % len(tries))
        with open(path, "w") as f:
            f.write(text)
        tries.append(("config file, " + label, ["--config", path], path))
    for label, args, _ in tries:
        srv = Server(s.bin, *args, start_timeout=60)
        try:
            srv.start()
        except mock.CheckError:
            srv.kill()
            continue
        try:
            with srv.connect() as c:
                lim = c.ok("server.info", {})[0].get("limits", {}).get("connections")
        except Exception:
            lim = None
        if lim == n:
            print("    connection limit %d set by %s" % (n, label))
            return srv
        srv.kill()
    return None


@T
def connection_limit(s):
    srv = _limit_server(s, 4)
    if srv is None:
        s.note("no documented way to lower the connection limit (no flag in --help, no config "
               "format giving limits.connections 4): skipped")
        return
    with srv:
        conns = [srv.connect() for _ in range(4)]
        for c in conns:
            c.ok("server.info", {})
        extra = srv.connect(timeout=5)
        outcome = None
        try:
            extra.send(extra.request("server.info", {}))
            m, _ = extra.recv_response(timeout=5)
            if "result" in m:
                outcome = "served"
            else:
                outcome = "error %s" % short(m.get("error"))
                s.check(extra.expect_eof(5), "over the limit: closed after the error")
        except (mock.Closed, ConnectionError, BrokenPipeError):
            outcome = "closed"
        except socket.timeout:
            outcome = "hang"
        s.check(outcome not in ("served", "hang"),
                "a connection over the limit is refused cleanly (error or close)", outcome)
        print("    5th connection with a limit of 4: %s" % outcome)
        extra.close()
        for c in conns:
            c.ok("server.info", {})
        conns[0].close()
        ok = False
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5 and not ok:
            try:
                with srv.connect(timeout=3) as c:
                    ok = c.ok("server.info", {})[0].get("name") == "volfxd"
            except Exception:
                time.sleep(0.2)
        s.check(ok, "a connection is accepted again once one closes")


if __name__ == "__main__":
    sys.exit(suite.main())
