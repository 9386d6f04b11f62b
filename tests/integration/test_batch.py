#!/usr/bin/env python3
"""
`volfx batch` and `volfx bake`, the render-farm commands, run as real subprocesses: each starts
a private volfxd of its own. Checked: files named by the #### pattern (with a space in the
folder), a range equal byte for byte to its sub-ranges rendered apart, complete frames skipped
(their mtimes kept) and a cut-short one rendered again, no server at all when nothing is left,
--overwrite, raw formats, exit status 2 for command-line mistakes and 1 (naming the frame) for
an unwritable output, a bad preset or a refused render, no temporary files left behind; a bake
every 8 frames, a batch starting from it equal to one simulating from frame 0, a bake of
another scene refused, a snapshot as the scene; and SIGTERM stopping the private server.

    python3 tests/integration/test_batch.py --bin build/bin
"""

import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_batch", timeout_s=300)
T = suite.test

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PRESET = "paper-001-flow"
SIZE = ["-W", "64", "-H", "48"]
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
work = None  # The folder every command runs in.


def volfx(s, *args, env=None, timeout=120):
    """Runs build/bin/volfx ARGS in 'work'; returns (status, stdout, stderr)."""
    e = dict(os.environ)
    e.update(env or {})
    p = subprocess.run([os.path.join(s.bin, "volfx")] + list(args), cwd=work, env=e,
                       stdin=subprocess.DEVNULL, capture_output=True, timeout=timeout)
    return p.returncode, p.stdout.decode("utf-8", "replace"), p.stderr.decode("utf-8", "replace")


def ok(s, *args, **kw):
    rc, out, err = volfx(s, *args, **kw)
    s.check(rc == 0, "`volfx %s` succeeds" % " ".join(args), "status %d: %s" % (rc, err[-600:]))
    return out, err


def path(*parts):
    return os.path.join(work, *parts)


def read(*parts):
    with open(path(*parts), "rb") as f:
        return f.read()


def frame_names(count=12, first=0, prefix="f_", ext=".png", width=4):
    """The names f_####.png gives frames first, first + 1, ... (count of them)."""
    return ["%s%0*d%s" % (prefix, width, first + i, ext) for i in range(count)]


def png_size(data):
    if data[:8] != mock.PNG_SIGNATURE or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def leftovers():
    """Temporary files of a frame or a snapshot anywhere under 'work'."""
    found = []
    for root, _, files in os.walk(work):
        found += [os.path.join(root, f) for f in files if f.startswith(".")]
    return found


def same_frames(s, a, b, names, what):
    differ = [n for n in names if read(a, n) != read(b, n)]
    s.check(not differ, what, "frames differing: %s" % differ)


@T
def pattern_with_spaces(s):
    out, _ = ok(s, "batch", PRESET, "-s", "0", "-e", "11", "-o", "shot 1/f_####.png", *SIZE)
    s.eq(sorted(os.listdir(path("shot 1"))), frame_names(), "files named by the pattern")
    for name in frame_names():
        data = read("shot 1", name)
        s.check(png_size(data) == (64, 48) and data.endswith(PNG_END),
                "%s is a whole 64x48 PNG" % name, "%d bytes" % len(data))
    s.check("volfx batch: 12 frames written, 0 skipped (0..11)" in out, "the summary", out)
    # Several runs of #, each its own width, wider when the number needs it; a step.
    ok(s, "batch", PRESET, "-s", "9", "-e", "13", "-j", "2", "-o", "multi/##/f_#.png", *SIZE)
    got = sorted(os.path.relpath(os.path.join(r, f), path("multi"))
                 for r, _, fs in os.walk(path("multi")) for f in fs)
    s.eq(got, ["09/f_9.png", "11/f_11.png", "13/f_13.png"], "runs of # and -j")
    s.eq(read("multi", "11", "f_11.png"), read("shot 1", "f_0011.png"), "-j frames are the frames")
    # One frame needs no #.
    ok(s, "batch", PRESET, "-s", "3", "-e", "3", "-o", "single.png", *SIZE)
    s.eq(read("single.png"), read("shot 1", "f_0003.png"), "a single frame without #")
    s.eq(leftovers(), [], "no temporary files left")


@T
def subranges_equal_the_range(s):
    ok(s, "batch", PRESET, "-s", "0", "-e", "5", "-o", "parts/f_####.png", *SIZE)
    ok(s, "batch", PRESET, "-s", "6", "-e", "11", "-o", "parts/f_####.png", *SIZE)
    same_frames(s, "shot 1", "parts", frame_names(),
                "frames 0-11 in one run equal 0-5 and 6-11 rendered apart")


