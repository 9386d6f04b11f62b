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
        frame = c.latest(sid, timeout=5)      # the newest frame, or None
        for params, data in c.frames(count=3):
            print(params["frame"], len(data))
        c.unsubscribe(sid)

- ``Client`` is blocking; ``AsyncClient`` (``volfx.aio``) is the same over asyncio streams.
  Every server method has a wrapper (``volfx.methods``; ``METHODS`` maps method names to
  them), and ``call``/``call_raw`` call any method by name.
- Frames keep the server's latest-wins: per subscription the client holds only the newest
  unread frame, however long a call blocks; ``replaced(sid)`` counts the frames a newer one
  replaced before they were read. ``frames.ended`` (a deleted scene, a server shutting down)
  is kept as ``ended(sid)`` and yielded by ``notifications()``.
- ``batch()`` collects calls for one JSON-RPC batch line; its ``send()`` returns one
  ``BatchReply`` (result or error) per call.

Params left as None are not sent, so the server applies the defaults of its method table
(docs/protocol.md's method reference); ``Client.defaults(method)`` reads them from rpc.discover.

``python3 -m volfx`` is a small command line over this client (info, get, set, step, play,
pause, render, watch, stats, discover, scenes, call, shutdown); the C ``volfx`` is the full
one (script, sequence, the render-farm commands). ``volfx.testing`` starts a private volfxd
for a test suite and compares frames with golden images (docs/testing.md).
"""

import argparse
import json
import os
import re
import select
import signal
import socket
import sys
import time

from .methods import METHODS, Batch, BatchReply, Methods, _given
from .wire import (ERROR_NAMES, ConnectionLost, Frame, Inbox, InboxViews, VolfxError,
                   attachment_need, encode_line, error_of, holders, is_notification, parse_line,
                   request)

__all__ = ["Client", "AsyncClient", "Batch", "BatchReply", "Frame", "VolfxError",
           "ConnectionLost", "METHODS", "ERROR_NAMES", "main"]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7878

# Messages one drain reads at most, so that a fast stream cannot keep latest() from returning.
DRAIN_MAX = 1024


class Client(InboxViews, Methods):
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
        self.inbox = Inbox()
        self._discovered = None
        if token:
            self.call("auth", token=token)

    # -- context manager -------------------------------------------------------------------

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def close(self):
        """Closes the socket; unread frames and notifications are discarded."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self.inbox.clear()

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

    def _read_message(self):
        """Reads one message and its attachments: ``(message, bytes or None)``, or for a batch
        response ``(array, [bytes or None per response])``."""
        while True:
            line = self._readline()
            if line.strip():
                break
        msg = parse_line(line)
        datas = []
        for holder in holders(msg):
            need = attachment_need(holder)
            datas.append(self._readexact(need) if isinstance(need, int) else need)
        if isinstance(msg, list):
            return msg, datas
        return msg, (datas[0] if datas else None)

    def _send(self, value):
        try:
            self._sock.sendall(encode_line(value))
        except socket.timeout:
            raise ConnectionLost("timed out sending to the server") from None
        except OSError as e:
            raise ConnectionLost(str(e)) from None

    def _await_answer(self, is_ours):
        """Reads until the response ``is_ours`` accepts; notifications met go to the inbox."""
        while True:
            msg, data = self._read_message()
            if is_notification(msg):
                self.inbox.put(msg, data)
            elif is_ours(msg):
                return msg, data

    # -- calls -----------------------------------------------------------------------------

    def call_raw(self, method, params=None):
        """Sends one request and returns ``(result, attachment bytes or None)``.

        ``params`` is a dict (or list), or None for none. Raises ``VolfxError`` for an error
        response. Frames and notifications that arrive first are kept in ``inbox``.
        """
        rid = self._next_id
        self._next_id += 1
        self._send(request(rid, method, params))
        msg, data = self._await_answer(
            lambda m: isinstance(m, dict) and (m.get("id") == rid
                                               or (m.get("id") is None and "error" in m)))
        err = error_of(msg)
        if err is not None:
            raise err
        return msg.get("result"), data

    def call(self, method, **params):
        """Calls ``method`` with keyword params and returns the result (attachment dropped)."""
        return self.call_raw(method, params)[0]

    def _request(self, method, params, post=None, raw=False):
        result, data = self.call_raw(method, params)
        value = (result, data) if raw else result
        return post(value) if post else value

    def batch(self):
        """A ``Batch``: add calls with the wrappers (each returns its index), then ``send()``
        them as one line and get one ``BatchReply`` per call."""
        return Batch(self)

    def _send_batch(self, batch):
        ids, reqs = batch._ids_and_line(self._next_id)
        self._next_id = ids[-1] + 1
        self._send(reqs)
        msg, datas = self._await_answer(
            lambda m: isinstance(m, list) or (isinstance(m, dict) and m.get("id") is None
                                              and "error" in m))
        return batch._replies(ids, msg, datas if isinstance(msg, list) else [])

    def defaults(self, method):
        """``{param: default}`` of ``method`` from the server's rpc.discover (read once): the
        values its params take when left out."""
        if self._discovered is None:
            self._discovered = self.discover()
        for m in self._discovered.get("methods", []):
            if m.get("name") == method:
                return {p["name"]: p["schema"]["default"] for p in m.get("params", [])
                        if "default" in (p.get("schema") or {})}
        raise ValueError("the server has no method %r" % method)

    # -- frames and notifications ----------------------------------------------------------

    def _pump(self, wait):
        """Reads what has arrived (all of it, at most DRAIN_MAX messages), waiting up to
        ``wait`` seconds (None: forever) for the first. Returns whether anything came."""
        got = False
        for _ in range(DRAIN_MAX):
            # Wait for the start of a message with select, so that a quiet stream returns
            # instead of raising, while a message once started is read whole.
            if not self._buf:
                ready, _, _ = select.select([self._sock], [], [], 0 if got else wait)
                if not ready:
                    break
            msg, data = self._read_message()
            if is_notification(msg):
                self.inbox.put(msg, data)
                got = True
        return got

    def _wait_for(self, take, timeout):
        """Drains the socket, then returns ``take()`` once it is not None, or None when
        nothing came for ``timeout`` seconds (None: the client's timeout)."""
        wait = self.timeout if timeout is None else timeout
        deadline = None if wait is None else time.monotonic() + wait
        self._pump(0)
        while True:
            item = take()
            if item is not None:
                return item
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            self._pump(left)

    def latest(self, sid, timeout=0):
        """The newest unread ``Frame`` of subscription ``sid``, after reading everything that
        has arrived; waits up to ``timeout`` seconds (None: the client's timeout) when there is
        none. None when none came, or when the subscription has ended (see ``ended``)."""
        return self._wait_for(
            lambda: self.inbox.take_frame(sid) or (False if sid in self.inbox.ended else None),
            timeout) or None

    def _each(self, take, timeout, count):
        got = 0
        while count is None or got < count:
            item = self._wait_for(take, timeout)
            if item is None:
                return
            got += 1
            yield item

    def frames(self, timeout=None, count=None, sid=None):
        """Yields the newest unread ``Frame`` (``params, data``) of ``sid`` (of any
        subscription when None) each time one is there, after reading everything that has
        arrived. Stops after ``count``, or when none came for ``timeout`` seconds (None: the
        client's timeout)."""
        return self._each(lambda: self.inbox.take_frame(sid), timeout, count)

    def notifications(self, method=None, timeout=None, count=None):
        """Yields ``(method, params, bytes)`` for notifications (of ``method`` when given):
        ``job.progress``, ``frames.ended``, and the newest waiting frame of each subscription.
        Stops after ``count``, or when none came for ``timeout`` seconds (None: the client's
        timeout)."""
        return self._each(lambda: self.inbox.take(method), timeout, count)


def __getattr__(name):
    # AsyncClient lives in volfx.aio, imported on first use so that the blocking client does
    # not load asyncio.
    if name == "AsyncClient":
        from .aio import AsyncClient
        return AsyncClient
    raise AttributeError("module 'volfx' has no attribute %r" % name)


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
    p = _given(scene=a.scene)
    for key in ("width", "height", "format", "aov", "fps", "encoding"):
        v = getattr(a, key, None)
        if v is not None:
            p[key] = v
    if getattr(a, "layers", None):
        p["layers"] = [x for x in a.layers.split(",") if x]
    if getattr(a, "camera", None):
        try:
            p["camera"] = json.loads(a.camera)
        except ValueError as e:
            raise SystemExit("volfx: --camera needs a JSON object: %s" % e)
    if p.get("aov") not in (None, "beauty") and "format" not in p:
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
    ap = argparse.ArgumentParser(
        prog="volfx", description="A small command line over the Python client of volfxd; "
        "the C volfx has the full set (script, sequence, the render-farm commands).")
    ap.add_argument("--host", default=DEFAULT_HOST)
    ap.add_argument("--port", type=int, default=DEFAULT_PORT)
    ap.add_argument("--unix")
    ap.add_argument("--token", default=os.environ.get("VOLFX_TOKEN"))
    ap.add_argument("--scene", help="the scene (default: the server's default scene)")
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
        s.add_argument("--camera", help="JSON members of the scene camera for these frames")
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
