#!/usr/bin/env python3
"""
The files requests name, against real volfxd processes: nothing is read or written outside the
data directory while a directory in it is swapped for a link (with openat2 and without it);
presets come only from the presets directory; FIFOs, directories and other files that are not
regular are refused at once; temporary files left by a killed save are removed; a snapshot
damaged anywhere does not load as a different state; and what a client names wrongly is
answered -32602 or -32004, never -32603.

    python3 tests/integration/test_file_safety.py --bin build/bin
"""

import base64
import json
import os
import random
import re
import shutil
import signal
import struct
import sys
import tempfile
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_NOT_FOUND, E_PARAMS, expect_error  # noqa: E402

E_INTERNAL = -32603

suite = mock.Suite("test_file_safety", timeout_s=500)
suite.server_args = []
T = suite.test

TRI = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
TEMP_PREFIX = ".volfx-tmp-"
TEMP_RE = re.compile(r"^\.volfx-tmp-[0-9a-f]{16}$")


def put(path, data):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data)


def snapshot_of(c, scene, data_dir, name):
    c.ok("scene.save", {"scene": scene, "file": name})
    with open(os.path.join(data_dir, name), "rb") as f:
        return f.read()


def tree(root):
    """Every file and link under 'root', with its size (links as their target)."""
    out = {}
    for d, dirs, files in os.walk(root):
        for n in files + [x for x in dirs if os.path.islink(os.path.join(d, x))]:
            p = os.path.join(d, n)
            out[os.path.relpath(p, root)] = (os.readlink(p) if os.path.islink(p)
                                             else os.path.getsize(p))
    return out


# --------------------------------------------------------------------------------------------
# Finding 10: a directory swapped for a link while requests run


