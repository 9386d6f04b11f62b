#!/usr/bin/env python3
"""volfx: a Python client for volfxd (standard library only, Python 3.9+).

The wire contract is docs/protocol.md: JSON-RPC 2.0, one JSON text per line, and binary
attachments as exactly ``attachment.bytes`` raw bytes after the line (or base64 in ``data``
when the request asked for ``encoding: "base64"``).

    with Client(port=7878) as c:
        print(c.info()["version"])
        c.set(path="camera.fov_y", value=50)
        result, png = c.render(256, 256)
        sid = c.subscribe(width=64, height=64, fps=10)
        for params, data in c.frames(count=3):
            print(params["frame"], len(data))
        c.unsubscribe(sid)

Run as a module it mirrors the C ``volfx`` CLI: ``python3 -m volfx --port P info`` (with
``client/python`` on ``PYTHONPATH``). ``volfx.testing`` starts a private volfxd for a test
suite and compares frames with golden images (docs/testing.md).
"""

import argparse
import base64
import collections
import json
import os
import re
import select
import signal
import socket
import sys
import time

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7878

# Notifications kept while nobody reads them; the oldest are dropped first.
QUEUE_MAX = 256

ERROR_NAMES = {
    -32700: "parse error",
    -32600: "invalid request",
    -32601: "method not found",
    -32602: "invalid params",
    -32603: "internal error",
    -32001: "unauthorized",
    -32002: "busy",
    -32003: "limit exceeded",
    -32004: "not found",
    -32005: "device error",
}


class VolfxError(Exception):
    """An error response from the server: JSON-RPC ``code``, ``message`` and ``data.path``."""

    def __init__(self, code, message, path=None, data=None):
        self.code = code
        self.message = message
        self.path = path
        self.data = data
        kind = ERROR_NAMES.get(code, "error %d" % code)
        text = message if message.startswith(kind) else "%s: %s" % (kind, message)
        if path:
            text += " (path %s)" % path
        super().__init__(text)


class ConnectionLost(Exception):
    """The connection closed, timed out or carried something that is not the protocol."""


