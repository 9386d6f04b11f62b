#!/usr/bin/env python3
"""
sim.bake against a real volfxd: a bake job steps a scene to its last frame and writes a
snapshot (scene.save's format) at every multiple of 'every' and at the last frame, plus the
manifest bake.json; a snapshot loaded and stepped on equals the bake's later snapshot bit for
bit; a bake resumed from its own snapshot writes the same files; a directory holding another
scene's bake, another interval, a last frame before the scene's, a playing scene and a bad
directory are refused with data.path naming the field; job.list shows the job as a bake.

    python3 tests/integration/test_bake.py --bin build/bin
"""

import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS  # noqa: E402

suite = mock.Suite("test_bake", timeout_s=300)
suite.server_args = []
T = suite.test


def wait_job(s, c, job_id, timeout=120):
    """Reads job.progress notifications until job_id ends; returns the last one's params."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg, _ = c.recv_notification(timeout=deadline - time.monotonic())
        if msg.get("method") != "job.progress":
            continue
        p = msg["params"]
        if p.get("id") == job_id and p.get("state") != "running":
            return p
    raise mock.CheckError("job %s did not end" % job_id)


def files_in(s, d):
    return sorted(os.listdir(os.path.join(s.srv.data_dir, d)))


def snap_bytes(s, d, frame):
    with open(os.path.join(s.srv.data_dir, d, "frame_%06d.snap" % frame), "rb") as f:
        return f.read()


def body_of(data):
    """A snapshot without its header's name (scenes of other names hold the same state)."""
    head, rest = data.split(b"\n", 1)
    h = json.loads(head)
    h.pop("name", None)
    h["scene"]["sim"].pop("playing", None)
    return h, rest


@T
def bake_and_continue(s):
    c = s.srv.connect(timeout=120)
    c.ok("scene.create", {"name": "b1", "preset": "demo"})
    r, _ = c.ok("sim.bake", {"scene": "b1", "dir": "bakes/one", "last": 30, "every": 8})
    s.eq(r.get("total"), 5, "snapshots at 0, 8, 16, 24 and 30")
    s.eq(r.get("files"), "bakes/one/frame_%06d.snap", "the files' pattern")
    end = wait_job(s, c, r["id"])
    s.eq(end.get("state"), "done", "the bake ends done")
    s.eq(end.get("kind"), "bake", "progress names the kind")
    s.eq(files_in(s, "bakes/one"), ["bake.json"] + ["frame_%06d.snap" % f for f in
                                                    (0, 8, 16, 24, 30)],
         "the bake's files, nothing else (no temporary file)")
    frame = c.ok("scene.get", {"scene": "b1", "path": "sim.frame"})[0]
    s.eq(frame, 30, "the scene is left at the last frame")
    with open(os.path.join(s.srv.data_dir, "bakes/one/bake.json")) as f:
        man = json.load(f)
    s.eq(man.get("volfx_bake"), 1, "manifest version")
    s.eq(man.get("every"), 8, "manifest interval")
    doc = c.ok("scene.get", {"scene": "b1"})[0]
    s.check("frame" not in man["scene"]["sim"] and "count" not in man["scene"]["fluid"],
            "the manifest's scene leaves out what the clock moves")
    s.eq(man["scene"]["camera"], doc["camera"], "the manifest holds the document")
    # A snapshot of the bake, loaded and stepped, equals the bake's later snapshot.
    c.ok("scene.create", {"name": "b2", "preset": "demo"})
    c.ok("scene.load", {"scene": "b2", "file": "bakes/one/frame_000016.snap"})
    c.ok("sim.step", {"scene": "b2", "steps": 14}, timeout=120)
    c.ok("scene.save", {"scene": "b2", "file": "b2-30.snap"})
    with open(os.path.join(s.srv.data_dir, "b2-30.snap"), "rb") as f:
        mine = f.read()
    s.check(body_of(mine) == body_of(snap_bytes(s, "bakes/one", 30)),
            "frame 16 of the bake stepped 14 is the bake's frame 30, byte for byte")
    # Resuming: from the bake's frame 16 into the same directory rewrites the same files.
    before = {f: snap_bytes(s, "bakes/one", f) for f in (24, 30)}
    c.ok("scene.load", {"scene": "b2", "file": "bakes/one/frame_000016.snap"})
    r, _ = c.ok("sim.bake", {"scene": "b2", "dir": "bakes/one", "last": 30, "every": 8})
    s.eq(r.get("total"), 3, "a bake resumed at 16 writes 16, 24 and 30")
    s.eq(wait_job(s, c, r["id"]).get("state"), "done", "the resumed bake ends done")
    for f in (24, 30):
        s.check(body_of(snap_bytes(s, "bakes/one", f)) == body_of(before[f]),
                "resumed frame %d is the same" % f)
    jobs = c.ok("job.list", {})[0]["jobs"]
    s.check(jobs and jobs[0].get("kind") == "bake", "job.list shows bakes", jobs[:1])
    c.close()


