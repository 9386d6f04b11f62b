#!/usr/bin/env python3
"""
Sends malformed and hostile input to a real volfxd. After each case the same server must
still answer server.info on a fresh connection, and the scenes must show nothing half-applied.

    python3 tests/integration/test_bad_input.py --bin build/bin
"""

import os
import random
import socket
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import (E_INVALID_REQUEST, E_LIMIT, E_METHOD, E_NOT_FOUND, E_PARAMS,  # noqa: E402
                  E_PARSE, expect_error, short)

suite = mock.Suite("test_bad_input", timeout_s=400)
suite.server_args = []
T = suite.test

BASE = {}


def req(method, params=None, id=1):
    m = {"jsonrpc": "2.0", "method": method, "id": id}
    if params is not None:
        m["params"] = params
    return mock.dumps(m).encode()


def snapshot(c):
    return {name: c.ok("scene.get", {"scene": name})[0] for name in ("main", "bad")}, \
        {x["name"]: x.get("version") for x in c.ok("scene.list", {})[0]["scenes"]}


def verify(s, label):
    """The server answers on a fresh connection and the scenes are exactly as before."""
    if not s.check(s.srv.alive(), "server alive after %s" % label):
        raise mock.CheckError("the server died after %s" % label)
    with s.srv.connect(timeout=15) as c:
        r, _ = c.ok("server.info", {})
        s.eq(r.get("name"), "volfxd", "server.info on a fresh connection after %s" % label)
        docs, versions = snapshot(c)
        s.check(docs == BASE["docs"], "scenes unchanged after %s" % label)
        s.eq(versions, BASE["versions"], "scene versions unchanged after %s" % label)


def same_conn_ok(s, c, label):
    try:
        r, _ = c.call("server.info", {}, id="alive")
    except (mock.Closed, OSError) as e:
        raise mock.CheckError("the same connection still works after %s: %s" % (label, e))
    s.check(r.get("result", {}).get("name") == "volfxd",
            "the same connection still works after %s" % label, short(r))


@T
def setup(s):
    with s.srv.connect(timeout=10) as c:
        c.ok("scene.create", {"name": "bad", "preset": "demo"})
        BASE["docs"], BASE["versions"] = snapshot(c)


@T
def parse_errors(s):
    c = s.srv.connect(timeout=10)
    lines = [b"{", b"}", b"{this is not json", b'{"jsonrpc":"2.0",}', b"nul", b"tru",
             b'{"jsonrpc":"2.0","method":"server.info","id":1',
             b'"unterminated', b"\x00", b"{'jsonrpc':'2.0'}", b"[1,]", b"{\"a\" 1}",
             b'{"jsonrpc":"2.0","method":"server.info","id":01}',
             b'{"jsonrpc":"2.0","method":"server.info","id":1} xyz',
             b'{"jsonrpc":"2.0","method":"server.info","id":1}{"b":2}',
             b'{"jsonrpc":"2.0","method":"server.info","id":1,"params":{"x":"\x01"}}',
             b'{"jsonrpc":"2.0","method":"server.info","id":1,"params":{"x":"\\q"}}',
             b'{"jsonrpc":"2.0","method":"server.info","id":1,"params":{"x":"\\u12"}}']
    for ln in lines:
        m = expect_error(s, c, None, None, E_PARSE, None, "parse error %s" % short(ln, 60),
                         raw=ln + b"\n")
        s.eq(m.get("id", "missing"), None, "parse error %s answered with id null" % short(ln, 60))
        same_conn_ok(s, c, "parse error %s" % short(ln, 60))
    verify(s, "parse errors")


def _send_bg(sock, data):
    def run():
        try:
            sock.sendall(data)
        except OSError:
            pass
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def _oversize(s, data, label):
    c = s.srv.connect(timeout=20)
    t = _send_bg(c.sock, data)
    try:
        m, _ = c.recv_response(timeout=20)
        s.check(isinstance(m, dict) and m.get("error", {}).get("code") == E_LIMIT and
                "id" in m and m["id"] is None,
                "%s -> one -32003 error with id null" % label, short(m))
        s.check(c.expect_eof(timeout=10), "%s: the connection is closed after the error" % label)
    except mock.Closed as e:
        s.fail("%s -> one -32003 error before the connection closes" % label,
               "%s (no error line was readable)" % e)
    except socket.timeout as e:
        s.fail("%s -> an answer within 20 s" % label, str(e))
    t.join(5)
    c.close()


