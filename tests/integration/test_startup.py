#!/usr/bin/env python3
"""
volfxd's command line, config file and life cycle: refusing a non-loopback address without a
token, --help/--version, bad options, a config file's limits, a missing main scene, the Unix
socket, the readiness a parent waits on (--port-file, --ready-fd), and a graceful stop on
SIGINT and SIGTERM.

    python3 tests/integration/test_startup.py --bin build/bin
"""

import json
import os
import signal
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_startup", timeout_s=300)
T = suite.test


def run(s, *args, timeout=60, env=None):
    """Runs volfxd to completion; returns (exit status, stdout, stderr)."""
    e = dict(os.environ)
    e.pop("VOLFX_TOKEN", None)
    if env:
        e.update(env)
    p = subprocess.run([os.path.join(s.bin, "volfxd")] + list(args), capture_output=True,
                       timeout=timeout, env=e)
    return p.returncode, p.stdout.decode(), p.stderr.decode()


@T
def command_line(s):
    rc, out, _ = run(s, "--help")
    s.eq(rc, 0, "--help exits 0")
    for flag in ("--listen", "--unix", "--data", "--token", "--insecure", "--device", "--kernels",
                 "--scene", "--config", "--log-level", "--version"):
        s.check(flag in out, "--help names %s" % flag, out[:200])
    rc, out, _ = run(s, "--version")
    s.check(rc == 0 and out.startswith("volfxd "), "--version prints the version", out)
    for bad in (["--no-such-flag"], ["--listen", "nohostport"], ["--listen", "127.0.0.1:70000"],
                ["--log-level", "loud"], ["--idle-timeout", "-1"], ["stray"]):
        rc, _, err = run(s, *bad)
        s.check(rc == 2 and err.startswith("volfxd: "), "bad command line %r refused" % bad,
                "rc %d: %s" % (rc, err[:200]))


@T
def loopback_only_without_token(s):
    rc, _, err = run(s, "--listen", "0.0.0.0:0")
    s.check(rc == 2 and "token" in err, "0.0.0.0 without a token is refused", err[:200])
    for extra in (["--token", "secret"], ["--insecure"]):
        srv = mock.Server(s.bin, *extra, listen="0.0.0.0:0")
        with srv:
            c = mock.Conn("127.0.0.1", srv.port)
            if extra[0] == "--token":
                mock.expect_error(s, c, "server.info", {}, mock.E_UNAUTHORIZED, None,
                                  "non-loopback server without auth")
                c.ok("auth", {"token": "secret"})
            s.eq(c.ok("server.info", {})[0]["name"], "volfxd",
                 "0.0.0.0 with %s serves" % extra[0])
            c.close()


@T
def config_file(s):
    d = tempfile.mkdtemp(prefix="volfx-cfg-")
    path = os.path.join(d, "volfxd.json")
    with open(path, "w") as f:
        json.dump({"idle-timeout": 42, "limits": {"frame_side": 640, "render_queue": 5}}, f)
    with mock.Server(s.bin, "--config", path) as srv:
        c = srv.connect()
        lim = c.ok("server.info", {})[0]["limits"]
        s.eq((lim["frame_side"], lim["render_queue"], lim["idle_timeout_s"]), (640, 5, 42),
             "limits from the config file")
        mock.expect_error(s, c, "render", {"width": 641, "height": 8}, mock.E_LIMIT, "width",
                          "the configured frame limit applies")
        c.close()
    for text in ("not json", json.dumps({"limits": {"frame_side": 0}}),
                 json.dumps({"no_such_member": 1})):
        with open(path, "w") as f:
            f.write(text)
        rc, _, err = run(s, "--config", path)
        s.check(rc == 2 and "config" in err, "bad config %r refused" % text[:40], err[:200])


