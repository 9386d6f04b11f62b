#!/usr/bin/env python3
"""
volfxd's --http listener: the viewer's static files (MIME types, no way out of the directory)
and JSON-RPC over WebSocket (docs/protocol.md, "WebSocket"):

- Origin checks: a WebSocket from another site's page is refused, the server's own address
  (any loopback name for a loopback listener) and --http-origin are taken, no Origin is taken;
- the token: nothing but auth before it, wrong tokens refused and the connection closed after
  limits.auth_failures of them;
- bad input gets what it gets over TCP: malformed JSON, a line break inside a string, a message
  over limits.line_bytes (answered -32003, then closed), a binary message (closed, 1003), the
  limit on connections waiting to authenticate; and the server keeps serving TCP and other
  WebSockets throughout;
- requests in text messages (fragmented, pretty-printed), attachments as the binary message
  after their text message, subscriptions with latest-wins for a reader that stalls.

    python3 tests/integration/test_websocket.py --bin build/bin
"""

import json
import os
import re
import socket
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
import wsclient  # noqa: E402
from mock import E_LIMIT, E_PARSE, E_UNAUTHORIZED  # noqa: E402
from wsclient import HandshakeRefused, WsClosed, WsConn, http_get  # noqa: E402

suite = mock.Suite("test_websocket", timeout_s=400)
T = suite.test
HTTP_RE = re.compile(r"volfxd http on (\S+):(\d+)\s*$")
PNG = b"\x89PNG\r\n\x1a\n"


def http_port(srv):
    for line in srv.stdout_lines:
        m = HTTP_RE.search(line)
        if m:
            return int(m.group(2))
    raise mock.CheckError("volfxd printed no 'volfxd http on HOST:PORT' line")


def start(*args, limits=None):
    extra = list(args)
    if limits:
        fd, path = tempfile.mkstemp(prefix="volfxd-", suffix=".json")
        with os.fdopen(fd, "w") as f:
            json.dump({"limits": limits}, f)
        extra += ["--config", path]
    return mock.Server(suite.bin, "--http", "127.0.0.1:0", *extra)


def refused(port, origin):
    try:
        WsConn("127.0.0.1", port, origin=origin).close()
    except HandshakeRefused:
        return True
    return False


@T
def static_files(s):
    with start() as srv:
        port = http_port(srv)
        status, headers, body = http_get("127.0.0.1", port, "/")
        suite.eq(status, 200, "GET /")
        suite.check(headers.get("content-type", "").startswith("text/html"), "/ is text/html",
                    headers.get("content-type"))
        suite.check(b"<html" in body.lower(), "/ is the viewer's page")
        for path, mime in (("/viewer.js", "javascript"), ("/viewer.css", "text/css")):
            status, headers, _ = http_get("127.0.0.1", port, path)
            suite.eq(status, 200, "GET " + path)
            suite.check(mime in headers.get("content-type", ""), path + " is " + mime,
                        headers.get("content-type"))
        for path in ("/../CMakeLists.txt", "/%2e%2e/CMakeLists.txt", "/..%2fCMakeLists.txt",
                     "/../../../../etc/passwd", "/nothing.html"):
            status, _, body = http_get("127.0.0.1", port, path)
            suite.check(status in (403, 404), "GET %s is refused" % path, "status %d" % status)
            suite.check(b"project(volfx" not in body and b"root:" not in body,
                        "GET %s reads nothing outside client/web" % path)


@T
def origins(s):
    with start("--http-origin", "https://tools.example.com, http://10.1.2.3:9000") as srv:
        port = http_port(srv)
        for origin in ("http://evil.example", "http://evil.example:%d" % port,
                       "https://127.0.0.1:%d" % port, "http://127.0.0.1:%d" % (port + 1),
                       "null", "http://127.0.0.1.evil.example:%d" % port):
            suite.check(refused(port, origin), "a WebSocket from %s is refused" % origin)
        for origin in (None, "http://127.0.0.1:%d" % port, "http://localhost:%d" % port,
                       "https://tools.example.com", "http://10.1.2.3:9000"):
            suite.check(not refused(port, origin), "a WebSocket from %s is taken" % origin)
        with mock.Conn(srv.host, srv.port) as c:
            r, _ = c.call("server.info")
            suite.check("result" in r, "TCP still served after the refusals")