def race(s, env, label):
    base = tempfile.mkdtemp(prefix="volfx-race-")
    data, outside = os.path.join(base, "data"), os.path.join(base, "outside")
    os.makedirs(os.path.join(data, "box", "seq"))
    os.makedirs(outside)
    with mock.Server(s.bin, data_dir=data, env=env) as srv:
        c = srv.connect(timeout=60)
        c.ok("scene.create", {"name": "in"})
        c.ok("scene.set", {"scene": "in", "path": "camera.fov_y", "value": 31})
        inside_snap = snapshot_of(c, "in", data, "box/s.snap")
        c.ok("scene.set", {"scene": "in", "path": "camera.fov_y", "value": 77})
        outside_snap = snapshot_of(c, "in", data, "o.snap")
        os.unlink(os.path.join(data, "o.snap"))
        put(os.path.join(outside, "s.snap"), outside_snap)
        put(os.path.join(data, "box", "m.obj"), TRI)
        # Outside, a mesh whose error would say it was read: a face past its vertices.
        put(os.path.join(outside, "m.obj"), b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 777777\n")
        before = tree(outside)
        assert inside_snap

        stop = threading.Event()
        swaps = [0]

        def swapper():
            box, real = os.path.join(data, "box"), os.path.join(data, "box.real")
            links = [outside, os.path.join("..", "outside"),
                     os.path.join("..", "..", os.path.basename(base), "outside")]
            while not stop.is_set():
                os.rename(box, real)
                try:
                    os.symlink(links[swaps[0] % len(links)], box)
                    time.sleep(0.0005)
                    os.unlink(box)
                finally:
                    os.rename(real, box)
                swaps[0] += 1
                time.sleep(0.0005)

        a, b = srv.connect(timeout=60), srv.connect(timeout=60)
        a.ok("scene.create", {"name": "a"})
        b.ok("scene.create", {"name": "b"})
        a.ok("scene.create", {"name": "j"})
        # A job writing frames into the directory meanwhile (started first: it makes its
        # directory, which the swaps must not race).
        r = a.call("render.sequence", {"scene": "j", "first": 0, "last": 40, "dir": "box/seq",
                                       "width": 16, "height": 12})[0]
        job = (r.get("result") or {}).get("id")
        t = threading.Thread(target=swapper, daemon=True)
        t.start()
        loads, saves, meshes, wrong = [0, 0], [0, 0], [0, 0], []
        internal = []
        deadline = time.monotonic() + 4.0
        i = 0
        while time.monotonic() < deadline:
            i += 1
            r = a.call("scene.load", {"scene": "a", "file": "box/s.snap"})[0]
            loads[1 if "result" in r else 0] += 1
            if "result" in r:
                fov = a.ok("scene.get", {"scene": "a", "path": "camera.fov_y"})[0]
                if fov != 31:
                    wrong.append("load %d read fov %s" % (i, fov))
            elif r["error"]["code"] == E_INTERNAL:
                internal.append(r)
            r = b.call("scene.save", {"scene": "b", "file": "box/out%d.snap" % (i % 3)})[0]
            saves[1 if "result" in r else 0] += 1
            if "error" in r and r["error"]["code"] == E_INTERNAL:
                internal.append(r)
            r = b.call("scene.set", {"scene": "b", "patch": {"objects": [
                {"shape": "mesh", "file": "box/m.obj"}]}})[0]
            meshes[1 if "result" in r else 0] += 1
            if "error" in r:
                if "777777" in r["error"].get("message", ""):
                    wrong.append("mesh read outside: %s" % r["error"]["message"])
                if r["error"]["code"] == E_INTERNAL:
                    internal.append(r)
            b.ok("scene.set", {"scene": "b", "patch": {"objects": []}})
        stop.set()
        t.join()
        if job is not None:
            for _ in range(100):
                jobs = a.ok("job.list", {})[0].get("jobs") or []
                mine = [j for j in jobs if j.get("id") == job]
                if not mine or mine[0].get("state") != "running":
                    break
                time.sleep(0.1)
        s.check(swaps[0] > 100, "%s: the directory was swapped many times" % label, swaps[0])
        s.eq(wrong, [], "%s: nothing was read from outside the data directory" % label)
        s.eq(tree(outside), before, "%s: nothing was written outside the data directory" % label)
        s.eq(internal[:1], [], "%s: no -32603 among the refusals" % label)
        s.check(loads[1] > 0 and saves[1] > 0 and meshes[1] > 0,
                "%s: loads, saves and meshes still succeed between the swaps" % label,
                "loads %s saves %s meshes %s" % (loads, saves, meshes))
        s.check(loads[0] + saves[0] + meshes[0] > 0,
                "%s: some requests met the link and were refused" % label,
                "loads %s saves %s meshes %s" % (loads, saves, meshes))
        print("    %s: %d swaps; loads ok/refused %d/%d, saves %d/%d, meshes %d/%d" %
              (label, swaps[0], loads[1], loads[0], saves[1], saves[0], meshes[1], meshes[0]))
    shutil.rmtree(base, ignore_errors=True)


@T
def swapped_directory_openat2(s):
    race(s, {"VOLFX_NO_OPENAT2": "0"}, "openat2")


@T
def swapped_directory_component_walk(s):
    race(s, {"VOLFX_NO_OPENAT2": "1"}, "O_NOFOLLOW walk")


# --------------------------------------------------------------------------------------------
# Finding 11: presets


@T
def presets_only_from_the_presets_directory(s):
    base = tempfile.mkdtemp(prefix="volfx-presets-")
    cwd, presets = os.path.join(base, "cwd"), os.path.join(base, "presets")
    os.makedirs(cwd)
    os.makedirs(presets)
    put(os.path.join(cwd, "private-scene.json"), b'{"token": "s3cret-member"}')
    put(os.path.join(cwd, "start.json"), b'{"camera": {"fov_y": 44}}')
    put(os.path.join(presets, "ok.json"), b'{"camera": {"fov_y": 40}}')
    put(os.path.join(presets, "broken.json"), b'{"token": "s3cret-member"')
    os.symlink(os.path.join(cwd, "private-scene.json"), os.path.join(presets, "link.json"))
    os.mkfifo(os.path.join(presets, "fifo.json"))
    os.mkdir(os.path.join(presets, "dir.json"))
    here = os.getcwd()
    os.chdir(cwd)
    try:
        # The operator's --scene may be a path, here relative to volfxd's working directory.
        srv = mock.Server(s.bin, "--presets", presets, "--scene", "start.json").start()
    finally:
        os.chdir(here)
    with srv:
        c = srv.connect()
        s.eq(c.ok("scene.get", {"path": "camera.fov_y"})[0], 44,
             "the operator's --scene FILE.json is read from the working directory")
        c.ok("scene.create", {"name": "ok", "preset": "ok"})
        s.eq(c.ok("scene.get", {"scene": "ok", "path": "camera.fov_y"})[0], 40,
             "a preset of the presets directory")
        for name in ("private-scene.json", "private-scene", "start.json", "../cwd/start",
                     "cwd/start.json", "/etc/passwd"):
            e = expect_error(s, c, "scene.create", {"name": "x", "preset": name}, E_NOT_FOUND,
                             "preset", "preset %r is not found" % name).get("error") or {}
            s.check("s3cret" not in e.get("message", "") and "token" not in e.get("message", ""),
                    "the answer for %r quotes nothing of the file" % name, e.get("message"))
        t0 = time.monotonic()
        for name in ("link", "fifo", "dir", "broken"):
            e = expect_error(s, c, "scene.create", {"name": "x", "preset": name}, E_PARAMS,
                             "preset", "preset %r is refused" % name).get("error") or {}
            s.check("s3cret" not in e.get("message", "") and "token" not in e.get("message", ""),
                    "the answer for %r quotes nothing of the file" % name, e.get("message"))
        s.check(time.monotonic() - t0 < 5, "a FIFO preset is refused at once")
        s.eq(sorted(x["name"] for x in c.ok("scene.list")[0]["scenes"]), ["main", "ok"],
             "no scene was made from a refused preset")
    shutil.rmtree(base, ignore_errors=True)


# --------------------------------------------------------------------------------------------
# Finding 12: regular files only


@T
def fifos_and_other_files_refused(s):
    d = s.srv.data_dir
    os.mkfifo(os.path.join(d, "fifo.snap"))
    os.mkfifo(os.path.join(d, "fifo.obj"))
    os.mkfifo(os.path.join(d, "fifo.u8"))
    c = s.srv.connect()
    c.ok("scene.create", {"name": "ff"})
    # More loads at once than libuv's pool has threads: none may hold one.
    t0 = time.monotonic()
    reqs = [c.request("scene.load", {"scene": "ff", "file": "fifo.snap"}) for _ in range(8)]
    c.send_raw(b"".join(mock.dumps(r).encode() + b"\n" for r in reqs))
    got = [c.recv_response(timeout=10)[0] for _ in reqs]
    s.check(all((g.get("error") or {}).get("code") == E_PARAMS and
                (g["error"].get("data") or {}).get("path") == "file" for g in got),
            "8 loads of a FIFO are refused with -32602 naming file", mock.short(got[:1]))
    s.check("not a regular file" in (got[0].get("error") or {}).get("message", ""),
            "the message says why", mock.short(got[0]))
    s.check(time.monotonic() - t0 < 5, "and at once")
    expect_error(s, c, "scene.set", {"scene": "ff", "patch": {"objects": [
        {"shape": "mesh", "file": "fifo.obj"}]}}, E_PARAMS, "objects.0.file", "a FIFO mesh")
    expect_error(s, c, "scene.set", {"scene": "ff", "patch": {"volumes": [
        {"source": "file", "file": "fifo.u8", "format": "u8", "dims": [2, 2, 2]}]}},
        E_PARAMS, "volumes.0.file", "a FIFO volume file")
    # The pool is free: a real save and load still work.
    c.ok("scene.save", {"scene": "ff", "file": "ff.snap"})
    c.ok("scene.load", {"scene": "ff", "file": "ff.snap"})
    c.ok("scene.delete", {"name": "ff"})


# --------------------------------------------------------------------------------------------
# Finding 13: stale temporary files


@T
def stale_temporary_files_removed(s):
    base = tempfile.mkdtemp(prefix="volfx-stale-")
    old = time.time() - 3600
    stale = ["%s0123456789abcdef" % TEMP_PREFIX, "deep/er/%sfedcba9876543210" % TEMP_PREFIX]
    kept = ["%saaaaaaaaaaaaaaaa" % TEMP_PREFIX,       # fresh: a write may be under way
            "%sbad" % TEMP_PREFIX, ".other", "plain.tmp",  # other names
            ".hidden/%s1111111111111111" % TEMP_PREFIX]    # hidden directories are not entered
    for n in stale + kept:
        put(os.path.join(base, n), b"x" * 100)
        if "aaaa" not in n:
            os.utime(os.path.join(base, n), (old, old))
    with mock.Server(s.bin, data_dir=base) as srv:
        left = [n for n in stale + kept if os.path.exists(os.path.join(base, n))]
        s.eq(left, kept, "at start-up, stale temporary files are removed, and only they")
        # Beside a file about to be written.
        put(os.path.join(base, "sub", TEMP_PREFIX + "2222222222222222"), b"y")
        os.utime(os.path.join(base, "sub", TEMP_PREFIX + "2222222222222222"), (old, old))
        c = srv.connect()
        c.ok("scene.save", {"file": "sub/x.snap"})
        s.eq(sorted(os.listdir(os.path.join(base, "sub"))), ["x.snap"],
             "a save removes stale temporary files beside its target, and leaves none")
    # A save killed part-way leaves a temporary file of the pattern: 1M particles make a 24 MiB
    # snapshot, long enough in the writing to be caught.
    before = set(os.listdir(base))
    srv = mock.Server(s.bin, data_dir=base).start()
    leftover = None
    try:
        c = srv.connect(timeout=120)
        c.ok("scene.set", {"patch": {"fluid": {
            "enabled": True, "bounds": {"min": [-10, 0, -10], "max": [10, 20, 10]},
            "max_particles": 1 << 20, "initial": [
                {"origin": [-6.4, 0.1, -6.4], "spacing": 0.1, "nx": 128, "nz": 128,
                 "count": 1 << 20}]}}}, timeout=120)
        for attempt in range(5):
            c.send(c.request("scene.save", {"file": "big.snap"}))
            t0 = time.monotonic()
            while time.monotonic() - t0 < 20 and not leftover:
                names = [x for x in os.listdir(base) if TEMP_RE.match(x) and x not in before]
                if names:
                    os.kill(srv.pid, signal.SIGKILL)
                    leftover = names[0]
                elif os.path.exists(os.path.join(base, "big.snap")):
                    break
            if leftover:
                break
            c.recv_response(timeout=60)
            os.unlink(os.path.join(base, "big.snap"))
    finally:
        srv.kill()
    if leftover and os.path.exists(os.path.join(base, leftover)):
        with mock.Server(s.bin, data_dir=base):
            s.check(os.path.exists(os.path.join(base, leftover)),
                    "the killed save's fresh temporary file is kept at start-up (it could be "
                    "another writer's)")
        os.utime(os.path.join(base, leftover), (old, old))
        with mock.Server(s.bin, data_dir=base):
            s.check(not os.path.exists(os.path.join(base, leftover)),
                    "once stale, the next start-up removes it")
    else:
        s.note("no save was caught part-way by kill -9 (the writes were too quick)")
    shutil.rmtree(base, ignore_errors=True)


# --------------------------------------------------------------------------------------------
# Finding 14: the checksum


def mutations(data, rng, count):
    head_len = data.index(b"\n") + 1
    out = []
    for i in range(count):
        b = bytearray(data)
        kind = i % 4
        if kind in (0, 1):  # A bit flipped: in the header, or anywhere.
            at = rng.randrange(head_len if kind == 0 else len(b))
            b[at] ^= 1 << rng.randrange(8)
            what = "bit flip at %d" % at
        else:  # Junk inserted: in the header, or anywhere.
            at = rng.randrange(head_len if kind == 2 else len(b) + 1)
            junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 9)))
            b[at:at] = junk
            what = "%d junk bytes at %d" % (len(junk), at)
        out.append((what, bytes(b)))
    return out