@T
def oversize_line(s):
    _oversize(s, b"x" * (2 << 20), "2 MiB without a newline")
    verify(s, "an oversize line")
    # Exactly at the limit (1 MiB without the '\n') is accepted; one byte more is not.
    limit = 1 << 20
    head = b'{"jsonrpc":"2.0","method":"no.such","id":9,"params":{"pad":"'
    tail = b'"}}'
    line = head + b"p" * (limit - len(head) - len(tail)) + tail
    assert len(line) == limit
    c = s.srv.connect(timeout=20)
    m = expect_error(s, c, None, None, E_METHOD, None, "a request line of exactly 1 MiB",
                     raw=line + b"\n")
    s.eq(m.get("id"), 9, "the 1 MiB request is answered with its id")
    same_conn_ok(s, c, "a 1 MiB line")
    c.close()
    line = head + b"p" * (limit + 1 - len(head) - len(tail)) + tail
    _oversize(s, line + b"\n", "a request line of 1 MiB + 1 byte")
    verify(s, "a line of 1 MiB + 1")


@T
def deep_nesting(s):
    c = s.srv.connect(timeout=20)
    cases = [(b"[" * 100 + b"]" * 100, "100 levels of ["),
             (b'{"jsonrpc":"2.0","method":"server.info","id":1,"params":{"a":' +
              b"[" * 100 + b"]" * 100 + b"}}", "100 levels inside params"),
             (b'{"jsonrpc":"2.0","method":"scene.set","id":1,"params":{"scene":"bad","patch":' +
              b'{"a":' * 100 + b"1" + b"}" * 100 + b"}}", "100 nested objects in a patch"),
             (b"[" * 500000, "500000 unclosed ["),
             (b'{"a":' * 150000, "150000 unclosed objects")]
    for data, label in cases:
        m = expect_error(s, c, None, None, E_PARSE, None, label, raw=data + b"\n")
        s.eq(m.get("id", "missing"), None, "%s answered with id null" % label)
        same_conn_ok(s, c, label)
    # Strings may hold brackets: they do not count as nesting.
    p = {"scene": "bad", "path": "[" * 200}
    expect_error(s, c, "scene.get", p, E_NOT_FOUND, "path", "brackets inside a string")
    verify(s, "deep nesting")


@T
def invalid_utf8(s):
    c = s.srv.connect(timeout=10)
    for bad, label in ((b"\xff\xfe", "0xff 0xfe"), (b"\xc0\xaf", "overlong '/'"),
                       (b"\xed\xa0\x80", "UTF-16 surrogate"), (b"\xe2\x82", "truncated sequence"),
                       (b"\xf4\x90\x80\x80", "above U+10FFFF"), (b"\x80", "lone continuation"),
                       (b"\xf8\x88\x80\x80\x80", "5-byte sequence")):
        line = b'{"jsonrpc":"2.0","method":"scene.set","id":1,"params":{"scene":"bad","patch":' \
               b'{"objects":[{"shape":"box","id":"' + bad + b'"}]}}}\n'
        expect_error(s, c, None, None, E_PARSE, None, "invalid UTF-8 in a string: %s" % label,
                     raw=line)
        line = b'{"jsonrpc":"2.0","method":"server.info' + bad + b'","id":1}\n'
        expect_error(s, c, None, None, E_PARSE, None, "invalid UTF-8 in the method: %s" % label,
                     raw=line)
    same_conn_ok(s, c, "invalid UTF-8")
    # An escaped lone surrogate is JSON syntax but no character: any error, no crash.
    c.send_raw(b'{"jsonrpc":"2.0","method":"scene.get","id":2,"params":{"scene":"\\ud800"}}\n')
    m, _ = c.recv_response()
    s.check("error" in m, "escaped lone surrogate in a scene name -> an error", short(m))
    verify(s, "invalid UTF-8")


