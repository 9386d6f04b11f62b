#!/usr/bin/env python3
"""Integration test of the clients: starts a real volfxd on a free port and drives it with the
C CLI (bin/volfx) and the Python client (the package client/python/volfx).

Run from the repository root: python3 tests/integration/test_client.py --bin build/bin
Exits 0 when every check passed; prints the first failure and exits 1 otherwise. A watchdog
kills everything after TOTAL_TIMEOUT seconds so the test never hangs.
"""

import argparse
import json
import os
import re
import struct
import subprocess
import sys
import tempfile
import threading
import time

TOTAL_TIMEOUT = 300  # seconds for the whole test
CALL_TIMEOUT = 120   # seconds for one CLI invocation
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

SERVERS = []  # every volfxd started, so that the watchdog can kill them all

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


class Failure(Exception):
    pass


def check(cond, what):
    if not cond:
        raise Failure(what)


def png_size(data):
    """(width, height) from a PNG's IHDR, after checking the signature and the chunk."""
    check(data[:8] == PNG_SIGNATURE, "not a PNG: starts with %r" % data[:8])
    check(len(data) >= 33, "PNG too short (%d bytes)" % len(data))
    length, kind = struct.unpack(">I4s", data[8:16])
    check(kind == b"IHDR" and length == 13, "first PNG chunk is %r/%d, not IHDR/13" % (kind, length))
    return struct.unpack(">II", data[16:24])


