#!/usr/bin/env python3
"""
render.sequence, job.list and job.cancel against a real volfxd: frames stepped and written as
numbered files under the data directory, each byte-equal to what `render` gives for a fresh
copy of the scene stepped to the same frame by sim.step (so the steps, the fluid's included,
land before each frame); job.progress notifications in order; a job that outlives its
connection; cancellation; and bad requests refused with data.path while nothing is written.

    python3 tests/integration/test_sequence.py --bin build/bin
"""

import os
import struct
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, expect_error  # noqa: E402

E_BUSY, E_LIMIT, E_NOT_FOUND = -32002, -32003, -32004

suite = mock.Suite("test_sequence", timeout_s=400)
suite.server_args = []
T = suite.test

SIZE = {"width": 48, "height": 32}


def png_size(data):
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def wait_job(s, c, job_id, timeout=120):
    """Reads job.progress notifications of 'job_id' until it ends; returns them all."""
    got = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg, _ = c.recv_notification(timeout=deadline - time.monotonic())
        if msg.get("method") != "job.progress":
            continue
        p = msg.get("params", {})
        if p.get("id") != job_id:
            continue
        got.append(p)
        if p.get("state") != "running":
            return got
    s.fail("job %s ends within %d s" % (job_id, timeout))
    return got


def files_in(s, d):
    path = os.path.join(s.srv.data_dir, d)
    return sorted(os.listdir(path)) if os.path.isdir(path) else []


@T
def frames_match_sim_step(s):
    """Each file equals a render of the same frame reached by sim.step on a fresh scene."""
    c = s.srv.connect()
    for preset, name in (("paper-000", "w"), ("demo", "d")):
        c.ok("scene.create", {"name": name, "preset": preset})
        r, _ = c.ok("render.sequence", dict(SIZE, scene=name, first=2, last=7, step=2,
                                            dir="seq/" + name), timeout=60)
        s.eq(r.get("total"), 3, "%s: frames 2, 4, 6 (7 is not on the step)" % preset)
        s.eq(r.get("files"), "seq/%s/frame_%%06d.png" % name, "%s: file pattern" % preset)
        notes = wait_job(s, c, r["id"])
        s.eq([n.get("done") for n in notes], [1, 2, 3], "%s: progress counts" % preset)
        s.eq([n.get("state") for n in notes], ["running", "running", "done"],
             "%s: states, the last one ending the job" % preset)
        s.eq(notes[-1].get("last"), "seq/%s/frame_000006.png" % name, "%s: last file" % preset)
        s.eq(files_in(s, "seq/" + name),
             ["frame_000002.png", "frame_000004.png", "frame_000006.png"],
             "%s: the files written" % preset)
        frame, _ = c.ok("scene.get", {"scene": name, "path": "sim.frame"})
        s.eq(frame, 6, "%s: the scene was left at the last frame" % preset)
        # The reference: a fresh copy stepped by sim.step, rendered by render.
        ref = name + "_ref"
        c.ok("scene.create", {"name": ref, "preset": preset})
        frame = 0
        for f in (2, 4, 6):
            c.ok("sim.step", {"scene": ref, "steps": f - frame}, timeout=60)
            frame = f
            _, want = c.ok("render", dict(SIZE, scene=ref), timeout=60)
            with open(os.path.join(s.srv.data_dir, "seq", name, "frame_%06d.png" % f),
                      "rb") as fh:
                got = fh.read()
            s.eq(png_size(got), (48, 32), "%s frame %d: a 48x32 PNG" % (preset, f))
            s.check(got == want, "%s frame %d: equal to render after sim.step" % (preset, f),
                    "%d against %d bytes" % (len(got), len(want)))
        # The frames differ: the scene moves.
        a = open(os.path.join(s.srv.data_dir, "seq", name, "frame_000002.png"), "rb").read()
        b = open(os.path.join(s.srv.data_dir, "seq", name, "frame_000006.png"), "rb").read()
        s.check(a != b, "%s: frames 2 and 6 differ" % preset)
        for n in (name, ref):
            c.ok("scene.delete", {"name": n})