@T
def refused(s):
    c = s.srv.connect(timeout=120)
    c.ok("scene.create", {"name": "r1", "preset": "paper-001-flow"})
    r, _ = c.ok("sim.bake", {"scene": "r1", "dir": "bakes/flow", "last": 4, "every": 2})
    wait_job(s, c, r["id"])
    # Another scene into the same directory.
    c.ok("scene.create", {"name": "r2", "preset": "paper-001"})
    e = mock.expect_error(s, c, "sim.bake", {"scene": "r2", "dir": "bakes/flow", "last": 4, "every": 2}, E_PARAMS, "dir",
                           "a bake of another scene is refused")["error"]
    s.check("another scene" in e.get("message", ""), "the message says why", e)
    # The same scene, a changed document.
    c.ok("scene.create", {"name": "r3", "preset": "paper-001-flow"})
    c.ok("scene.set", {"scene": "r3", "path": "fluid.viscosity", "value": 3})
    e = mock.expect_error(s, c, "sim.bake", {"scene": "r3", "dir": "bakes/flow", "last": 4, "every": 2}, E_PARAMS, "dir",
                           "a changed document is another scene")["error"]
    # The same scene at another interval.
    c.ok("scene.create", {"name": "r4", "preset": "paper-001-flow"})
    e = mock.expect_error(s, c, "sim.bake", {"scene": "r4", "dir": "bakes/flow", "last": 4, "every": 3}, E_PARAMS, "dir",
                           "another interval is refused")["error"]
    s.check("every 2" in e.get("message", ""), "the message names the interval", e)
    # The same scene at the same interval further on: accepted (a longer shot).
    r, _ = c.ok("sim.bake", {"scene": "r4", "dir": "bakes/flow", "last": 6, "every": 2})
    s.eq(wait_job(s, c, r["id"]).get("state"), "done", "the same bake goes on")
    # A last frame before the scene's.
    e = mock.expect_error(s, c, "sim.bake", {"scene": "r4", "dir": "bakes/x", "last": 2}, E_PARAMS, "last",
                           "last before the scene's frame")["error"]
    for bad in ("", "../up", "/abs", ".hidden"):
        e = mock.expect_error(s, c, "sim.bake", {"scene": "r4", "dir": bad, "last": 10}, E_PARAMS, "dir",
                               "dir %r is refused" % bad)["error"]
    e = mock.expect_error(s, c, "sim.bake", {"scene": "r4", "dir": "bakes/y", "last": 10, "every": 0}, E_PARAMS, "every",
                           "every 0 is refused")["error"]
    c.ok("sim.play", {"scene": "r4"})
    e = mock.expect_error(s, c, "sim.bake", {"scene": "r4", "dir": "bakes/y", "last": 1000}, E_PARAMS, "scene",
                           "a playing scene is refused")["error"]
    c.ok("sim.pause", {"scene": "r4"})
    s.check(not os.path.exists(os.path.join(s.srv.data_dir, "bakes/y/bake.json")),
            "a refused bake writes nothing")
    c.close()


if __name__ == "__main__":
    sys.exit(suite.main())