@T
def token_and_bad_input(s):
    with start("--token", "sesame", limits={"line_bytes": 4096, "unauthenticated": 3}) as srv:
        port = http_port(srv)
        with WsConn("127.0.0.1", port) as w:
            r, _ = w.call("server.info")
            suite.eq(r.get("error", {}).get("code"), E_UNAUTHORIZED, "server.info before auth")
            r, _ = w.call("auth", {"token": "wrong"})
            suite.eq(r.get("error", {}).get("code"), E_UNAUTHORIZED, "a wrong token")
            r, _ = w.call("auth", {"token": "sesame"})
            suite.check(r.get("result") is not None, "the right token", mock.short(r))
            # Malformed JSON, then a line break inside a string, then pretty-printed JSON.
            w.send_text('{"jsonrpc": "2.0", "id": 1, "method": ')
            r, _ = w.recv_response()
            suite.eq(r.get("error", {}).get("code"), E_PARSE, "malformed JSON")
            w.send_text('{"jsonrpc":"2.0","id":2,"method":"scene.get","params":{"scene":"a\nb"}}')
            r, _ = w.recv_response()
            suite.eq(r.get("error", {}).get("code"), E_PARSE, "a raw line break in a string")
            w.send_text(json.dumps({"jsonrpc": "2.0", "id": 3, "method": "server.info"},
                                   indent=2), fragments=7)
            r, _ = w.recv_response()
            suite.eq(r.get("id"), 3, "a pretty-printed request in seven fragments")
            r, att = w.call("render", {"width": 64, "height": 48})
            suite.check(att is not None and att.startswith(PNG) and
                        len(att) == r["result"]["attachment"]["bytes"],
                        "render's PNG is the binary message after its response")
            # A batch: one array message, then its attachments in order.
            w.send([{"jsonrpc": "2.0", "id": 10 + i, "method": "render",
                     "params": {"width": 16 + i, "height": 16}} for i in range(2)])
            op, data = w.recv_message()
            arr = json.loads(data)
            suite.eq([x["id"] for x in arr], [10, 11], "a batch is one array message")
            for x in arr:
                op, att = w.recv_message()
                suite.check(op == wsclient.OP_BINARY and len(att) == x["result"]["attachment"]
                            ["bytes"], "a batch's attachments follow it in order")
            # Over the line limit: -32003, then closed.
            w.send_text('{"jsonrpc":"2.0","id":4,"method":"server.info","params":{"x":"%s"}}' %
                        ("y" * 8000))
            r, _ = w.recv_response()
            suite.eq(r.get("error", {}).get("code"), E_LIMIT, "a message over line_bytes")
            try:
                w.recv_message()
                suite.fail("the connection closes after an oversize message")
            except (WsClosed, OSError):
                pass
        # A wrong token three times closes; the unauthenticated slots are limited.
        with WsConn("127.0.0.1", port) as w:
            for i in range(3):
                r, _ = w.call("auth", {"token": "no%d" % i})
                suite.eq(r.get("error", {}).get("code"), E_UNAUTHORIZED, "wrong token %d" % i)
            try:
                w.recv_message()
                suite.fail("three wrong tokens close the WebSocket")
            except (WsClosed, OSError):
                pass
        waiting = [WsConn("127.0.0.1", port) for _ in range(3)]
        with WsConn("127.0.0.1", port) as w:
            r, _ = w.recv_response()
            suite.eq(r.get("error", {}).get("code"), E_LIMIT, "a 4th connection waiting to auth")
            suite.eq(r.get("error", {}).get("data", {}).get("path"), "unauthenticated",
                     "its error names the limit")
        with mock.Conn(srv.host, srv.port) as c:
            r, _ = c.recv_response()
            suite.eq(r.get("error", {}).get("code"), E_LIMIT,
                     "TCP shares the slots waiting to authenticate")
        for w in waiting:
            w.close()
        time.sleep(0.5)
        with WsConn("127.0.0.1", port) as w:
            r, _ = w.call("auth", {"token": "sesame"})
            suite.check(r.get("result") is not None, "a slot frees when its WebSocket closes")
        # A binary message closes with 1003; others go on.
        with WsConn("127.0.0.1", port) as w, WsConn("127.0.0.1", port) as other:
            other.call("auth", {"token": "sesame"})
            w.send_frame(wsclient.OP_BINARY, b"\x00\x01")
            try:
                w.recv_message()
                suite.fail("a binary message closes the WebSocket")
            except WsClosed as e:
                suite.eq(e.code, 1003, "the close code of a binary message")
            r, _ = other.call("server.info")
            suite.check("result" in r, "another WebSocket goes on")


@T
def subscriptions_latest_wins(s):
    with start() as srv:
        port = http_port(srv)
        with WsConn("127.0.0.1", port) as w:
            w.call("sim.play", {})
            r, _ = w.call("frames.subscribe", {"width": 320, "height": 180, "fps": 60,
                                               "camera": {"fov_y": 30}})
            sub = r["result"]["id"]
            msg, att = w.recv_json()
            suite.eq(msg.get("method"), "frames", "a frame notification")
            suite.check(att is not None and att.startswith(PNG), "its PNG follows it")
            # Reading nothing for a while: once the socket's buffers are full, the frames wait
            # one at a time, the newest winning, and the server's output stays small.
            time.sleep(4)
            with WsConn("127.0.0.1", port) as other:
                r, _ = other.call("stats")
                out = r["result"]["memory"]["output_total_bytes"]
                suite.check(out < 8 << 20, "a stalled subscriber holds at most a few frames", out)
            last, deadline = None, time.monotonic() + 20
            while time.monotonic() < deadline and not (last and last["dropped"] > 0):
                msg, att = w.recv_json()
                if msg.get("method") == "frames":
                    last = msg["params"]
            suite.check(last and last["dropped"] > 0, "frames were dropped while not reading",
                        mock.short(last))
            suite.check(last and last["frame"] > 0, "the scene plays", mock.short(last))
            r, _ = w.call("frames.unsubscribe", {"id": sub})
            suite.check("result" in r, "unsubscribed", mock.short(r))


@T
def http_connections_bounded(s):
    """Plain HTTP connections that never send a request hold at most limits.connections (plus
    libwebsockets' own few) of the server's sockets; the rest wait in the kernel's backlog, and
    the server goes on serving once they close."""
    with start(limits={"connections": 4}) as srv:
        port = http_port(srv)
        fds = "/proc/%d/fd" % srv.proc.pid
        before = len(os.listdir(fds))
        socks = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(40)]
        time.sleep(1.5)
        held = len(os.listdir(fds)) - before
        suite.check(held <= 4 + 8, "40 idle HTTP connections hold at most 12 sockets",
                    "%d held" % held)
        for k in socks:
            k.close()
        time.sleep(0.5)
        with socket.create_connection(("127.0.0.1", port), timeout=10) as k:
            k.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1:%d\r\n\r\n" % port)
            suite.check(k.recv(12).startswith(b"HTTP/1.1 200"), "a page is served after them")


suite.main()