@T
def damaged_snapshots_do_not_load(s):
    d = s.srv.data_dir
    c = s.srv.connect(timeout=60)
    c.ok("scene.create", {"name": "mut"})
    c.ok("scene.set", {"scene": "mut", "patch": {
        "camera": {"fov_y": 37}, "cloud": {"enabled": True, "grid": [8, 8, 8], "smoothing": 0}}})
    pts = [(0.1 * i, 0.2, -0.1 * i) for i in range(5)]
    c.ok("fluid.set_particles", {"scene": "mut", "positions": base64.b64encode(
        struct.pack("<15f", *[x for p in pts for x in p])).decode()})
    c.ok("sim.step", {"scene": "mut", "steps": 3}, timeout=60)
    orig = snapshot_of(c, "mut", d, "orig.snap")
    head = json.loads(orig.split(b"\n", 1)[0])
    s.check(isinstance(head.get("crc32"), int), "the header holds a crc32", mock.short(head))
    s.eq([x["name"] for x in head["sections"]], ["cloud", "fluid"], "both sections are there")
    c.ok("scene.load", {"scene": "mut", "file": "orig.snap"})
    ref = snapshot_of(c, "mut", d, "ref.snap")
    s.eq(ref, orig, "a load and a save give the same bytes")

    # The checksum is of the values, not their spelling: spaces in the header change nothing.
    line, rest = orig.split(b"\n", 1)
    spaced = json.dumps(json.loads(line), indent=1).replace("\n", " ").encode() + b"\n" + rest
    put(os.path.join(d, "spaced.snap"), spaced)
    c.ok("scene.load", {"scene": "mut", "file": "spaced.snap"})
    s.eq(snapshot_of(c, "mut", d, "out.snap"), ref, "a header respelled loads the same state")
    # Older snapshots have no checksum, and still load.
    h = json.loads(line)
    del h["crc32"]
    put(os.path.join(d, "old.snap"), json.dumps(h).encode() + b"\n" + rest)
    c.ok("scene.load", {"scene": "mut", "file": "old.snap"})
    s.eq(snapshot_of(c, "mut", d, "out.snap"), ref, "a snapshot without crc32 loads")

    rng = random.Random(17)
    refused, same, changed, internal = 0, 0, [], []
    for what, data in mutations(orig, rng, 160):
        put(os.path.join(d, "m.snap"), data)
        r = c.call("scene.load", {"scene": "mut", "file": "m.snap"})[0]
        if "error" in r:
            refused += 1
            if r["error"]["code"] == E_INTERNAL:
                internal.append((what, r))
            continue
        out = snapshot_of(c, "mut", d, "out.snap")
        if out == ref:
            same += 1
        else:
            changed.append(what)
            c.ok("scene.load", {"scene": "mut", "file": "orig.snap"})
    print("    160 damaged snapshots: %d refused, %d loaded the same state" % (refused, same))
    s.eq(changed, [], "no damaged snapshot loads a different state")
    s.eq(internal, [], "none is answered -32603")
    s.check(refused >= 150, "nearly all are refused", refused)
    # The answer names the damage.
    b = bytearray(orig)
    b[-3] ^= 0x10
    put(os.path.join(d, "m.snap"), bytes(b))
    e = expect_error(s, c, "scene.load", {"scene": "mut", "file": "m.snap"}, E_PARAMS, "file",
                     "a flipped bit in the fluid section").get("error") or {}
    s.check("checksum" in e.get("message", ""), "the message says the checksum does not match",
            e.get("message"))
    c.ok("scene.delete", {"name": "mut"})