@T
def complete_frames_skipped(s):
    folder = path("shot 1")
    before = {n: os.stat(os.path.join(folder, n)).st_mtime_ns for n in frame_names()}
    want5 = read("shot 1", "f_0005.png")
    with open(os.path.join(folder, "f_0005.png"), "r+b") as f:
        f.truncate(len(want5) // 2)  # A frame cut short, as by a full disk.
    stale = os.path.join(folder, ".f_0005.png.part.Ab12Cd")
    with open(stale, "wb") as f:
        f.write(b"left by a killed run")
    time.sleep(0.02)
    out, err = ok(s, "batch", PRESET, "-s", "0", "-e", "11", "-o", "shot 1/f_####.png", *SIZE,
                  "-v")
    s.check("1 frames written, 11 skipped (0..11)" in out, "only the cut frame rendered", out)
    s.check("frame 4: skipped" in err and "frame 5: wrote" in err, "-v says which", err)
    s.eq(read("shot 1", "f_0005.png"), want5, "the cut frame rendered again, the same")
    after = {n: os.stat(os.path.join(folder, n)).st_mtime_ns for n in frame_names()}
    kept = [n for n in before if n != "f_0005.png" and before[n] != after[n]]
    s.eq(kept, [], "complete frames untouched (mtime)")
    s.check(not os.path.exists(stale), "the stale temporary file of frame 5 removed")
    # Nothing left: no server is started (a missing volfxd would fail the run).
    out, _ = ok(s, "batch", PRESET, "-s", "0", "-e", "11", "-o", "shot 1/f_####.png", *SIZE,
                env={"VOLFX_VOLFXD": path("no-such-volfxd")})
    s.check("nothing left to do" in out and "0 frames written, 12 skipped" in out,
            "all complete: nothing to do", out)


@T
def overwrite(s):
    folder = path("shot 1")
    before = os.stat(os.path.join(folder, "f_0001.png")).st_mtime_ns
    time.sleep(0.02)
    out, _ = ok(s, "batch", PRESET, "-s", "0", "-e", "1", "-o", "shot 1/f_####.png", *SIZE,
                "--overwrite")
    s.check("2 frames written, 0 skipped (0..1)" in out, "--overwrite renders them", out)
    s.check(os.stat(os.path.join(folder, "f_0001.png")).st_mtime_ns != before, "a new file")
    same_frames(s, "shot 1", "parts", frame_names(count=2), "and the same frames")


@T
def raw_formats(s):
    ok(s, "batch", PRESET, "-s", "0", "-e", "1", "-o", "raw/d_#.f32", "--aov", "depth", *SIZE)
    ok(s, "batch", PRESET, "-s", "0", "-e", "0", "-o", "raw/c_#.rgba8", "--format", "rgba8",
       *SIZE)
    s.eq(sorted(os.listdir(path("raw"))), ["c_0.rgba8", "d_0.f32", "d_1.f32"], "raw files")
    s.eq(len(read("raw", "d_1.f32")), 64 * 48 * 4, "f32: one float per pixel")
    s.eq(len(read("raw", "c_0.rgba8")), 64 * 48 * 4, "rgba8: four bytes per pixel")
    with open(path("raw", "d_1.f32"), "ab") as f:
        f.write(b"\0")  # One byte too many: not this frame's file.
    out, _ = ok(s, "batch", PRESET, "-s", "0", "-e", "1", "-o", "raw/d_#.f32", "--aov", "depth",
                *SIZE)
    s.check("1 frames written, 1 skipped" in out, "a raw file of the wrong size rendered", out)
    s.eq(len(read("raw", "d_1.f32")), 64 * 48 * 4, "and now whole")


@T
def usage_errors(s):
    nothing = {"VOLFX_VOLFXD": path("no-such-volfxd")}
    cases = [
        ("batch", PRESET, "-s", "0", "-e", "3"),                        # no -o
        ("batch", PRESET, "-e", "3", "-o", "u/f_#.png"),                # no -s
        ("batch", PRESET, "-s", "0", "-o", "u/f_#.png"),                # no -e
        ("batch", "-s", "0", "-e", "3", "-o", "u/f_#.png"),             # no scene
        ("batch", PRESET, "-s", "5", "-e", "3", "-o", "u/f_#.png"),     # LAST < FIRST
        ("batch", PRESET, "-s", "0", "-e", "3", "-j", "0", "-o", "u/f_#.png"),
        ("batch", PRESET, "-s", "x", "-e", "3", "-o", "u/f_#.png"),
        ("batch", PRESET, "-s", "-1", "-e", "3", "-o", "u/f_#.png"),
        ("batch", PRESET, "-s", "0", "-e", "9007199254740992", "-o", "u/f_#.png"),
        ("batch", PRESET, "-s", "0", "-e", "3", "-o", "u/f.png"),       # no # for 4 frames
        ("batch", PRESET, "-s", "0", "-e", "3", "-o", "u/f_#.png", "--bogus"),
        ("batch", PRESET, "-s", "0", "-e", "3", "-o", "u/f_#.png", "--format", "u8"),
        ("batch", PRESET, "-s", "0", "-e", "3", "-o"),                  # -o without a value
        ("bake", PRESET, "-o", "u/bk"),                                 # no -e
        ("bake", PRESET, "-e", "3"),                                    # no -o
        ("bake", PRESET, "-e", "3", "-k", "0", "-o", "u/bk"),
    ]
    for args in cases:
        rc, out, err = volfx(s, *args, env=nothing)
        s.check(rc == 2, "`volfx %s` exits 2" % " ".join(args), "status %d: %s" % (rc, err))
        s.check(err.startswith("volfx %s: " % args[0]), "and says why on stderr", err)
    s.check(not os.path.exists(path("u")), "nothing was written for them")


@T
def failures_name_the_frame(s):
    with open(path("a-file"), "wb") as f:
        f.write(b"not a folder")
    rc, out, err = volfx(s, "batch", PRESET, "-s", "3", "-e", "4", "-o", "a-file/sub/f_#.png",
                         *SIZE)
    s.eq(rc, 1, "an output that cannot be written: status 1")
    s.check("frame 3:" in err and "a-file" in err, "the frame and the path named", err)
    s.check("0 frames written" in out, "the summary still printed", out)
    rc, out, err = volfx(s, "batch", "no-such-preset", "-s", "0", "-e", "1", "-o", "np/f_#.png",
                         *SIZE)
    s.eq(rc, 1, "a bad preset: status 1")
    s.check("frame 0:" in err and "no-such-preset" in err, "the frame and the preset named", err)
    rc, out, err = volfx(s, "batch", PRESET, "-s", "2", "-e", "3", "-o", "big/f_#.png",
                         "-W", "100000", "-H", "48")
    s.eq(rc, 1, "a render the server refuses: status 1")
    s.check("frame 2: render:" in err and "width" in err, "the frame and the message", err)
    s.eq(os.listdir(path("big")) if os.path.isdir(path("big")) else [], [], "no file written")
    s.eq(leftovers(), [], "no temporary files left")


@T
def bake_then_batch(s):
    out, err = ok(s, "bake", PRESET, "-e", "23", "-k", "8", "-o", "bk", "-v")
    names = sorted(os.listdir(path("bk")))
    s.eq(names, ["bake.json", "frame_000000.snap", "frame_000008.snap", "frame_000016.snap",
                 "frame_000023.snap"], "snapshots every 8 frames and at the last")
    s.check("4 snapshots written" in out, "the bake's summary", out)
    out, _ = ok(s, "bake", PRESET, "-e", "23", "-k", "8", "-o", "bk")
    s.check("nothing left to do" in out, "a finished bake has nothing left", out)
    ok(s, "batch", PRESET, "-s", "16", "-e", "23", "-o", "nobake/f_####.png", *SIZE)
    out, err = ok(s, "batch", PRESET, "-s", "16", "-e", "23", "-o", "baked/f_####.png", *SIZE,
                  "--bake", "bk", "-v")
    s.check("bk/frame_000016.snap" in err, "it starts from the snapshot of frame 16", err)
    same_frames(s, "nobake", "baked", frame_names(count=8, first=16),
                "frames 16-23 from the bake equal those simulated from frame 0")
    # A bake of another scene, or a batch of another scene with this bake: refused.
    rc, _, err = volfx(s, "bake", "demo", "-e", "23", "-k", "8", "-o", "bk")
    s.check(rc == 1 and "another scene" in err, "bake: another scene refused", err)
    rc, _, err = volfx(s, "bake", PRESET, "-e", "23", "-k", "5", "-o", "bk")
    s.check(rc == 1 and "every 8" in err, "bake: another -k refused", err)
    rc, _, err = volfx(s, "batch", "demo", "-s", "16", "-e", "17", "-o", "other/f_#.png", *SIZE,
                       "--bake", "bk")
    s.check(rc == 1 and "another scene" in err and "frame 16" in err,
            "batch: another scene's bake refused", err)
    # A snapshot as the scene: it renders from its own frame on.
    ok(s, "batch", "bk/frame_000008.snap", "-s", "8", "-e", "11", "-o", "snap/f_####.png",
       *SIZE)
    same_frames(s, "shot 1", "snap", frame_names(count=4, first=8),
                "frames 8-11 from the snapshot of frame 8 equal the batch's")
    rc, _, err = volfx(s, "batch", "bk/frame_000008.snap", "-s", "5", "-e", "9", "-o",
                       "early/f_#.png", *SIZE)
    s.check(rc == 1 and "frame 5" in err, "a frame before the snapshot's: status 1", err)
    outside = tempfile.mkdtemp(prefix="volfx-outside-")
    try:
        shutil.copy(path("bk", "frame_000008.snap"), outside)
        rc, _, err = volfx(s, "batch", os.path.join(outside, "frame_000008.snap"), "-s", "8",
                           "-e", "9", "-o", "x/f_#.png", "--bake", "bk")
        s.check(rc == 2 and "bk" in err and outside in err,
                "a snapshot outside the bake's parent: usage error naming both", err)
        rc, _, err = volfx(s, "bake", os.path.join(outside, "frame_000008.snap"), "-e", "9",
                           "-o", "bk2")
        s.check(rc == 2 and outside in err, "bake: the same usage error", err)
        s.check(not os.path.exists(path("bk2")), "and no bake directory made for it")
    finally:
        shutil.rmtree(outside, ignore_errors=True)
    s.eq(leftovers(), [], "no temporary files left")


@T
def private_server_setup(s):
    """The private volfxd's command line and environment, seen through a wrapper script."""
    wrapper = path("volfxd-wrapper.sh")
    with open(wrapper, "w") as f:
        f.write('#!/bin/sh\nprintf "%%s\\n" "$@" > "%s"\nenv > "%s"\nexec "%s" "$@"\n' %
                (path("wrapper-args"), path("wrapper-env"), os.path.join(s.bin, "volfxd")))
    os.chmod(wrapper, 0o755)
    presets = path("my presets")
    os.makedirs(presets)
    shutil.copy(os.path.join(ROOT, "scenes", PRESET + ".json"), os.path.join(presets, "mine.json"))
    env = {"VOLFX_VOLFXD": wrapper, "SLURM_CPUS_PER_TASK": "3"}
    saved = os.environ.pop("POCL_MAX_PTHREAD_COUNT", None)
    try:
        ok(s, "batch", "mine", "--presets", presets, "-s", "2", "-e", "2", "-o", "mine/f_#.png",
           *SIZE, env=env)
    finally:
        if saved is not None:
            os.environ["POCL_MAX_PTHREAD_COUNT"] = saved
    s.eq(read("mine", "f_2.png"), read("shot 1", "f_0002.png"), "a preset from --presets")
    args = read("wrapper-args").decode().splitlines()
    child_env = dict(line.split("=", 1) for line in read("wrapper-env").decode().splitlines()
                     if "=" in line)
    s.check(args[:2] == ["--listen", "127.0.0.1:0"], "loopback, a port of the kernel's", args)
    for pair in (["--log-level", "warn"], ["--scene", "mine"], ["--presets", presets]):
        s.check(any(args[i:i + 2] == pair for i in range(len(args))), "volfxd gets %s" % pair,
                args)
    token = child_env.get("VOLFX_TOKEN", "")
    s.check(len(token) == 32 and all(c in "0123456789abcdef" for c in token),
            "a random token of 32 hex digits in its environment", token)
    s.check(token not in " ".join(args), "and not on its command line")
    s.eq(child_env.get("POCL_MAX_PTHREAD_COUNT"), "3", "PoCL threads from SLURM_CPUS_PER_TASK")


def children_of(pid):
    kids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open("/proc/%s/stat" % entry) as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            kids.append(int(entry))
    return kids


@T
def sigterm_stops_the_server(s):
    tmp = tempfile.mkdtemp(prefix="volfx-tmp-")
    env = dict(os.environ, TMPDIR=tmp)
    p = subprocess.Popen([os.path.join(s.bin, "volfx"), "batch", PRESET, "-s", "0", "-e",
                          "1000000", "-o", "long/f_#######.png"] + SIZE, cwd=work, env=env,
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and p.poll() is None:
            if os.path.isdir(path("long")) and len(os.listdir(path("long"))) >= 3:
                break
            time.sleep(0.05)
        kids = children_of(p.pid)
        s.eq(len(kids), 1, "one private volfxd")
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    s.eq(p.returncode, -signal.SIGTERM, "the CLI ends by SIGTERM after cleaning up")
    s.check(b"interrupted by SIGTERM" in err, "and says so", err[-300:])
    s.check(b"frames written" in out, "with its summary", out[-300:])
    for k in kids:
        s.check(not os.path.exists("/proc/%d" % k), "volfxd %d is gone" % k)
    s.eq(os.listdir(tmp), [], "its data directory is removed")
    shutil.rmtree(tmp, ignore_errors=True)
    s.eq(leftovers(), [], "no temporary files left")


def main():
    global work
    work = tempfile.mkdtemp(prefix="volfx-batch-test-")
    try:
        return suite.main()
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