@T
def raw_formats(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "raw", "preset": "paper-000"})
    r, _ = c.ok("render.sequence", dict(SIZE, scene="raw", first=0, last=1, dir="raw",
                                        format="f32", aov="depth"))
    notes = wait_job(s, c, r["id"])
    s.eq(notes[-1].get("state") if notes else None, "done", "the job ends done: %s" % notes[-1:])
    names = files_in(s, "raw")
    s.eq(names, ["frame_000000.f32", "frame_000001.f32"], "f32 files")
    for n in names:
        s.eq(os.path.getsize(os.path.join(s.srv.data_dir, "raw", n)), 48 * 32 * 4,
             "%s: one float per pixel" % n)
    c.ok("scene.delete", {"name": "raw"})


@T
def list_cancel_and_closed_connection(s):
    a = s.srv.connect()
    a.ok("scene.create", {"name": "long", "preset": "paper-000"})
    r, _ = a.ok("render.sequence", dict(SIZE, scene="long", first=0, last=100000, dir="long"))
    jid = r["id"]
    # A second job on the same scene waits its turn.
    expect_error(s, a, "render.sequence", dict(SIZE, scene="long", first=200000, last=200001,
                                               dir="long2"), E_BUSY, "scene")
    first, _ = a.recv_notification(timeout=60)
    s.eq(first.get("method"), "job.progress", "progress arrives")
    a.close()  # The job belongs to the server, not to this connection.
    b = s.srv.connect()
    time.sleep(0.5)
    jobs, _ = b.ok("job.list")
    mine = [j for j in jobs.get("jobs", []) if j.get("id") == jid]
    s.check(mine and mine[0].get("state") == "running", "the job runs on without its client",
            str(jobs))
    done_before = mine[0].get("done", 0) if mine else 0
    time.sleep(0.5)
    jobs, _ = b.ok("job.list")
    mine = [j for j in jobs.get("jobs", []) if j.get("id") == jid]
    s.check(mine and mine[0].get("done", 0) > done_before, "and keeps writing frames",
            str(mine))
    st, _ = b.ok("stats")
    s.eq(st.get("jobs"), 1, "stats counts the running job")
    res, _ = b.ok("job.cancel", {"id": jid})
    s.eq(res.get("state"), "cancelled", "job.cancel ends it")
    time.sleep(0.5)  # Work in flight lands, then nothing more.
    n = len(files_in(s, "long"))
    time.sleep(1.0)
    s.eq(len(files_in(s, "long")), n, "no files after the cancel")
    s.check(n >= 2, "frames were written before the cancel", str(n))
    jobs, _ = b.ok("job.list")
    mine = [j for j in jobs.get("jobs", []) if j.get("id") == jid]
    s.check(mine and mine[0].get("state") == "cancelled", "job.list shows it cancelled",
            str(mine))
    st, _ = b.ok("stats")
    s.eq(st.get("jobs"), 0, "and stats no longer counts it")
    expect_error(s, b, "job.cancel", {"id": 999999}, E_NOT_FOUND, "id")
    b.ok("scene.delete", {"name": "long"})


@T
def cli_sequence(s):
    """`volfx sequence` starts the job, prints each file with -v and exits 0 when it is done."""
    c = s.srv.connect()
    c.ok("scene.create", {"name": "cli", "preset": "paper-000"})
    exe = os.path.join(s.bin, "volfx")
    p = subprocess.run([exe, "--port", str(s.srv.port), "--scene", "cli", "sequence", "1", "3",
                        "--dir", "cli/shots", "-W", "40", "-H", "30", "-v"],
                       capture_output=True, timeout=120)
    out = p.stdout.decode("utf-8", "replace")
    s.eq(p.returncode, 0, "volfx sequence exits 0 (%s)" % p.stderr.decode("utf-8", "replace"))
    s.check("1/3 cli/shots/frame_000001.png" in out and "3/3 cli/shots/frame_000003.png" in out,
            "it prints each file", out)
    s.check("done, 3 of 3 frames" in out, "and the end", out)
    s.eq(files_in(s, "cli/shots"), ["frame_%06d.png" % f for f in (1, 2, 3)], "the files")
    p = subprocess.run([exe, "--port", str(s.srv.port), "--scene", "cli", "sequence", "0", "3",
                        "--dir", "cli/again"], capture_output=True, timeout=120)
    s.eq(p.returncode, 1, "a refused job exits 1")
    s.check("path first" in p.stderr.decode("utf-8", "replace"), "naming the path",
            p.stderr.decode("utf-8", "replace"))
    c.ok("scene.delete", {"name": "cli"})


