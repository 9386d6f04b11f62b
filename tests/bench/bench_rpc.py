#!/usr/bin/env python3
"""
RPC throughput and latency of volfxd (not run by ctest).

(a) pipelined: N small requests (`scene.get` of `camera.fov_y`) on one connection, sent in
    windows by a sender thread while a receiver thread counts response lines; req/s.
(b) concurrent: C connections, each doing sequential request/response for D seconds, spread
    over worker processes (one selector loop each, so the GIL is not shared); total req/s,
    p50 and p99 latency.
Each is repeated R times; the medians are printed as a markdown table with the command line.

The client is Python: for small requests it may be the bottleneck rather than the server. The
table shows the client's CPU time beside the wall time so a reader can tell.

    python3 tests/bench/bench_rpc.py --bin build/bin          # starts its own volfxd
    python3 tests/bench/bench_rpc.py --port 7878               # an already running one
"""

import argparse
import json
import multiprocessing
import os
import selectors
import socket
import statistics
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402

REQ = b'{"jsonrpc":"2.0","method":"scene.get","params":{"path":"camera.fov_y"},"id":%d}\n'
TARGET_PIPELINED = 50000.0
TARGET_P99_MS = 2.0


def connect(host, port, bufsize=4 << 20):
    s = socket.create_connection((host, port), timeout=30)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, bufsize)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, bufsize)
    return s


def check_one(host, port):
    """One request, checked, so a broken server does not produce a fast but empty figure."""
    s = connect(host, port)
    s.sendall(REQ % 1)
    buf = b""
    while b"\n" not in buf:
        chunk = s.recv(65536)
        if not chunk:
            raise SystemExit("bench: the server closed the connection")
        buf += chunk
    msg = json.loads(buf.split(b"\n", 1)[0])
    s.close()
    if "result" not in msg:
        raise SystemExit("bench: scene.get camera.fov_y failed: %s" % msg)


def pipelined(host, port, n, window):
    """Returns (req/s, client CPU s, wall s)."""
    blocks = []
    for start in range(0, n, window):
        blocks.append(b"".join(REQ % i for i in range(start, min(n, start + window))))
    s = connect(host, port)
    cond = threading.Condition()
    state = {"sent": 0, "recv": 0, "err": None}

    def receiver():
        got = 0
        try:
            while got < n:
                chunk = s.recv(1 << 20)
                if not chunk:
                    state["err"] = "connection closed after %d responses" % got
                    break
                got += chunk.count(b"\n")
                with cond:
                    state["recv"] = got
                    cond.notify()
        except OSError as e:
            state["err"] = str(e)
        with cond:
            state["recv"] = max(got, state["recv"])
            state["done"] = True
            cond.notify()

    c0 = time.process_time()
    t0 = time.perf_counter()
    rt = threading.Thread(target=receiver, daemon=True)
    rt.start()
    sent = 0
    for i, b in enumerate(blocks):
        with cond:
            # At most two windows in flight.
            while sent - state["recv"] > window and not state.get("done"):
                cond.wait(5)
        if state.get("done"):
            break
        s.sendall(b)
        sent += min(window, n - i * window)
    rt.join(300)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    s.close()
    if state["err"] or state["recv"] < n:
        raise SystemExit("bench: pipelined run failed: %s (%d of %d)" %
                         (state["err"], state["recv"], n))
    return n / wall, cpu, wall


def _worker(host, port, nconn, duration, out):
    """One process: 'nconn' connections, each sequential, in one selector loop."""
    sel = selectors.DefaultSelector()
    conns = []
    for i in range(nconn):
        s = connect(host, port, 1 << 16)
        s.setblocking(False)
        st = {"sock": s, "buf": b"", "t": 0.0, "id": i * 10000000}
        conns.append(st)
        sel.register(s, selectors.EVENT_READ, st)
    lat = []
    c0 = time.process_time()
    start = time.perf_counter()
    end = start + duration
    for st in conns:
        st["t"] = time.perf_counter()
        st["sock"].send(REQ % st["id"])
    active = len(conns)
    while active:
        for key, _ in sel.select(timeout=5):
            st = key.data
            chunk = st["sock"].recv(65536)
            if not chunk:
                raise SystemExit("bench: the server closed a connection")
            st["buf"] += chunk
            while b"\n" in st["buf"]:
                _, st["buf"] = st["buf"].split(b"\n", 1)
                now = time.perf_counter()
                lat.append(now - st["t"])
                if now < end:
                    st["id"] += 1
                    st["t"] = now
                    st["sock"].send(REQ % st["id"])
                else:
                    sel.unregister(st["sock"])
                    active -= 1
    wall = time.perf_counter() - start
    for st in conns:
        st["sock"].close()
    out.put((lat, wall, time.process_time() - c0))


