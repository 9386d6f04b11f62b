#!/usr/bin/env python3
"""
scene.save and scene.load against a real volfxd: a snapshot round-trips the document and the
clock, is written atomically into the data directory, and bad file names (absolute, "..",
hidden, through a link that leads outside, missing) are refused with data.path "file" and
nothing changed.

    python3 tests/integration/test_snapshot.py --bin build/bin
"""

import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_NOT_FOUND, E_PARAMS, expect_error  # noqa: E402

suite = mock.Suite("test_snapshot", timeout_s=300)
suite.server_args = []
T = suite.test


@T
def round_trip(s):
    c = s.srv.connect()
    c.ok("scene.set", {"patch": {"camera": {"fov_y": 33}, "background": [0.1, 0.2, 0.3]}})
    c.ok("sim.step", {"steps": 7})
    saved = c.ok("scene.get", {})[0]
    r, _ = c.ok("scene.save", {"file": "snap1.json"})
    s.eq(r.get("file"), "snap1.json", "save echoes the file")
    path = os.path.join(s.srv.data_dir, "snap1.json")
    s.check(os.path.isfile(path), "the snapshot is in the data directory", path)
    with open(path, "rb") as f:
        data = f.read()
    s.eq(r.get("bytes"), len(data), "save reports the bytes written")
    head = json.loads(data.split(b"\n", 1)[0])
    s.eq(head.get("volfx_snapshot"), 1, "snapshot header version")
    s.eq(head.get("scene"), saved, "the snapshot holds the document")
    leftovers = [n for n in os.listdir(s.srv.data_dir) if ".tmp" in n]
    s.eq(leftovers, [], "no temporary files left behind")

    c.ok("scene.set", {"patch": {"camera": {"fov_y": 70}}})
    c.ok("sim.step", {"steps": 5})
    r, _ = c.ok("scene.load", {"file": "snap1.json"})
    s.eq(r.get("frame"), 7, "load restores the frame")
    s.eq(c.ok("scene.get", {})[0], saved, "load restores the whole document")

    # Into another scene, and into a subdirectory that exists.
    c.ok("scene.create", {"name": "copy"})
    os.mkdir(os.path.join(s.srv.data_dir, "sub"))
    c.ok("scene.save", {"file": "sub/snap2.json"})
    c.ok("scene.load", {"scene": "copy", "file": "sub/snap2.json"})
    s.eq(c.ok("scene.get", {"scene": "copy", "path": "camera.fov_y"})[0], 33,
         "a snapshot loads into another scene")


@T
def concurrent_saves(s):
    """Several connections saving the same file at once all succeed and leave one whole
    snapshot (each writes a temporary file of its own), and a link planted beside it is never
    written through."""
    outside = os.path.join(os.path.dirname(s.srv.data_dir), "outside-%d" % os.getpid())
    with open(outside, "w") as f:
        f.write("untouched")
    for suffix in (".tmp%d" % s.srv.pid, ".tmp", ".tmpXXXXXX"):
        os.symlink(outside, os.path.join(s.srv.data_dir, "same.snap" + suffix))
    conns = [s.srv.connect() for _ in range(4)]
    for i, c in enumerate(conns):
        c.ok("scene.create", {"name": "cs%d" % i})
    for _ in range(10):
        for i, c in enumerate(conns):
            c.send(c.request("scene.save", {"scene": "cs%d" % i, "file": "same.snap"}))
    answers = [c.recv_response(timeout=60)[0] for _ in range(10) for c in conns]
    bad = [a for a in answers if "result" not in a]
    s.check(not bad, "40 concurrent saves of one file all succeed", mock.short(bad[:2]))
    with open(os.path.join(s.srv.data_dir, "same.snap"), "rb") as f:
        head = json.loads(f.read().split(b"\n", 1)[0])
    s.check(head.get("name", "").startswith("cs"), "the file is one whole snapshot")
    with open(outside) as f:
        s.eq(f.read(), "untouched", "no link beside the file was written through")
    leftovers = [n for n in os.listdir(s.srv.data_dir)
                 if n.startswith("same.snap.tmp") and not os.path.islink(
                     os.path.join(s.srv.data_dir, n))]
    s.eq(leftovers, [], "no temporary file is left")
    for i, c in enumerate(conns):
        c.ok("scene.delete", {"name": "cs%d" % i})
        c.close()


@T
def bad_files(s):
    c = s.srv.connect()
    before = c.ok("scene.get", {})[0]
    outside = os.path.join(os.path.dirname(s.srv.data_dir.rstrip("/")), "outside-snap")
    os.makedirs(outside, exist_ok=True)
    os.symlink(outside, os.path.join(s.srv.data_dir, "escape"))
    for name in ("/etc/passwd", "../x.json", "a/../../x.json", ".hidden", "sub/.x", "a//b",
                 "", "x" * 300, "bad name.json", "escape/x.json"):
        expect_error(s, c, "scene.save", {"file": name}, (E_PARAMS, E_NOT_FOUND), "file",
                     "save to %r refused" % name)
        expect_error(s, c, "scene.load", {"file": name}, (E_PARAMS, E_NOT_FOUND), "file",
                     "load from %r refused" % name)
    s.eq(os.listdir(outside), [], "nothing was written outside the data directory")
    expect_error(s, c, "scene.load", {"file": "missing.json"}, E_NOT_FOUND, "file",
                 "a missing snapshot")
    expect_error(s, c, "scene.save", {"file": "nodir/x.json"}, E_NOT_FOUND, "file",
                 "a missing directory")
    # Files that are not snapshots, or hold an invalid scene, change nothing.
    with open(os.path.join(s.srv.data_dir, "junk.json"), "w") as f:
        f.write("not json\n")
    expect_error(s, c, "scene.load", {"file": "junk.json"}, E_PARAMS, "file", "junk file")
    bad = {"volfx_snapshot": 1, "scene": {"camera": {"fov_y": 500}}, "sections": []}
    with open(os.path.join(s.srv.data_dir, "bad.json"), "w") as f:
        f.write(json.dumps(bad) + "\n")
    expect_error(s, c, "scene.load", {"file": "bad.json"}, E_PARAMS, "camera.fov_y",
                 "a snapshot with an invalid scene")
    s.eq(c.ok("scene.get", {})[0], before, "refused loads left the scene unchanged")


@T
def no_data_dir(s):
    with mock.Server(s.bin, data_dir="") as srv:
        c = srv.connect()
        expect_error(s, c, "scene.save", {"file": "x.json"}, E_PARAMS, "file",
                     "save without --data")


if __name__ == "__main__":
    sys.exit(suite.main())