# --------------------------------------------------------------------------------------------
# Finding 16: what clients name wrongly is not an internal error


@T
def client_mistakes_are_not_internal_errors(s):
    d = s.srv.data_dir
    c = s.srv.connect()
    c.ok("scene.create", {"name": "cm"})
    long_name = "n" * 245 + ".snap"
    r, _ = c.ok("scene.save", {"scene": "cm", "file": long_name})
    s.eq(r.get("file"), long_name, "a 250-byte name is saved")
    c.ok("scene.load", {"scene": "cm", "file": long_name})
    expect_error(s, c, "scene.load", {"scene": "cm", "file": "m" * 250}, E_NOT_FOUND, "file",
                 "a missing 250-byte name")
    expect_error(s, c, "scene.save", {"scene": "cm", "file": "d/" + "n" * 248}, E_NOT_FOUND,
                 "file", "a 250-byte name in a missing directory")
    put(os.path.join(d, "plain.txt"), b"text")
    for m in ("scene.save", "scene.load"):
        e = expect_error(s, c, m, {"scene": "cm", "file": "plain.txt/x.json"}, E_PARAMS, "file",
                         "%s of plain.txt/x.json" % m).get("error") or {}
        s.check("not a directory" in e.get("message", ""), "the message says why",
                e.get("message"))
    expect_error(s, c, "scene.set", {"scene": "cm", "patch": {"objects": [
        {"shape": "mesh", "file": "plain.txt/x.obj"}]}}, E_PARAMS, "objects.0.file",
        "a mesh under a plain file")
    os.mkdir(os.path.join(d, "adir"))
    for m in ("scene.save", "scene.load"):
        e = expect_error(s, c, m, {"scene": "cm", "file": "adir"}, E_PARAMS, "file",
                         "%s of a directory" % m).get("error") or {}
        s.check("is a directory" in e.get("message", ""), "the message says why",
                e.get("message"))
    expect_error(s, c, "scene.set", {"scene": "cm", "patch": {"objects": [
        {"shape": "mesh", "file": "adir"}]}}, E_PARAMS, "objects.0.file", "a directory as a mesh")
    with open(os.path.join(d, "huge.snap"), "wb") as f:
        f.truncate((256 << 20) + 1)
    e = expect_error(s, c, "scene.load", {"scene": "cm", "file": "huge.snap"}, E_PARAMS, "file",
                     "a snapshot over 256 MiB").get("error") or {}
    s.check("256 MiB" in e.get("message", ""), "the message names the limit", e.get("message"))
    os.unlink(os.path.join(d, "huge.snap"))
    # A link as the target of a save is refused, not replaced; the file it names is untouched.
    put(os.path.join(d, "target.snap"), b"kept")
    os.symlink("target.snap", os.path.join(d, "lnk.snap"))
    expect_error(s, c, "scene.save", {"scene": "cm", "file": "lnk.snap"}, E_PARAMS, "file",
                 "a save over a link")
    with open(os.path.join(d, "target.snap"), "rb") as f:
        s.eq(f.read(), b"kept", "the link's target is untouched")
    s.check(os.path.islink(os.path.join(d, "lnk.snap")), "the link is still a link")
    s.check(E_INTERNAL not in s.codes_seen, "no request of this suite was answered -32603")
    c.ok("scene.delete", {"name": "cm"})


if __name__ == "__main__":
    sys.exit(suite.main())