def concurrent(host, port, clients, duration, procs):
    """Returns (req/s, p50 ms, p99 ms, client CPU s, wall s)."""
    q = multiprocessing.Queue()
    per = [clients // procs + (1 if i < clients % procs else 0) for i in range(procs)]
    ps = [multiprocessing.Process(target=_worker, args=(host, port, n, duration, q))
          for n in per if n]
    for p in ps:
        p.start()
    lat, wall, cpu = [], 0.0, 0.0
    for _ in ps:
        l, w, c = q.get(timeout=duration + 120)
        lat += l
        wall = max(wall, w)
        cpu += c
    for p in ps:
        p.join(30)
    lat.sort()
    p50 = lat[len(lat) // 2] * 1000
    p99 = lat[min(len(lat) - 1, int(len(lat) * 0.99))] * 1000
    return len(lat) / wall, p50, p99, cpu, wall


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, help="use a running volfxd instead of starting one")
    ap.add_argument("-n", type=int, default=200000, help="pipelined requests per run")
    ap.add_argument("--window", type=int, default=2000, help="pipelined requests per write")
    ap.add_argument("--clients", type=int, default=64)
    ap.add_argument("--duration", type=float, default=5.0)
    ap.add_argument("--procs", type=int, default=0, help="client processes for (b); 0: nproc")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--only", choices=("pipelined", "concurrent"))
    a = ap.parse_args()
    procs = a.procs or min(a.clients, max(1, os.cpu_count() or 1))

    srv = None
    if a.port is None:
        srv = mock.Server(os.path.abspath(a.bin), stop_timeout=30)
        srv.start()
        host, port = srv.host, srv.port
    else:
        host, port = a.host, a.port
    try:
        check_one(host, port)
        c = mock.Conn(host, port)
        info, _ = c.ok("server.info", {})
        c.close()
        rows = []
        if a.only in (None, "pipelined"):
            runs = []
            for i in range(a.repeat):
                r = pipelined(host, port, a.n, a.window)
                runs.append(r)
                print("  pipelined run %d: %.0f req/s (client CPU %.2f s of %.2f s)" %
                      (i + 1, r[0], r[1], r[2]), flush=True)
            rates = [r[0] for r in runs]
            cpu_share = statistics.median(r[1] / r[2] for r in runs)
            rows.append(("(a) pipelined, 1 connection, %d requests, window %d" % (a.n, a.window),
                         "%.0f req/s" % statistics.median(rates),
                         "%.0f-%.0f" % (min(rates), max(rates)),
                         ">= %.0f req/s" % TARGET_PIPELINED,
                         "yes" if statistics.median(rates) >= TARGET_PIPELINED else "no",
                         "%.0f%%" % (100 * cpu_share)))
        if a.only in (None, "concurrent"):
            runs = []
            for i in range(a.repeat):
                r = concurrent(host, port, a.clients, a.duration, procs)
                runs.append(r)
                print("  concurrent run %d: %.0f req/s, p50 %.3f ms, p99 %.3f ms "
                      "(client CPU %.2f s over %d processes, %.2f s)" %
                      (i + 1, r[0], r[1], r[2], r[3], procs, r[4]), flush=True)
            rate = statistics.median(r[0] for r in runs)
            p50 = statistics.median(r[1] for r in runs)
            p99 = statistics.median(r[2] for r in runs)
            cpu_share = statistics.median(r[3] / (r[4] * procs) for r in runs)
            label = "(b) %d connections, sequential, %.0f s" % (a.clients, a.duration)
            rows.append((label + ": throughput", "%.0f req/s" % rate,
                         "%.0f-%.0f" % (min(r[0] for r in runs), max(r[0] for r in runs)),
                         "", "", "%.0f%%" % (100 * cpu_share)))
            rows.append((label + ": p50 latency", "%.3f ms" % p50,
                         "%.3f-%.3f" % (min(r[1] for r in runs), max(r[1] for r in runs)),
                         "", "", ""))
            rows.append((label + ": p99 latency", "%.3f ms" % p99,
                         "%.3f-%.3f" % (min(r[2] for r in runs), max(r[2] for r in runs)),
                         "<= %.0f ms" % TARGET_P99_MS, "yes" if p99 <= TARGET_P99_MS else "no",
                         ""))
        print()
        print("`%s`" % " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]))
        print()
        print("volfxd %s, OpenCL device %s; client: Python %s, %d CPUs, medians of %d runs" %
              (info.get("version"), (info.get("opencl") or {}).get("device"),
               sys.version.split()[0], os.cpu_count() or 0, a.repeat))
        print()
        print("| benchmark | median | range | target | met | client CPU |")
        print("| --- | --- | --- | --- | --- | --- |")
        for row in rows:
            print("| " + " | ".join(row) + " |")
        print()
        print("Client CPU near 100% means the Python client, not volfxd, limits the figure.")
    finally:
        if srv is not None:
            srv.stop()


if __name__ == "__main__":
    main()