@T
def binary_garbage(s):
    rnd = random.Random(1234)
    c = s.srv.connect(timeout=20)
    for round_ in range(4):
        chunk = bytearray()
        for _ in range(40):
            line = bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 200)))
            chunk += line.replace(b"\n", b"?") + b"\n"
        c.send_raw(bytes(chunk))
        c.send_raw(req("server.info", {}, id="sentinel-%d" % round_) + b"\n")
        answers = 0
        while True:
            m, _ = c.recv_response(timeout=20)
            if isinstance(m, dict) and m.get("id") == "sentinel-%d" % round_:
                s.check("result" in m, "request after garbage round %d answered" % round_,
                        short(m))
                break
            answers += 1
            ok = (isinstance(m, dict) and "error" in m) or \
                 (isinstance(m, list) and all("error" in x for x in m))
            s.check(ok, "garbage lines get only errors", short(m))
        s.check(answers <= 40 + 1, "at most one answer per garbage line", answers)
    verify(s, "binary garbage")


@T
def not_objects(s):
    c = s.srv.connect(timeout=10)
    for text in (b"42", b'"x"', b"[]", b"null", b"true", b"3.5", b"{}",
                 b'{"jsonrpc":"2.0"}', b'{"jsonrpc":2.0,"method":"server.info","id":1}',
                 b'{"jsonrpc":"2.0","method":null,"id":1}'):
        m = expect_error(s, c, None, None, E_INVALID_REQUEST, None, "not a request: %s" %
                         text.decode(), raw=text + b"\n")
        s.check(isinstance(m, dict), "not a request %s -> one error object, not an array" %
                text.decode(), short(m))
    c.send_raw(b"[42, \"x\"]\n")
    m, _ = c.recv_response()
    s.check(isinstance(m, list) and len(m) == 2 and
            all(x.get("error", {}).get("code") == E_INVALID_REQUEST for x in m),
            "batch [42, \"x\"] -> two -32600 errors", short(m))
    same_conn_ok(s, c, "non-objects")
    verify(s, "JSON that is not a request")


@T
def nan_infinity(s):
    c = s.srv.connect(timeout=10)
    for lit in (b"NaN", b"Infinity", b"-Infinity", b"nan", b"inf", b"-inf"):
        line = b'{"jsonrpc":"2.0","method":"scene.set","id":3,"params":{"scene":"bad",' \
               b'"path":"camera.fov_y","value":' + lit + b"}}\n"
        expect_error(s, c, None, None, E_PARSE, None, "literal %s" % lit.decode(), raw=line)
        line = b'{"jsonrpc":"2.0","method":"render","id":4,"params":{"scene":"bad",' \
               b'"width":' + lit + b"}}\n"
        expect_error(s, c, None, None, E_PARSE, None, "render width %s" % lit.decode(), raw=line)
    same_conn_ok(s, c, "NaN/Infinity")
    verify(s, "NaN/Infinity literals")