@T
def missing_scene_and_unix_socket(s):
    rc, _, err = run(s, "--listen", "127.0.0.1:0", "--scene", "no-such-preset")
    s.check(rc == 1 and "no-such-preset" in err, "a missing main scene stops the start",
            err[-300:])
    sock = os.path.join(tempfile.mkdtemp(prefix="volfx-sock-"), "v.sock")
    with mock.Server(s.bin, "--unix", sock) as srv:
        import socket
        u = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        u.settimeout(30)
        u.connect(sock)
        u.sendall(b'{"jsonrpc":"2.0","id":1,"method":"server.info"}\n')
        data = b""
        while not data.endswith(b"\n"):
            data += u.recv(65536)
        s.eq(json.loads(data)["result"]["name"], "volfxd", "served over the Unix socket")
        u.close()
        del srv
    s.check(not os.path.exists(sock), "the socket file is removed at exit", sock)


@T
def graceful_signals(s):
    for sig in (signal.SIGINT, signal.SIGTERM):
        srv = mock.Server(s.bin)
        srv.start()
        c = srv.connect()
        # A render in flight when the signal arrives is still answered. The frame is large
        # enough to be rendering still when the signal comes, a moment after the request.
        c.send(c.request("render", {"width": 2048, "height": 2048}))
        time.sleep(0.02)
        srv.proc.send_signal(sig)
        resp, att = c.recv_response(timeout=60)
        s.check("result" in resp or resp.get("error", {}).get("code") == mock.E_BUSY,
                "a render in flight at %s is answered" % sig.name, mock.short(resp))
        s.eq(srv.proc.wait(60), 0, "exit status after %s" % sig.name)
        srv.stop()


@T
def port_file_and_ready_fd(s):
    d = tempfile.mkdtemp(prefix="volfx-ready-")
    port_file = os.path.join(d, "port")
    rfd, wfd = os.pipe()
    try:
        srv = mock.Server(s.bin, "--port-file", port_file, "--ready-fd", str(wfd))
        srv.popen_kw = {"pass_fds": (wfd,)}
        with srv:
            os.close(wfd)
            wfd = -1
            line = os.read(rfd, 4096).decode()
            s.eq(line, "ready %d %s\n" % (srv.port, srv.host), "--ready-fd gets one line")
            s.eq(os.read(rfd, 4096), b"", "and is closed after it")
            with open(port_file) as f:
                s.eq(f.read(), "%d\n%s\n" % (srv.port, srv.host), "the port file's contents")
            s.eq(sorted(os.listdir(d)), ["port"], "no temporary file is left beside it")
        s.check(not os.path.exists(port_file), "the port file is removed at exit", port_file)
    finally:
        os.close(rfd)
        if wfd >= 0:
            os.close(wfd)
    # The config file's member of the same name.
    cfg = os.path.join(d, "volfxd.json")
    with open(cfg, "w") as f:
        json.dump({"port-file": port_file}, f)
    with mock.Server(s.bin, "--config", cfg) as srv:
        with open(port_file) as f:
            s.eq(f.read().split(), [str(srv.port), srv.host], "port-file in the config file")
    # A place volfxd cannot write fails the start at once, naming the path and the cause.
    for bad, cause in ((os.path.join(d, "missing", "port"), "No such file or directory"),
                       (d, "is a directory")):
        rc, _, err = run(s, "--listen", "127.0.0.1:0", "--port-file", bad)
        s.check(rc != 0 and bad in err and cause in err and "listening" not in err,
                "an unwritable port file %s is a start-up error" % bad, "rc %d: %s" % (rc, err))
    rc, _, err = run(s, "--listen", "127.0.0.1:0", "--ready-fd", "97")
    s.check(rc != 0 and "--ready-fd 97" in err, "a ready descriptor that is not open is refused",
            "rc %d: %s" % (rc, err))
    rc, _, err = run(s, "--ready-fd", "x")
    s.check(rc == 2 and "--ready-fd" in err, "--ready-fd wants a number", err)


if __name__ == "__main__":
    sys.exit(suite.main())
