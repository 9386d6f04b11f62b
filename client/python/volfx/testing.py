"""volfx.testing: test a game, tool or pipeline against a private volfxd (standard library only).

    from volfx import testing

    with testing.Server() as srv, srv.client() as c:
        with testing.Scene(c, preset="demo") as scene:
            scene.step(30)
            testing.assert_frame_matches(scene.render(64, 64), "golden/demo_30.png", tolerance=2)

- ``Server`` starts volfxd on 127.0.0.1, port 0, with a temporary ``--data`` directory and a
  random token, waits on ``--ready-fd`` until it listens, keeps its log, and stops it with
  SIGTERM (SIGKILL after ``stop_timeout``). A server is never left behind: volfxd runs in its
  own process group with PR_SET_PDEATHSIG, so it dies with the test process even when that is
  killed, and an atexit hook stops whatever a crashed test left running.
- ``Scene`` is a fresh scene per test, made from a preset or a document, deleted afterwards;
  it steps with ``sim.step`` only (the clock is frame-indexed, so 300 steps are 300 steps
  however they are grouped), never with the wall clock's ``sim.play``.
- ``assert_frame_matches`` compares a frame with a golden PNG; on failure it writes the actual
  frame and a diff image and names the worst pixel. ``VOLFX_UPDATE_GOLDEN=1`` writes the
  goldens instead.
- ``TestCase`` is a unittest base class with one server per class and a fresh scene per test,
  adding the server's log to a failed test's report. ``volfx.pytest_plugin`` gives the same as
  pytest fixtures.

Which volfxd: the ``volfxd`` argument, else ``$VOLFX_VOLFXD``, else ``volfxd`` on ``PATH``.
docs/testing.md says how to write tests that give the same frames every run.
"""

import atexit
import ctypes
import itertools
import os
import secrets
import select
import shutil
import signal
import subprocess
import tempfile
import time
import unittest

import volfx
from volfx import png

UPDATE_ENV = "VOLFX_UPDATE_GOLDEN"
OUTPUT_ENV = "VOLFX_TEST_OUTPUT"

_PR_SET_PDEATHSIG = 1
_live = []  # Servers started and not yet stopped, for the atexit hook.


class ServerError(RuntimeError):
    """volfxd did not start, did not stop cleanly, or exited with an error; the message ends
    with the tail of its log."""


class FrameMismatch(AssertionError):
    """A frame differs from its golden image (or the golden is missing or another size)."""


def find_volfxd(volfxd=None):
    """The volfxd executable: 'volfxd', else $VOLFX_VOLFXD, else volfxd on PATH."""
    path = volfxd or os.environ.get("VOLFX_VOLFXD") or shutil.which("volfxd")
    if not path:
        raise ServerError("no volfxd: pass volfxd=PATH, set VOLFX_VOLFXD or put it on PATH")
    if not os.access(path, os.X_OK):
        raise ServerError("volfxd %s is not an executable file" % path)
    return os.path.abspath(path)


def _child_setup(parent):
    """Runs in the child before exec: its own process group, and SIGKILL when the parent
    dies (Linux), checked against the race of a parent that died first."""
    os.setpgid(0, 0)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(1)