class Client:
    """One blocking connection to volfxd.

    ``host``/``port`` for TCP, or ``unix`` for a Unix socket path. ``token`` is sent with
    ``auth`` right after connecting. ``timeout`` (seconds, None for none) bounds every socket
    operation; a call that times out raises ``ConnectionLost`` and the client should be closed.
    Not thread-safe.
    """

    def __init__(self, host=DEFAULT_HOST, port=DEFAULT_PORT, unix=None, token=None, timeout=30):
        self.timeout = timeout
        if unix:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self._sock.settimeout(timeout)
            self._sock.connect(unix)
        else:
            self._sock = socket.create_connection((host or DEFAULT_HOST, port or DEFAULT_PORT),
                                                  timeout=timeout)
            self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buf = bytearray()
        self._next_id = 1
        self._queue = collections.deque()
        self.queue_dropped = 0
        if token:
            self.call("auth", token=token)

    # -- context manager -------------------------------------------------------------------

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def close(self):
        """Closes the socket; queued notifications are discarded."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self._queue.clear()

    # -- framing ---------------------------------------------------------------------------

    def _recv(self):
        try:
            chunk = self._sock.recv(65536)
        except socket.timeout:
            raise ConnectionLost("timed out waiting for the server") from None
        except OSError as e:
            raise ConnectionLost(str(e)) from None
        if not chunk:
            raise ConnectionLost("connection closed by the server")
        self._buf += chunk

    def _readline(self):
        while True:
            i = self._buf.find(b"\n")
            if i >= 0:
                line = bytes(self._buf[:i])
                del self._buf[:i + 1]
                return line.rstrip(b"\r")
            self._recv()

    def _readexact(self, n):
        while len(self._buf) < n:
            self._recv()
        data = bytes(self._buf[:n])
        del self._buf[:n]
        return data

    def _take_attachment(self, holder):
        """Returns the bytes of ``holder["attachment"]`` (base64 ``data`` or raw), or None."""
        if not isinstance(holder, dict) or not isinstance(holder.get("attachment"), dict):
            return None
        att = holder["attachment"]
        for owner in (att, holder):
            if isinstance(owner.get("data"), str):
                return base64.b64decode(owner.pop("data"))
        n = att.get("bytes")
        if not isinstance(n, int) or n < 0:
            raise ConnectionLost("attachment without a valid byte count")
        return self._readexact(n)

    def _read_message(self):
        """Reads one message and its attachment: (message, bytes or None)."""
        while True:
            line = self._readline()
            if line.strip():
                break
        try:
            msg = json.loads(line)
        except ValueError:
            raise ConnectionLost("malformed line from the server: %r" % line[:200]) from None
        if isinstance(msg, dict) and "method" in msg and "id" not in msg:
            return msg, self._take_attachment(msg.get("params"))
        if isinstance(msg, dict):
            return msg, self._take_attachment(msg.get("result"))
        return msg, None

    def _enqueue(self, msg, data):
        self._queue.append((msg, data))
        while len(self._queue) > QUEUE_MAX:
            self._queue.popleft()
            self.queue_dropped += 1

    # -- calls -----------------------------------------------------------------------------

    def call_raw(self, method, params=None):
        """Sends one request and returns ``(result, attachment bytes or None)``.

        ``params`` is a dict (or list), or None for none. Raises ``VolfxError`` for an error
        response. Notifications that arrive first are queued for ``frames()``/``notifications()``.
        """
        rid = self._next_id
        self._next_id += 1
        req = {"jsonrpc": "2.0", "id": rid, "method": method}
        if params is not None:
            req["params"] = params
        line = json.dumps(req, separators=(",", ":"), allow_nan=False).encode() + b"\n"
        try:
            self._sock.sendall(line)
        except socket.timeout:
            raise ConnectionLost("timed out sending to the server") from None
        except OSError as e:
            raise ConnectionLost(str(e)) from None
        while True:
            msg, data = self._read_message()
            if not isinstance(msg, dict):
                continue
            if "method" in msg and "id" not in msg:
                self._enqueue(msg, data)
                continue
            mid = msg.get("id")
            if mid != rid and not (mid is None and "error" in msg):
                continue  # a stray response, not ours
            if "error" in msg:
                e = msg["error"] or {}
                d = e.get("data")
                path = d.get("path") if isinstance(d, dict) else None
                raise VolfxError(e.get("code", -32603), e.get("message", ""), path, d)
            return msg.get("result"), data

    def call(self, method, **params):
        """Calls ``method`` with keyword params and returns the result (attachment dropped)."""
        return self.call_raw(method, params)[0]

    # -- helpers ---------------------------------------------------------------------------

    def auth(self, token):
        return self.call("auth", token=token)

    def info(self):
        return self.call("server.info")

    def discover(self):
        return self.call("rpc.discover")

    def stats(self):
        return self.call("stats")

    def scenes(self):
        return self.call("scene.list")

    def shutdown(self):
        return self.call("server.shutdown")

    def get(self, path=None, scene="main"):
        """The scene document, or the value at dotted ``path``."""
        params = {"scene": scene}
        if path is not None:
            params["path"] = path
        return self.call("scene.get", **params)

    def set(self, path, value, scene="main"):
        """Sets one value at dotted ``path``; returns ``{"version": n}``."""
        return self.call("scene.set", scene=scene, path=path, value=value)

    def patch(self, patch, scene="main"):
        """Applies an RFC 7386 merge patch atomically; returns ``{"version": n}``."""
        return self.call("scene.set", scene=scene, patch=patch)

    def changes(self, changes, scene="main"):
        """Applies ``[{"path", "value"} or {"path", "patch"}, ...]`` in order as one version,
        or nothing; returns ``{"version": n}``."""
        return self.call("scene.set", scene=scene, changes=list(changes))

    def json_patch(self, ops, scene="main"):
        """Applies an RFC 6902 JSON Patch (a list of operations) as one version, or nothing;
        returns ``{"version": n}``."""
        return self.call("scene.set", scene=scene, ops=list(ops))

    def step(self, n=1, dt=None, scene="main"):
        params = {"scene": scene, "steps": n}
        if dt is not None:
            params["dt"] = dt
        return self.call("sim.step", **params)

    def play(self, rate=None, scene="main"):
        params = {"scene": scene}
        if rate is not None:
            params["rate"] = rate
        return self.call("sim.play", **params)

    def pause(self, scene="main"):
        return self.call("sim.pause", scene=scene)

    def render(self, width=512, height=512, format="png", **kw):
        """Renders one frame; returns ``(result, bytes)``. ``kw``: scene, aov, layers, camera,
        t, encoding, png_level."""
        kw.setdefault("scene", "main")
        return self.call_raw("render", dict(kw, width=width, height=height, format=format))

    def subscribe(self, **kw):
        """Starts a frame stream (``frames.subscribe``) and returns its id."""
        kw.setdefault("scene", "main")
        return self.call("frames.subscribe", **kw)["id"]

    def unsubscribe(self, sid):
        """Ends a stream; returns ``{"id", "sent", "dropped"}``. Its queued frames are dropped."""
        result = self.call("frames.unsubscribe", id=sid)
        self._queue = collections.deque(
            (m, d) for (m, d) in self._queue
            if not (m.get("method") == "frames" and (m.get("params") or {}).get("id") == sid))
        return result

    def notifications(self, method=None, timeout=None, count=None):
        """Yields ``(method, params, bytes)`` for notifications (of ``method`` when given),
        queued ones first. Stops after ``count``, or when none came for ``timeout`` seconds
        (None: the client's timeout)."""
        wait = self.timeout if timeout is None else timeout
        got = 0
        while count is None or got < count:
            item = self._pop(method)
            if item is None:
                item = self._wait_notification(method, wait)
                if item is None:
                    return
            msg, data = item
            got += 1
            yield msg.get("method"), msg.get("params"), data

    def frames(self, timeout=None, count=None):
        """Yields ``(params, bytes)`` for each ``frames`` notification; see notifications()."""
        for _, params, data in self.notifications("frames", timeout, count):
            yield params, data

    def _pop(self, method):
        for i, (msg, data) in enumerate(self._queue):
            if method is None or msg.get("method") == method:
                del self._queue[i]
                return msg, data
        return None

    def _wait_notification(self, method, wait):
        deadline = None if wait is None else time.monotonic() + wait
        while True:
            # Wait for the start of a message with select, so that a quiet stream ends the
            # generator instead of raising, while a message once started is read whole.
            if not self._buf:
                left = None if deadline is None else max(0.0, deadline - time.monotonic())
                ready, _, _ = select.select([self._sock], [], [], left)
                if not ready:
                    return None
            msg, data = self._read_message()
            if not (isinstance(msg, dict) and "method" in msg and "id" not in msg):
                continue
            if method is None or msg.get("method") == method:
                return msg, data
            self._enqueue(msg, data)


# -- command line ----------------------------------------------------------------------------


def _value(text):
    """A CLI value: JSON when it parses, otherwise the string itself."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def _assignments_patch(pairs):
    """Builds a merge patch from PATH=VALUE pairs, or None when a path has an array index."""
    patch = {}
    for path, value in pairs:
        keys = path.split(".")
        if any(k.isdigit() for k in keys):
            return None
        node = patch
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                node[k] = {}
            node = node[k]
        node[keys[-1]] = value
    return patch


def _frame_path(pattern, frame):
    return re.sub(r"%(0?)(\d*)d|%%",
                  lambda m: "%" if m.group(0) == "%%"
                  else ("%" + m.group(1) + m.group(2) + "d") % frame, pattern)


def _frame_params(a):
    p = {"scene": a.scene}
    for key in ("width", "height", "format", "aov", "fps", "encoding"):
        v = getattr(a, key, None)
        if v is not None:
            p[key] = v
    if getattr(a, "layers", None):
        p["layers"] = [x for x in a.layers.split(",") if x]
    if p.get("aov", "beauty") != "beauty" and "format" not in p:
        p["format"] = "f32"
    return p


def _print(v):
    print(json.dumps(v, indent=2))


def _run(c, a):
    cmd = a.command
    if cmd == "info":
        _print(c.info())
    elif cmd == "get":
        _print(c.get(a.path, scene=a.scene))
    elif cmd == "set":
        if a.patch is not None:
            _print(c.patch(json.loads(a.patch), scene=a.scene))
            return 0
        if not a.assignments:
            raise SystemExit("volfx: set needs PATH=VALUE or --patch JSON")
        pairs = []
        for s in a.assignments:
            path, eq, value = s.partition("=")
            if not eq or not path:
                raise SystemExit("volfx: expected PATH=VALUE, got %r" % s)
            pairs.append((path, _value(value)))
        patch = _assignments_patch(pairs)
        if patch is not None:
            _print(c.patch(patch, scene=a.scene))
        else:
            result = None
            for path, value in pairs:
                result = c.set(path, value, scene=a.scene)
            _print(result)
    elif cmd == "step":
        _print(c.step(a.n, a.dt, scene=a.scene))
    elif cmd == "play":
        _print(c.play(a.rate, scene=a.scene))
    elif cmd == "pause":
        _print(c.pause(scene=a.scene))
    elif cmd == "render":
        p = _frame_params(a)
        result, data = c.call_raw("render", p)
        data = data or b""
        if a.output == "-":
            sys.stdout.buffer.write(data)
            out = sys.stderr
        else:
            with open(a.output, "wb") as f:
                f.write(data)
            out = sys.stdout
        print("%s: %sx%s %s %d bytes frame %s work_ms %s" % (
            a.output, result.get("width"), result.get("height"), result.get("format"),
            len(data), result.get("frame"),
            json.dumps(result.get("work_ms", {}), separators=(",", ":"))), file=out)
    elif cmd == "watch":
        p = _frame_params(a)
        sid = c.subscribe(**p)
        received, dropped = 0, 0
        stop = []
        old = signal.signal(signal.SIGINT, lambda *_: stop.append(1))
        try:
            while not stop and (a.count == 0 or received < a.count):
                item = None
                for item in c.frames(timeout=0.2, count=1):
                    pass
                if item is None:
                    continue
                params, data = item
                received += 1
                dropped = params.get("dropped", dropped)
                if a.output:
                    n = received if a.seq else params.get("frame", received)
                    with open(_frame_path(a.output, n), "wb") as f:
                        f.write(data or b"")
        finally:
            signal.signal(signal.SIGINT, old)
        r = c.unsubscribe(sid)
        print("watch: received %d frames, dropped %s, sent %s (subscription %s)" % (
            received, r.get("dropped", dropped), r.get("sent"), sid))
    elif cmd == "stats":
        _print(c.stats())
    elif cmd == "discover":
        _print(c.discover())
    elif cmd == "scenes":
        _print(c.scenes())
    elif cmd == "call":
        params = json.loads(a.params) if a.params else None
        _print(c.call_raw(a.method, params)[0])
    elif cmd == "shutdown":
        _print(c.shutdown())
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(prog="volfx", description="Python client of volfxd.")
    ap.add_argument("--host", default=DEFAULT_HOST)
    ap.add_argument("--port", type=int, default=DEFAULT_PORT)
    ap.add_argument("--unix")
    ap.add_argument("--token", default=os.environ.get("VOLFX_TOKEN"))
    ap.add_argument("--scene", default="main")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds; 0 waits forever")
    sub = ap.add_subparsers(dest="command", required=True)
    for name in ("info", "pause", "stats", "discover", "scenes", "shutdown"):
        sub.add_parser(name)
    sub.add_parser("get").add_argument("path", nargs="?")
    s = sub.add_parser("set", help="PATH=VALUE... (one merge patch unless a path has an index)")
    s.add_argument("assignments", nargs="*")
    s.add_argument("--patch")
    s = sub.add_parser("step")
    s.add_argument("n", type=int)
    s.add_argument("--dt", type=float)
    sub.add_parser("play").add_argument("rate", type=float, nargs="?")
    for name in ("render", "watch"):
        s = sub.add_parser(name)
        s.add_argument("-o", "--output", required=(name == "render"))
        s.add_argument("-W", "--width", type=int)
        s.add_argument("-H", "--height", type=int)
        s.add_argument("-f", "--format")
        s.add_argument("--aov")
        s.add_argument("--layers")
        s.add_argument("--encoding")
        if name == "watch":
            s.add_argument("--fps", type=float)
            s.add_argument("-n", "--count", type=int, default=0)
            s.add_argument("--seq", action="store_true",
                           help="number files by arrival, not by the scene's frame number")
    s = sub.add_parser("call")
    s.add_argument("method")
    s.add_argument("params", nargs="?")
    a = ap.parse_args(argv)

    try:
        with Client(a.host, a.port, unix=a.unix, token=a.token,
                    timeout=a.timeout or None) as c:
            return _run(c, a)
    except VolfxError as e:
        print("volfx: %s" % e, file=sys.stderr)
        return 1
    except (ConnectionLost, OSError, ValueError) as e:
        print("volfx: %s" % e, file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
