#!/usr/bin/env python3
"""
The Python test kit (client/python/volfx/testing.py) as a user's test suite meets it: a private
volfxd on port 0 with a token and its own data directory, ready through --ready-fd and gone
afterwards even when the test process is killed; fresh scenes; the frame-indexed clock seen
from outside (sim.step 300 gives the same frame and particles as 10 x sim.step 30); golden
images (match, mismatch with the worst pixel, wrong size, missing, update flag); the PNG codec;
the server log in a failed test's report; and the pytest plugin when pytest is installed.

    python3 tests/integration/test_testkit.py --bin build/bin
"""

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import unittest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PYDIR = os.path.join(ROOT, "client", "python")
sys.path.insert(0, PYDIR)
import volfx  # noqa: E402
from volfx import png, testing  # noqa: E402


def pid_alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie is dead for our purposes.
    try:
        with open("/proc/%d/stat" % pid) as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


class PngCodec(unittest.TestCase):
    def test_round_trip_and_errors(self):
        img = png.Image(3, 2, bytes(range(24)))
        back = png.read(png.write(img))
        self.assertEqual((back.size, back.rgba), ((3, 2), img.rgba))
        self.assertEqual(back.pixel(2, 1), (20, 21, 22, 23))
        with self.assertRaisesRegex(png.PngError, "signature"):
            png.read(b"GIF89a")
        damaged = bytearray(png.write(img))
        damaged[20] ^= 1
        with self.assertRaisesRegex(png.PngError, "CRC"):
            png.read(bytes(damaged))