class Server:
    """One private volfxd. ``args`` are more volfxd options (``--scene``, ``--device``, ...).

    Attributes once started: ``host``, ``port``, ``token``, ``data_dir``, ``log_path``,
    ``pid``. ``client()`` opens an authenticated ``volfx.Client``.
    """

    def __init__(self, volfxd=None, args=(), token=None, start_timeout=120.0, stop_timeout=30.0,
                 env=None):
        self.volfxd = find_volfxd(volfxd)
        self.args = list(args)
        self.token = token or secrets.token_hex(16)
        self.start_timeout = start_timeout
        self.stop_timeout = stop_timeout
        self.env = dict(os.environ if env is None else env)
        self.env.pop("VOLFX_TOKEN", None)
        self.proc = None
        self.host = self.port = None
        self.root = self.data_dir = self.log_path = None
        self.returncode = None

    # -- life cycle ------------------------------------------------------------------------

    def start(self):
        """Starts volfxd and waits until it listens; raises ServerError with its log if it
        exits or stays silent past ``start_timeout``."""
        self.root = tempfile.mkdtemp(prefix="volfx-test-")
        self.data_dir = os.path.join(self.root, "data")
        os.mkdir(self.data_dir)
        self.log_path = os.path.join(self.root, "volfxd.log")
        rfd, wfd = os.pipe()
        cmd = [self.volfxd, "--listen", "127.0.0.1:0", "--data", self.data_dir, "--token",
               self.token, "--ready-fd", str(wfd)] + self.args
        parent = os.getpid()
        try:
            with open(self.log_path, "wb") as log:
                self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log,
                                             stderr=subprocess.STDOUT, env=self.env,
                                             pass_fds=(wfd,),
                                             preexec_fn=lambda: _child_setup(parent))
            _live.append(self)
            os.close(wfd)
            wfd = -1
            line = self._read_ready(rfd)
        except BaseException:
            # The error carries the log's tail; the files go.
            self.kill()
            self._remove_files()
            raise
        finally:
            os.close(rfd)
            if wfd >= 0:
                os.close(wfd)
        parts = line.split()
        if len(parts) != 3 or parts[0] != "ready":
            self.kill()
            err = self._error("volfxd wrote %r to its ready descriptor, not 'ready PORT HOST'" %
                              line)
            self._remove_files()
            raise err
        self.port, self.host = int(parts[1]), parts[2]
        return self

    def _read_ready(self, rfd):
        deadline = time.monotonic() + self.start_timeout
        got = b""
        while not got.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0:
                self.kill()
                raise self._error("volfxd was not ready within %.0f s" % self.start_timeout)
            ready, _, _ = select.select([rfd], [], [], min(left, 1.0))
            if not ready:
                continue
            chunk = os.read(rfd, 256)
            if not chunk:
                # Closed without a line: the start failed.
                try:
                    self.returncode = self.proc.wait(timeout=self.stop_timeout)
                except subprocess.TimeoutExpired:
                    self.kill()
                self._forget()
                raise self._error("volfxd exited with status %s before it was ready" %
                                  self.returncode)
            got += chunk
        return got.decode("utf-8", "replace").strip()

    def stop(self, check=True):
        """Stops volfxd (SIGTERM, then SIGKILL after ``stop_timeout``), removes its files and
        returns its exit status. With 'check', an exit status other than 0 (a crash, a kill,
        an error) raises ServerError with the log."""
        if self.proc is None:
            return self.returncode
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=self.stop_timeout)
            except subprocess.TimeoutExpired:
                self.kill()
                self.returncode = self.proc.returncode
                err = self._error("volfxd did not stop within %.0f s of SIGTERM; killed" %
                                  self.stop_timeout)
                self._remove_files()
                if check:
                    raise err
                return self.returncode
        self.returncode = self.proc.returncode
        self._forget()
        err = None
        if self.returncode != 0:
            why = ("killed by signal %d" % -self.returncode if self.returncode < 0
                   else "exit status %d" % self.returncode)
            err = self._error("volfxd ended with %s" % why)
        self._remove_files()
        if err and check:
            raise err
        return self.returncode

    def kill(self):
        """Kills volfxd's process group at once (no clean stop)."""
        if self.proc is not None and self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except OSError:
                self.proc.kill()
            self.proc.wait()
        self._forget()

    def _forget(self):
        if self in _live:
            _live.remove(self)

    def _remove_files(self):
        if self.root:
            shutil.rmtree(self.root, ignore_errors=True)
            self.root = None

    def __enter__(self):
        return self.start() if self.proc is None else self

    def __exit__(self, et, ev, tb):
        # A test that failed already reports its own error; the stop is still checked.
        self.stop(check=et is None)
        return False

    # -- use -------------------------------------------------------------------------------

    @property
    def pid(self):
        return self.proc.pid if self.proc else None

    def alive(self):
        return self.proc is not None and self.proc.poll() is None

    def client(self, timeout=60):
        """A new connection, authenticated with the server's token."""
        return volfx.Client(self.host, self.port, token=self.token, timeout=timeout)

    def log_offset(self):
        """Where the log ends now, for ``log_text(since=...)``."""
        try:
            return os.path.getsize(self.log_path)
        except (OSError, TypeError):
            return 0

    def log_text(self, since=0):
        """volfxd's stdout and stderr so far (from byte 'since')."""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(since)
                return f.read().decode("utf-8", "replace")
        except (OSError, TypeError):
            return ""

    def _error(self, what, tail=60):
        lines = self.log_text().splitlines()[-tail:]
        text = "%s\ncommand: %s\n--- volfxd log (last %d lines) ---\n%s" % (
            what, " ".join(self.proc.args) if self.proc else self.volfxd, len(lines),
            "\n".join(lines))
        return ServerError(text)