@T
def out_of_range_numbers(s):
    c = s.srv.connect(timeout=10)
    cases = [
        ("scene.set", {"scene": "bad", "path": "camera.fov_y", "value": 1e308}, E_PARAMS,
         "camera.fov_y"),
        ("scene.set", {"scene": "bad", "patch": {"camera": {"fov_y": 1e308}}}, E_PARAMS,
         "camera.fov_y"),
        ("scene.set", {"scene": "bad", "patch": {"camera": {"fov_y": -1e-300}}}, E_PARAMS,
         "camera.fov_y"),
        ("render", {"scene": "bad", "width": -1, "height": 8}, E_PARAMS, "width"),
        ("render", {"scene": "bad", "width": 1.5, "height": 8}, E_PARAMS, "width"),
        ("render", {"scene": "bad", "width": 8, "height": 0}, E_PARAMS, "height"),
        ("render", {"scene": "bad", "width": 8, "height": 8, "png_level": 1e10}, E_PARAMS,
         "png_level"),
        ("sim.step", {"scene": "bad", "steps": 0}, E_PARAMS, "steps"),
        ("sim.step", {"scene": "bad", "steps": 4294967297}, E_PARAMS, "steps"),
        ("sim.step", {"scene": "bad", "steps": -4294967295}, E_PARAMS, "steps"),
        ("sim.step", {"scene": "bad", "steps": 1e300}, E_PARAMS, "steps"),
        ("sim.step", {"scene": "bad", "steps": 1, "dt": 1e-400}, E_PARAMS, "dt"),
        ("frames.subscribe", {"scene": "bad", "fps": 1e-300 * 0}, E_PARAMS, "fps"),
    ]
    for method, params, code, path in cases:
        expect_error(s, c, method, params, code, path, "%s %s" % (method, short(params, 120)))
    # 1e400 overflows a double: refused as not finite (-32602) or not JSON (-32700).
    for line, label in (
            (b'{"jsonrpc":"2.0","method":"scene.set","id":5,"params":{"scene":"bad",'
             b'"path":"camera.fov_y","value":1e400}}', "fov_y 1e400"),
            (b'{"jsonrpc":"2.0","method":"render","id":6,"params":{"scene":"bad",'
             b'"width":-1e400}}', "width -1e400"),
            (b'{"jsonrpc":"2.0","method":"sim.step","id":7,"params":{"scene":"bad",'
             b'"steps":1,"dt":1e400}}', "dt 1e400")):
        c.send_raw(line + b"\n")
        m, _ = c.recv_response()
        s.check(m.get("error", {}).get("code") in (E_PARAMS, E_PARSE),
                "%s -> -32602 or -32700" % label, short(m))
    same_conn_ok(s, c, "out-of-range numbers")
    verify(s, "out-of-range numbers")


@T
def huge_frames(s):
    c = s.srv.connect(timeout=10)
    for params, path in (({"width": 100000, "height": 8}, "width"),
                         ({"width": 8, "height": 100000}, "height"),
                         ({"width": 4097, "height": 4097}, "width"),
                         ({"width": 4294967296 + 64, "height": 64}, "width"),
                         ({"width": 1e20, "height": 64}, "width")):
        expect_error(s, c, "render", dict(params, scene="bad"), E_LIMIT, path,
                     "render %s" % short(params))
    expect_error(s, c, "frames.subscribe", {"scene": "bad", "width": 8, "height": 65536},
                 E_LIMIT, "height", "frames.subscribe height 65536")
    same_conn_ok(s, c, "huge frames")
    verify(s, "huge frames")


@T
def unknown_scene_and_method(s):
    c = s.srv.connect(timeout=10)
    for method, params in (("render", {"scene": "nope", "width": 8, "height": 8}),
                           ("scene.get", {"scene": "nope"}),
                           ("scene.set", {"scene": "nope", "patch": {}}),
                           ("sim.step", {"scene": "nope"}),
                           ("sim.play", {"scene": "nope"}),
                           ("frames.subscribe", {"scene": "nope"})):
        expect_error(s, c, method, params, E_NOT_FOUND, "scene", "%s unknown scene" % method)
    # A NUL escape would truncate a name in C ("main\u0000" reading as "main"): protocol.md
    # refuses any line holding \u0000 as a parse error, so nothing can match by accident.
    for method, params in (("scene.get", {"scene": "bad\u0000x"}),
                           ("scene.set", {"scene": "main\u0000", "path": "camera.fov_y",
                                          "value": 44}),
                           ("scene.delete", {"name": "bad\u0000"}),
                           ("server.info\u0000", {})):
        line = mock.dumps({"jsonrpc": "2.0", "method": method, "params": params,
                           "id": 7}).encode() + b"\n"
        expect_error(s, c, None, None, E_PARSE, None,
                     "%r with a NUL in a string -> parse error" % method, raw=line)
    for name in ("no.such", "", "server.info ", "SERVER.INFO", "x" * 10000,
                 "rpc.", "render\n"):
        expect_error(s, c, name, {}, E_METHOD, None, "unknown method %s" % short(name, 40))
    for params in (5, True, "x", None):
        line = b'{"jsonrpc":"2.0","method":"server.info","id":11,"params":' + \
            mock.dumps(params).encode() + b"}\n"
        m = expect_error(s, c, None, None, E_INVALID_REQUEST, None, "params %r" % (params,),
                         raw=line)
        s.eq(m.get("id"), 11, "params %r: the error echoes the id" % (params,))
    same_conn_ok(s, c, "unknown names")
    verify(s, "unknown scenes and methods")