class Kit(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.srv = testing.Server().start()
        cls.client = cls.srv.client()

    @classmethod
    def tearDownClass(cls):
        cls.client.close()
        root = cls.srv.root
        rc = cls.srv.stop()
        assert rc == 0, "volfxd's exit status %r" % rc
        assert not os.path.exists(root), "the server's temporary files are removed"

    def test_server_is_private(self):
        self.assertNotEqual(self.srv.port, 7878)
        self.assertTrue(os.path.isdir(self.srv.data_dir))
        with volfx.Client(self.srv.host, self.srv.port) as anon:
            with self.assertRaises(volfx.VolfxError) as e:
                anon.info()
            self.assertEqual(e.exception.code, -32001, "a client without the token is refused")
        self.assertEqual(self.client.info()["name"], "volfxd")

    def test_fresh_scenes(self):
        with testing.Scene(self.client, preset="demo") as a:
            a.step(5)
            a.set("camera.fov_y", 33)
            with testing.Scene(self.client) as b:
                self.assertEqual(b.get("sim.frame"), 0)
                self.assertNotEqual(b.name, a.name)
            self.assertEqual(a.get("sim.frame"), 5)
        names = [s["name"] for s in self.client.scenes()["scenes"]]
        self.assertNotIn(a.name, names, "a scene is deleted after its block")
        doc = {"camera": {"fov_y": 21}, "sim": {"playing": True}}
        with testing.Scene(self.client, document=doc) as d:
            self.assertEqual(d.get("camera.fov_y"), 21)
            self.assertFalse(d.get("sim.playing"), "a test scene never plays")
        with self.assertRaises(volfx.VolfxError):
            testing.Scene(self.client, preset="no-such-preset")

    def test_clock_is_frame_indexed(self):
        """sim.step 300 and 10 x sim.step 30 reach the same frame: the same image and the
        same particles, bit for bit, on one build and device."""
        doc = {"fluid": {"enabled": True}}
        with testing.Scene(self.client, preset="demo", document=doc) as one, \
                testing.Scene(self.client, preset="demo", document=doc) as ten:
            r1 = one.step(300)
            for _ in range(10):
                r10 = ten.step(30)
            self.assertEqual((r1["frame"], r1["time"]), (r10["frame"], r10["time"]))
            p1 = self.client.call("fluid.get_particles", scene=one.name, encoding="base64")
            p10 = self.client.call("fluid.get_particles", scene=ten.name, encoding="base64")
            self.assertGreater(p1.get("count", 0), 0, "the demo's pool has particles")
            self.assertEqual(p1, p10, "the particles after 300 steps, however grouped")
            self.assertEqual(one.render(48, 32), ten.render(48, 32))

    def test_golden_images(self):
        work = tempfile.mkdtemp(prefix="volfx-golden-")
        self.addCleanup(shutil.rmtree, work, True)
        golden = os.path.join(work, "g", "demo.png")
        with testing.Scene(self.client, preset="demo") as s:
            s.step(3)
            frame = s.render(40, 24)
        with self.assertRaisesRegex(testing.FrameMismatch, "does not exist"):
            testing.assert_frame_matches(frame, golden)
        os.environ[testing.UPDATE_ENV] = "1"
        try:
            testing.assert_frame_matches(frame, golden)
        finally:
            del os.environ[testing.UPDATE_ENV]
        testing.assert_frame_matches(frame, golden)  # Written by the update flag.
        # One pixel changed by 10 in green: within tolerance 10, not within 9.
        img = png.read(frame)
        rgba = bytearray(img.rgba)
        i = 4 * (7 * 40 + 13)
        rgba[i + 1] = rgba[i + 1] + 10 if rgba[i + 1] < 200 else rgba[i + 1] - 10
        png.write_file(golden, png.Image(40, 24, rgba))
        testing.assert_frame_matches(frame, golden, tolerance=10)
        testing.assert_frame_matches(frame, golden, tolerance=0, max_pixels=1)
        out = os.path.join(work, "out")
        with self.assertRaises(testing.FrameMismatch) as e:
            testing.assert_frame_matches(frame, golden, tolerance=9, out_dir=out)
        msg = str(e.exception)
        self.assertIn("worst at (13, 7)", msg)
        self.assertIn("1 of 960 pixels", msg)
        self.assertEqual(png.read_file(os.path.join(out, "demo.actual.png")).rgba, img.rgba)
        diff = png.read_file(os.path.join(out, "demo.diff.png"))
        self.assertEqual(diff.pixel(13, 7)[:3], (168, 0, 0))
        self.assertEqual(diff.pixel(0, 0)[1:3], (diff.pixel(0, 0)[0],) * 2, "grey elsewhere")
        # A golden of another size fails saying so.
        png.write_file(golden, png.Image(20, 24, bytes(20 * 24 * 4)))
        with self.assertRaisesRegex(testing.FrameMismatch, "is 20x24 but the frame is 40x24"):
            testing.assert_frame_matches(frame, golden, out_dir=out)
        with open(golden, "wb") as f:
            f.write(b"not a png")
        with self.assertRaisesRegex(testing.FrameMismatch, "cannot be read"):
            testing.assert_frame_matches(frame, golden, out_dir=out)

    def test_failed_test_report_has_the_log(self):
        class Failing(testing.TestCase):
            def test_fails(self):
                self.client.call("no.such.method")

        result = unittest.TestResult()
        unittest.defaultTestLoader.loadTestsFromTestCase(Failing).run(result)
        self.assertEqual(len(result.errors), 1)
        text = result.errors[0][1]
        self.assertIn("method not found", text)
        self.assertIn("--- volfxd log during the test ---", text)
        self.assertIsNone(Failing.server, "the class's server is stopped")


class Lifecycle(unittest.TestCase):
    def test_start_failure_names_the_cause(self):
        with self.assertRaises(testing.ServerError) as e:
            testing.Server(args=["--scene", "no-such-preset"]).start()
        msg = str(e.exception)
        self.assertIn("exited with status 1 before it was ready", msg)
        self.assertIn("no-such-preset", msg, "the log's tail is in the error")
        with self.assertRaisesRegex(testing.ServerError, "not an executable"):
            testing.Server(volfxd=os.path.join(ROOT, "README.md"))

    def test_no_process_left_when_the_test_process_dies(self):
        """A test process killed with SIGKILL (no atexit) or ending with an exception takes
        its volfxd with it."""
        script = textwrap.dedent("""
            import os, signal, sys
            sys.path.insert(0, %r)
            from volfx import testing
            srv = testing.Server().start()
            print(srv.pid, srv.root, flush=True)
            if sys.argv[1] == "kill":
                os.kill(os.getpid(), signal.SIGKILL)
            raise RuntimeError("a test crashed")
        """ % PYDIR)
        for how in ("kill", "raise"):
            p = subprocess.run([sys.executable, "-c", script, how], capture_output=True,
                               timeout=180, env=os.environ)
            fields = p.stdout.decode().split()
            self.assertEqual(len(fields), 2, p.stderr.decode()[-2000:])
            pid = int(fields[0])
            deadline = time.monotonic() + 30
            while pid_alive(pid) and time.monotonic() < deadline:
                time.sleep(0.1)
            self.assertFalse(pid_alive(pid), "volfxd %d outlived a test process that %s" %
                             (pid, "was killed" if how == "kill" else "crashed"))
            if how == "raise":
                self.assertFalse(os.path.exists(fields[1]), "the atexit hook removed its files")
            else:
                shutil.rmtree(fields[1], ignore_errors=True)

    def test_crash_is_reported(self):
        srv = testing.Server().start()
        os.kill(srv.pid, signal.SIGKILL)
        srv.proc.wait()
        with self.assertRaisesRegex(testing.ServerError, "killed by signal 9"):
            srv.stop()


class PytestPlugin(unittest.TestCase):
    def test_fixtures(self):
        # This Python's pytest, or the system's (run.sh installs python3-pytest) when this
        # interpreter is another one without it.
        python = next((exe for exe in (sys.executable, "/usr/bin/python3")
                       if os.path.exists(exe) and subprocess.run(
                           [exe, "-c", "import pytest"], capture_output=True).returncode == 0),
                      None)
        if python is None:
            self.skipTest("pytest is not installed")
        work = tempfile.mkdtemp(prefix="volfx-pytest-")
        self.addCleanup(shutil.rmtree, work, True)
        with open(os.path.join(work, "conftest.py"), "w") as f:
            f.write('pytest_plugins = ["volfx.pytest_plugin"]\n')
        with open(os.path.join(work, "test_it.py"), "w") as f:
            f.write(textwrap.dedent("""
                import pytest

                @pytest.mark.volfx_scene(preset="demo")
                def test_steps(volfx_scene):
                    assert volfx_scene.step(4)["frame"] == 4

                def test_fails(volfx_client):
                    volfx_client.call("no.such.method")
            """))
        env = dict(os.environ, PYTHONPATH=PYDIR)
        p = subprocess.run([python, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                            work], capture_output=True, timeout=300, env=env, cwd=work)
        out = p.stdout.decode()
        self.assertIn("1 failed, 1 passed", out, out[-3000:])
        self.assertIn("volfxd log (call)", out, out[-3000:])


def main():
    args = sys.argv[1:]
    if "--bin" in args:
        i = args.index("--bin")
        os.environ["VOLFX_VOLFXD"] = os.path.join(os.path.abspath(args[i + 1]), "volfxd")
        del args[i:i + 2]
    # One fresh kernel cache for this test process and the servers it starts.
    if "POCL_CACHE_DIR" not in os.environ:
        cache = tempfile.mkdtemp(prefix="volfx-pocl-")
        os.environ["POCL_CACHE_DIR"] = cache
        import atexit
        atexit.register(shutil.rmtree, cache, True)
    unittest.main(argv=[sys.argv[0], "-v"] + args)


if __name__ == "__main__":
    main()