@atexit.register
def _stop_leftovers():
    for srv in list(_live):
        try:
            srv.stop(check=False)
        except Exception:
            srv.kill()


# -- scenes ----------------------------------------------------------------------------------

_scene_numbers = itertools.count(1)


class Scene:
    """A fresh scene on 'client': the default scene, a ``preset`` ("demo", ...) or a
    ``document`` (a dict applied as a merge patch over the default scene, so members it leaves
    out keep their defaults). It never plays: ``sim.playing`` is forced off. ``name`` defaults
    to a new unique one. Deleted by ``delete()`` or at the end of a ``with`` block."""

    def __init__(self, client, preset=None, document=None, name=None):
        self.client = client
        self.name = name or "test-%d-%d" % (os.getpid(), next(_scene_numbers))
        params = {"name": self.name}
        if preset:
            params["preset"] = preset
        client.call("scene.create", **params)
        try:
            if document is not None:
                doc = dict(document)
                doc["sim"] = dict(doc.get("sim") or {}, playing=False)
                client.patch(doc, scene=self.name)
            elif client.get("sim.playing", scene=self.name):
                client.pause(scene=self.name)
                if client.get("sim.frame", scene=self.name) != 0:
                    raise ValueError("preset %r plays by the wall clock and moved before it "
                                     "was paused; give it sim.playing false" % preset)
        except BaseException:
            self.delete()
            raise

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.delete()
        return False

    def delete(self):
        try:
            self.client.call("scene.delete", name=self.name)
        except (volfx.VolfxError, volfx.ConnectionLost, OSError):
            pass

    def step(self, n=1):
        """Advances the clock by 'n' frames with ``sim.step``; returns {"time", "frame"}."""
        return self.client.step(n, scene=self.name)

    def get(self, path=None):
        return self.client.get(path, scene=self.name)

    def set(self, path, value):
        return self.client.set(path, value, scene=self.name)

    def patch(self, patch):
        return self.client.patch(patch, scene=self.name)

    def render(self, width=128, height=128, **kw):
        """Renders the scene's current frame as PNG bytes (``kw``: aov, layers, camera, ...)."""
        _, data = self.client.render(width, height, scene=self.name, **kw)
        return data


# -- golden images ---------------------------------------------------------------------------


def update_requested():
    """True when ``VOLFX_UPDATE_GOLDEN`` asks for goldens to be written, not compared."""
    return os.environ.get(UPDATE_ENV, "") not in ("", "0", "no", "false")


def _diff_image(actual, golden, tolerance):
    """Dimmed grey golden where the pixels match; red, brighter for larger differences,
    where they differ by more than 'tolerance'."""
    out = bytearray(len(actual.rgba))
    a, g = actual.rgba, golden.rgba
    for i in range(0, len(a), 4):
        d = max(abs(a[i + c] - g[i + c]) for c in range(4))
        if d > tolerance:
            out[i:i + 4] = bytes((min(255, 128 + 4 * d), 0, 0, 255))
        else:
            grey = (g[i] + g[i + 1] + g[i + 2]) // 12
            out[i:i + 4] = bytes((grey, grey, grey, 255))
    return png.Image(actual.width, actual.height, out)


def _output_paths(golden, out_dir):
    out_dir = out_dir or os.environ.get(OUTPUT_ENV) or os.path.dirname(os.path.abspath(golden))
    os.makedirs(out_dir, exist_ok=True)
    stem = os.path.splitext(os.path.basename(golden))[0]
    return os.path.join(out_dir, stem + ".actual.png"), os.path.join(out_dir, stem + ".diff.png")