class Server:
    """A volfxd child process on 127.0.0.1 with a free port and a temporary data directory."""

    def __init__(self, bindir, datadir, extra=()):
        self.log_path = os.path.join(datadir, "volfxd.log")
        self.log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            [os.path.join(bindir, "volfxd"), "--listen", "127.0.0.1:0", "--data", datadir]
            + list(extra), stdout=subprocess.PIPE, stderr=self.log, cwd=ROOT)
        SERVERS.append(self)
        self.port = None
        found = threading.Event()

        def reader():
            # Parses the "listening" line, then keeps draining stdout so the server never
            # blocks on a full pipe.
            for raw in self.proc.stdout:
                line = raw.decode("utf-8", "replace").strip()
                m = re.match(r"volfxd listening on (\S+):(\d+)$", line)
                if m and self.port is None:
                    self.port = int(m.group(2))
                    found.set()
            found.set()

        threading.Thread(target=reader, daemon=True).start()
        found.wait(60)
        if self.port is None:
            self.stop()
            raise Failure("volfxd did not print 'volfxd listening on HOST:PORT' (log: %s)"
                          % self.tail())

    def tail(self):
        try:
            with open(self.log_path, "rb") as f:
                return f.read()[-2000:].decode("utf-8", "replace")
        except OSError:
            return ""

    def stop(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


class Cli:
    """Runs bin/volfx against the server."""

    def __init__(self, bindir, port, workdir, conn=None):
        self.exe = os.path.join(bindir, "volfx")
        self.conn = conn if conn is not None else ["--port", str(port)]
        self.workdir = workdir

    def run(self, *args, ok=True, env=None):
        cmd = [self.exe] + self.conn + list(args)
        environ = dict(os.environ)
        environ.pop("VOLFX_TOKEN", None)
        environ.update(env or {})
        p = subprocess.run(cmd, capture_output=True, timeout=CALL_TIMEOUT, cwd=self.workdir,
                           env=environ)
        out = p.stdout.decode("utf-8", "replace")
        err = p.stderr.decode("utf-8", "replace")
        if ok:
            check(p.returncode == 0, "`volfx %s` exited %d: %s" % (" ".join(args), p.returncode,
                                                                  err.strip()))
        return p.returncode, out, err

    def json(self, *args):
        _, out, _ = self.run(*args)
        try:
            return json.loads(out)
        except ValueError:
            raise Failure("`volfx %s` printed no JSON: %r" % (" ".join(args), out[:300]))


def test_cli(cli, work):
    info = cli.json("info")
    check(info.get("name") == "volfxd", "info.name is %r" % info.get("name"))
    check(info.get("protocol") == "1", "info.protocol is %r" % info.get("protocol"))
    check("merge patch" in cli.run("--help")[1], "--help does not document the set rule")

    fov = cli.json("get", "camera.fov_y")
    check(isinstance(fov, (int, float)), "get camera.fov_y printed %r" % fov)
    cli.run("set", "camera.fov_y=50")
    check(cli.json("get", "camera.fov_y") == 50, "fov_y is not 50 after set")
    # Numbers go both ways with every digit they need.
    cli.run("set", "sim.seed=9007199254740991", "render.exposure=0.30000000000000004")
    check(cli.run("get", "sim.seed")[1].strip() == "9007199254740991",
          "get sim.seed printed %r" % cli.run("get", "sim.seed")[1])
    check(cli.json("get", "render.exposure") == 0.30000000000000004, "exposure lost digits")
    cli.run("set", "sim.seed=0", "render.exposure=0")

    # A bad value fails, names the path, and changes nothing, not even the good assignment
    # beside it in the same merge patch.
    far = cli.json("get", "camera.far")
    rc, _, err = cli.run("set", "camera.far=%s" % json.dumps(far + 1), "camera.fov_y=500",
                         ok=False)
    check(rc != 0, "set camera.fov_y=500 exited 0")
    check("camera.fov_y" in err, "the error does not name camera.fov_y: %r" % err)
    check(err.startswith("volfx: "), "the error is not prefixed 'volfx: ': %r" % err)
    check(cli.json("get", "camera.fov_y") == 50, "a failed set changed fov_y")
    check(cli.json("get", "camera.far") == far, "a failed set applied part of its patch")

    rc, _, err = cli.run("get", "camera.no_such_member", ok=False)
    check(rc != 0 and "not found" in err, "get of an unknown path: rc %d, %r" % (rc, err))
    rc, _, err = cli.run("frobnicate", ok=False)
    check(rc == 2, "an unknown command exited %d, not 2" % rc)

    frame0 = cli.json("get", "sim.frame")
    r = cli.json("step", "3")
    check(r.get("frame") == frame0 + 3, "step 3 from frame %r gave %r" % (frame0, r))

    _, out, _ = cli.run("render", "-o", "x.png", "-W", "64", "-H", "48")
    with open(os.path.join(work, "x.png"), "rb") as f:
        check(png_size(f.read()) == (64, 48), "x.png is not 64x48")
    check("work_ms" in out and len(out.strip().splitlines()) == 1,
          "render summary is not one line with work_ms: %r" % out)

    # A .jpg name without --format asks for jpeg.
    _, out, _ = cli.run("render", "-o", "x.jpg", "-W", "64", "-H", "48")
    with open(os.path.join(work, "x.jpg"), "rb") as f:
        head = f.read(3)
    check(head == b"\xff\xd8\xff" and "jpeg" in out, "x.jpg is not a JPEG: %r, %r" % (head, out))

    cli.run("render", "-o", "d.f32", "--format", "f32", "--aov", "depth", "-W", "32", "-H", "16")
    size = os.path.getsize(os.path.join(work, "d.f32"))
    check(size == 4 * 32 * 16, "depth f32 is %d bytes, not %d" % (size, 4 * 32 * 16))

    # A paused, unchanged scene sends one frame only; playing, every tick has a new one.
    cli.run("play")
    _, out, _ = cli.run("watch", "--count", "3", "--fps", "20", "-W", "32", "-H", "32",
                        "-o", "w_%06d.png", "--seq")
    cli.run("pause")
    m = re.search(r"received (\d+) frames, dropped (\d+)", out)
    check(m is not None and m.group(1) == "3", "watch summary: %r" % out)
    frames = sorted(f for f in os.listdir(work) if re.match(r"w_\d{6}\.png$", f))
    check(frames == ["w_000001.png", "w_000002.png", "w_000003.png"],
          "watch -o --seq wrote %r" % frames)
    with open(os.path.join(work, frames[0]), "rb") as f:
        check(png_size(f.read()) == (32, 32), "watched frame is not 32x32")

    script = os.path.join(work, "good.volfx")
    with open(script, "w") as f:
        f.write("# a comment, then a blank line\n\n"
                "set camera.fov_y=55\n"
                "get camera.fov_y\n"
                "step 2   # trailing comment\n"
                "render -o s.png -W 16 -H 8\n"
                "set --patch '{\"camera\": {\"fov_y\": 45}}'\n"
                "scenes\n")
    cli.run("script", script)
    with open(os.path.join(work, "s.png"), "rb") as f:
        check(png_size(f.read()) == (16, 8), "script render is not 16x8")
    check(cli.json("get", "camera.fov_y") == 45, "script's last set did not apply")

    frame1 = cli.json("get", "sim.frame")
    bad = os.path.join(work, "bad.volfx")
    with open(bad, "w") as f:
        f.write("info\n# comment\nset camera.fov_y=999\nstep 1\n")
    rc, _, err = cli.run("script", bad, ok=False)
    check(rc != 0, "a script with a bad line exited 0")
    check(":3:" in err and "camera.fov_y" in err, "the error lacks line 3 or the path: %r" % err)
    check(cli.json("get", "sim.frame") == frame1, "the script went on after its failing line")


def load_python_client():
    """The package client/python/volfx of this tree (its modules import one another)."""
    path = os.path.join(ROOT, "client", "python")
    if path not in sys.path:
        sys.path.insert(0, path)
    import volfx
    return volfx


def test_python(port):
    volfx = load_python_client()

    with volfx.Client("127.0.0.1", port, timeout=60) as c:
        check(c.info()["name"] == "volfxd", "python info")
        result, data = c.render(40, 20)
        check(png_size(data) == (40, 20), "python render is not 40x20")
        check(result.get("width") == 40 and "work_ms" in result, "python render result %r" % result)
        _, data = c.render(8, 8, encoding="base64")
        check(png_size(data) == (8, 8), "python base64 render is not an 8x8 PNG")

        # 'repeat': a frame at every tick of the paused, unchanged scene.
        sid = c.subscribe(width=16, height=16, fps=20, repeat=True)
        got = list(c.frames(count=3, timeout=30))
        check(len(got) == 3, "python received %d frames, not 3" % len(got))
        for params, data in got:
            check(params.get("id") == sid, "frame of subscription %r" % params.get("id"))
            check(png_size(data) == (16, 16), "python frame is not 16x16")
        r = c.unsubscribe(sid)
        check(r.get("id") == sid and r.get("sent", 0) >= 3, "unsubscribe result %r" % r)

        before = c.get("camera.fov_y")
        try:
            c.set(path="camera.fov_y", value=500)
            raise Failure("set camera.fov_y=500 did not raise")
        except volfx.VolfxError as e:
            check(e.code == -32602, "error code %r, not -32602" % e.code)
            check(e.path == "camera.fov_y", "error path %r" % e.path)
        check(c.get("camera.fov_y") == before, "a refused set changed fov_y")
        c.patch({"camera": {"fov_y": 42}})
        check(c.get("camera.fov_y") == 42, "patch did not apply")

    env = dict(os.environ, PYTHONPATH=os.path.join(ROOT, "client", "python"))
    out = subprocess.run([sys.executable, "-m", "volfx", "--port", str(port), "get",
                          "camera.fov_y"], capture_output=True, timeout=CALL_TIMEOUT, env=env)
    check(out.returncode == 0 and json.loads(out.stdout) == 42,
          "python3 -m volfx get: %r %r" % (out.stdout, out.stderr))


def test_token_unix(bindir, root):
    """A second server with a token and a Unix socket: auth is required and works both ways."""
    data = os.path.join(root, "data-token")
    os.mkdir(data)
    sock = os.path.join(data, "volfxd.sock")
    token = "t0k3n-for-tests"
    server = Server(bindir, data, ["--token", token, "--unix", sock])
    try:
        cli = Cli(bindir, server.port, data)
        rc, _, err = cli.run("info", ok=False)
        check(rc == 1 and "unauthorized" in err, "no token: rc %d, %r" % (rc, err))
        rc, _, err = cli.run("--token", "wrong", "info", ok=False)
        check(rc == 1 and "unauthorized" in err, "wrong token: rc %d, %r" % (rc, err))
        check(cli.json("--token", token, "info").get("auth_required") is True,
              "info.auth_required is not true")

        unix = Cli(bindir, None, data, conn=["--unix", sock])
        _, out, _ = unix.run("get", "camera.fov_y", env={"VOLFX_TOKEN": token})
        check(isinstance(json.loads(out), (int, float)), "get over the Unix socket: %r" % out)

        volfx = load_python_client()
        with volfx.Client(unix=sock, timeout=30) as c:
            try:
                c.info()
                raise Failure("python: info without auth did not raise")
            except volfx.VolfxError as e:
                check(e.code == -32001, "python: no auth gave code %r" % e.code)
        with volfx.Client(unix=sock, token=token, timeout=30) as c:
            check(c.info()["name"] == "volfxd", "python over the Unix socket with a token")

        unix.run("shutdown", env={"VOLFX_TOKEN": token})
        try:
            rc = server.proc.wait(30)
        except subprocess.TimeoutExpired:
            raise Failure("the token server did not exit within 30 s of shutdown")
        check(rc == 0, "the token server exited %d" % rc)
    finally:
        server.stop()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", required=True, help="directory holding volfxd and volfx")
    a = ap.parse_args()
    bindir = os.path.abspath(a.bin)

    tmp = tempfile.TemporaryDirectory(prefix="volfx-client-test-")
    data = os.path.join(tmp.name, "data")
    work = os.path.join(tmp.name, "work")
    os.mkdir(data)
    os.mkdir(work)
    server = None

    def watchdog():
        print("FAIL: test_client timed out after %d s" % TOTAL_TIMEOUT, flush=True)
        for s in SERVERS:
            if s.proc.poll() is None:
                s.proc.kill()
        os._exit(1)

    timer = threading.Timer(TOTAL_TIMEOUT, watchdog)
    timer.daemon = True
    timer.start()
    status = 1
    try:
        test_token_unix(bindir, tmp.name)
        server = Server(bindir, data)
        cli = Cli(bindir, server.port, work)
        test_cli(cli, work)
        test_python(server.port)
        _, out, _ = cli.run("shutdown")
        check(json.loads(out).get("shutting_down") is True, "shutdown result %r" % out)
        try:
            rc = server.proc.wait(30)
        except subprocess.TimeoutExpired:
            raise Failure("volfxd did not exit within 30 s of shutdown")
        check(rc == 0, "volfxd exited %d after shutdown" % rc)
        print("ok: test_client")
        status = 0
    except Failure as e:
        print("FAIL: %s" % e)
        if server is not None:
            print("--- volfxd log (tail) ---\n%s" % server.tail())
    finally:
        timer.cancel()
        if server is not None:
            server.stop()
        tmp.cleanup()
    return status


if __name__ == "__main__":
    sys.exit(main())