@T
def quoted_names_cut_short(s):
    """Errors quote what the client sent, cut to a length limit; a cut that falls inside a
    character must not make the answer invalid UTF-8 (the mock refuses such a line)."""
    c = s.srv.connect(timeout=10)
    for n in range(28, 36):
        for ch in ("\u00e9", "\u20ac", "\U0001F600"):
            name = "a" + ch * n
            expect_error(s, c, "scene.save", {"file": name}, E_PARAMS, "file",
                         "scene.save of a long non-ASCII name (%d x U+%04X)" % (n, ord(ch)))
            expect_error(s, c, "scene.get", {"scene": name * 4}, (E_PARAMS, E_NOT_FOUND),
                         "scene", "scene.get of a long non-ASCII scene name")
    same_conn_ok(s, c, "names cut short")
    verify(s, "names cut short")


@T
def partial_patch(s):
    c = s.srv.connect(timeout=10)
    fov0 = c.ok("scene.get", {"scene": "bad", "path": "camera.fov_y"})[0]
    good = 41.25 if fov0 != 41.25 else 42.5
    for patch, path in (
            ({"camera": {"fov_y": good}, "objects": [{"shape": "nope"}]}, "objects.0.shape"),
            ({"objects": [{"shape": "nope"}], "camera": {"fov_y": good}}, "objects.0.shape"),
            ({"camera": {"fov_y": good, "near": -1}}, "camera.near"),
            ({"background": [0.1, "x", 0], "camera": {"fov_y": good}}, "background.1"),
            ({"camera": {"fov_y": good}, "sim": {"playing": "yes"}}, "sim.playing"),
            ({"camera": {"fov_y": good}, "light": {"direction": [0, 0, 0]}},
             "light.direction")):
        m = expect_error(s, c, "scene.set", {"scene": "bad", "patch": patch}, E_PARAMS, None,
                         "patch %s" % short(patch, 100))
        got = ((m.get("error") or {}).get("data") or {}).get("path")
        ok = got == path or (path == "background.1" and got == "background")
        s.check(ok, "patch %s -> data.path %s" % (short(patch, 100), path), short(m))
        s.eq(c.ok("scene.get", {"scene": "bad", "path": "camera.fov_y"})[0], fov0,
             "the good field of a refused patch is not applied (%s)" % short(patch, 80))
    verify(s, "a half-good patch")


@T
def odd_but_valid(s):
    c = s.srv.connect(timeout=10)
    # Blank lines (nothing, or only spaces and tabs) are skipped: no answer at all.
    c.send_raw(b"\n\r\n   \n\t \r\n")
    c.send_raw(req("server.info", {}, id="after-empty") + b"\n")
    m, _ = c.recv_response()
    s.eq(m.get("id"), "after-empty", "blank lines get no answer; the next request is answered")
    s.check("result" in m, "request after blank lines answered", short(m))
    # Duplicate keys: any answer, no crash.
    c.send_raw(b'{"jsonrpc":"2.0","method":"server.info","method":"nope","id":12}\n')
    m, _ = c.recv_response()
    s.eq(m.get("id"), 12, "duplicate keys: answered")
    # A request split across many writes, byte by byte.
    data = req("scene.get", {"scene": "bad", "path": "camera.fov_y"}, id=13) + b"\n"
    for i in range(len(data)):
        c.send_raw(data[i:i + 1])
        if i % 16 == 0:
            time.sleep(0.001)
    m, _ = c.recv_response()
    s.check(m.get("id") == 13 and "result" in m, "a request sent byte by byte", short(m))
    # A client that vanishes mid-line, and one that vanishes mid-render.
    c2 = s.srv.connect(timeout=10)
    c2.send_raw(b'{"jsonrpc":"2.0","method":"rend')
    c2.close()
    c3 = s.srv.connect(timeout=10)
    c3.send_raw(req("render", {"scene": "bad", "width": 512, "height": 512}, id=1) + b"\n")
    c3.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    c3.close()  # RST
    same_conn_ok(s, c, "vanishing clients")
    verify(s, "odd but valid input")


if __name__ == "__main__":
    sys.exit(suite.main())