def assert_frame_matches(frame, golden, tolerance=0, max_pixels=0, out_dir=None):
    """Checks that PNG bytes 'frame' match the golden PNG file 'golden': no more than
    'max_pixels' pixels may have a channel (R, G, B or A) more than 'tolerance' (0-255) away.

    On a mismatch raises ``FrameMismatch`` naming the worst pixel, after writing
    ``NAME.actual.png`` and ``NAME.diff.png`` into 'out_dir' (else ``$VOLFX_TEST_OUTPUT``, else
    the golden's directory). A missing golden or one of another size fails the same way. With
    ``VOLFX_UPDATE_GOLDEN=1`` the frame is written as the golden instead, and nothing fails.
    """
    actual = png.read(frame)
    if update_requested():
        os.makedirs(os.path.dirname(os.path.abspath(golden)), exist_ok=True)
        with open(golden, "wb") as f:
            f.write(frame)
        return
    actual_path, diff_path = _output_paths(golden, out_dir)
    if not os.path.exists(golden):
        png.write_file(actual_path, actual)
        raise FrameMismatch("golden image %s does not exist (the frame is in %s; run with %s=1 "
                            "to make it the golden)" % (golden, actual_path, UPDATE_ENV))
    try:
        expect = png.read_file(golden)
    except png.PngError as e:
        png.write_file(actual_path, actual)
        raise FrameMismatch("golden image %s cannot be read: %s (the frame is in %s)" %
                            (golden, e, actual_path)) from None
    if expect.size != actual.size:
        png.write_file(actual_path, actual)
        raise FrameMismatch("golden image %s is %dx%d but the frame is %dx%d (the frame is in "
                            "%s; run with %s=1 to replace the golden)" %
                            (golden, expect.width, expect.height, actual.width, actual.height,
                             actual_path, UPDATE_ENV))
    a, g = actual.rgba, expect.rgba
    if a == g:
        return
    worst, worst_at, over = -1, 0, 0
    for i in range(0, len(a), 4):
        d = max(abs(a[i] - g[i]), abs(a[i + 1] - g[i + 1]), abs(a[i + 2] - g[i + 2]),
                abs(a[i + 3] - g[i + 3]))
        if d > tolerance:
            over += 1
        if d > worst:
            worst, worst_at = d, i // 4
    if over <= max_pixels:
        return
    png.write_file(actual_path, actual)
    png.write_file(diff_path, _diff_image(actual, expect, tolerance))
    x, y = worst_at % actual.width, worst_at // actual.width
    raise FrameMismatch(
        "frame differs from golden %s: %d of %d pixels differ by more than %d (at most %d "
        "allowed); worst at (%d, %d): RGBA %s, golden %s (difference %d). Actual: %s, diff: %s" %
        (golden, over, actual.width * actual.height, tolerance, max_pixels, x, y,
         actual.pixel(x, y), expect.pixel(x, y), worst, actual_path, diff_path))


# -- unittest --------------------------------------------------------------------------------


class TestCase(unittest.TestCase):
    """A unittest base class: one volfxd per class (``volfxd_args`` adds options), one
    connection ``self.client`` and a fresh ``self.scene`` per test (from ``scene_preset`` or
    ``scene_document``). A failed test's report ends with what volfxd logged during it."""

    volfxd = None
    volfxd_args = ()
    scene_preset = None
    scene_document = None
    server = None

    @classmethod
    def setUpClass(cls):
        super().setUpClass()
        cls.server = Server(cls.volfxd, args=cls.volfxd_args).start()

    @classmethod
    def tearDownClass(cls):
        try:
            if cls.server is not None:
                cls.server.stop()
        finally:
            cls.server = None
            super().tearDownClass()

    def setUp(self):
        super().setUp()
        self.client = self.server.client()
        self.addCleanup(self.client.close)
        self.scene = Scene(self.client, preset=self.scene_preset, document=self.scene_document)
        self.addCleanup(self.scene.delete)

    def run(self, result=None):
        result = result if result is not None else self.defaultTestResult()
        server = type(self).server
        since = server.log_offset() if server else 0
        before = len(result.failures) + len(result.errors)
        try:
            return super().run(result)
        finally:
            if server is not None and len(result.failures) + len(result.errors) > before:
                log = server.log_text(since) or "(nothing)\n"
                for kind in (result.failures, result.errors):
                    if kind and kind[-1][0] is self:
                        kind[-1] = (self, kind[-1][1] + "\n--- volfxd log during the test ---\n"
                                    + log)