@T
def scene_deleted_mid_job(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "gone", "preset": "paper-000"})
    r, _ = c.ok("render.sequence", dict(SIZE, scene="gone", first=0, last=100000, dir="gone"))
    c.recv_notification(timeout=60)
    c.ok("scene.delete", {"name": "gone"})
    notes = wait_job(s, c, r["id"])
    s.eq(notes[-1].get("state") if notes else None, "failed", "the job fails")
    s.check("deleted" in (notes[-1].get("error", "") if notes else ""), "saying why",
            str(notes[-1:]))


@T
def shutdown_fails_the_job(s):
    """server.shutdown during a job: its client gets a last job.progress, failed with a reason,
    before the connection closes."""
    with mock.Server(s.bin) as srv:
        c = srv.connect()
        c.ok("scene.create", {"name": "long", "preset": "demo"})
        r, _ = c.ok("render.sequence", dict(SIZE, scene="long", first=0, last=100000,
                                            dir="long"))
        job = r.get("id")
        c.recv_notification(timeout=60)
        other = srv.connect()
        other.ok("server.shutdown", {})
        last = None
        try:
            while True:
                msg, _ = c.recv_notification(timeout=30)
                if msg.get("method") == "job.progress" and msg.get("params", {}).get("id") == job:
                    last = msg.get("params")
        except (mock.Closed, OSError):
            pass
        s.eq((last or {}).get("state"), "failed", "the last job.progress says failed")
        s.check("shutting down" in (last or {}).get("error", ""), "and why", mock.short(last))
        s.eq(srv.wait_exit(15), 0, "the server exits cleanly")


@T
def bad_requests(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "bad", "preset": "paper-000"})
    base = dict(SIZE, scene="bad", first=0, last=3, dir="bad")
    cases = [
        (dict(base, last=-1), E_PARAMS, "last"),
        (dict(base, first=5, last=3), E_PARAMS, "last"),
        (dict(base, step=0), E_PARAMS, "step"),
        (dict(base, dir="../out"), E_PARAMS, "dir"),
        (dict(base, dir="/tmp/x"), E_PARAMS, "dir"),
        (dict(base, dir=""), E_PARAMS, "dir"),
        ({k: v for k, v in base.items() if k != "dir"}, E_PARAMS, "dir"),
        (dict(base, format="f32"), E_PARAMS, "format"),
        (dict(base, width=100000), E_LIMIT, "width"),
        (dict(base, camera={"fov_y": -3}), E_PARAMS, "camera.fov_y"),
        (dict(base, scene="nosuch"), E_NOT_FOUND, "scene"),
    ]
    for params, code, path in cases:
        expect_error(s, c, "render.sequence", params, code, path)
    s.eq(c.ok("scene.get", {"scene": "bad", "path": "sim.frame"})[0], 0,
         "refused jobs did not step the scene")
    # A scene past 'first' cannot go back.
    c.ok("sim.step", {"scene": "bad", "steps": 5})
    expect_error(s, c, "render.sequence", dict(base, first=2, last=8), E_PARAMS, "first")
    c.ok("sim.play", {"scene": "bad", "rate": 30})
    expect_error(s, c, "render.sequence", dict(base, first=100, last=101), E_PARAMS, "scene")
    c.ok("sim.pause", {"scene": "bad"})
    s.eq(files_in(s, "bad"), [], "nothing written by refused jobs")
    frame, _ = c.ok("scene.get", {"scene": "bad", "path": "sim.frame"})
    s.check(frame >= 5, "the scene kept its clock", str(frame))
    c.ok("scene.delete", {"name": "bad"})


if __name__ == "__main__":
    sys.exit(suite.main())
