#!/usr/bin/env python3
"""
The limits on scenes, simulation work and jobs (docs/protocol.md, server.info's limits):

- scenes (limits.scenes) and their estimated simulation memory (limits.scene_bytes): a
  scene.create, scene.set, scene.load or fluid.set_particles past them is -32003 naming the
  field, and nothing changes;
- animation keys of one document (limits.keyframes);
- a long sim.step runs in slices: another scene's render is answered meanwhile, scene.delete
  and sim.pause stop it after the slice in flight, SIGTERM ends the server within seconds, and
  more automaton steps than limits.automaton_steps is refused up front;
- render.sequence and sim.bake count frames in 64 bits (a frame past 2^32 is that frame), write
  at most limits.job_frames files and limits.job_bytes bytes, and leave
  limits.data_reserve_bytes free on the data directory's file system.

Servers with small limits are started with --config. Scenes and grids are small: the long
steppings are sized from the cost of one step measured first, for a few seconds of work.

    python3 tests/integration/test_limits.py --bin build/bin
"""

import base64
import json
import os
import signal
import struct
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_LIMIT, E_NOT_FOUND, expect_error  # noqa: E402

suite = mock.Suite("test_limits", timeout_s=500)
suite.server_args = []
T = suite.test

FRAME = {"width": 48, "height": 32}
# A cloud whose frames cost tens of milliseconds: a long sim.step of it is a few seconds.
BIG_CLOUD = {"cloud": {"enabled": True, "rules": "dobashi", "grid": [96, 96, 96],
                       "steps_per_frame": 8, "init": {"steps": 0}}}


def config_server(s, limits):
    """A second volfxd with 'limits' in its config file."""
    fd, path = tempfile.mkstemp(prefix="volfx-limits-", suffix=".json")
    with os.fdopen(fd, "w") as f:
        json.dump({"limits": limits}, f)
    srv = mock.Server(s.bin, "--config", path)
    srv.start()
    os.unlink(path)
    return srv


def big_cloud(c, name):
    """A scene with BIG_CLOUD, and the seconds one of its frames takes (measured)."""
    c.ok("scene.create", {"name": name})
    c.ok("scene.set", {"scene": name, "patch": BIG_CLOUD}, timeout=120)
    c.ok("sim.step", {"scene": name, "steps": 2}, timeout=120)
    t0 = time.monotonic()
    c.ok("sim.step", {"scene": name, "steps": 4}, timeout=120)
    return (time.monotonic() - t0) / 4


def steps_for(per_frame, seconds):
    return max(8, min(100000, int(seconds / max(per_frame, 1e-4))))


# ---- scenes and their memory ----

@T
def scene_count(s):
    with config_server(s, {"scenes": 3}) as srv:
        c = srv.connect()
        s.eq(c.ok("server.info")[0]["limits"]["scenes"], 3, "server.info reports limits.scenes")
        c.ok("scene.create", {"name": "a"})
        c.ok("scene.create", {"name": "b"})
        expect_error(s, c, "scene.create", {"name": "c"}, E_LIMIT, "name")
        names = [x["name"] for x in c.ok("scene.list")[0]["scenes"]]
        s.check("c" not in names, "a refused scene.create adds no scene", names)
        c.ok("scene.delete", {"name": "a"})
        c.ok("scene.create", {"name": "c"})


@T
def scene_memory(s):
    # 8 MiB: a 64³ cloud (about 5.5 MB) fits, a second one or a 128³ one does not.
    with config_server(s, {"scene_bytes": 8 << 20, "line_bytes": 4 << 20}) as srv:
        c = srv.connect(timeout=120)
        s.eq(c.ok("server.info")[0]["limits"]["scene_bytes"], 8 << 20,
             "server.info reports limits.scene_bytes")
        c.ok("scene.create", {"name": "a"})
        c.ok("scene.set", {"scene": "a", "patch": {"cloud": {"enabled": True, "grid": [64, 64, 64]}}},
             timeout=120)
        v = c.ok("scene.list")[0]["scenes"]
        expect_error(s, c, "scene.set", {"scene": "a", "path": "cloud.grid", "value": [128, 128, 128]},
                     E_LIMIT, "cloud.grid")
        s.eq(c.ok("scene.get", {"scene": "a", "path": "cloud.grid"})[0], [64, 64, 64],
             "a refused scene.set leaves the grid")
        s.eq(c.ok("scene.list")[0]["scenes"], v, "a refused scene.set changes no version")
        # The fluid: emitters fill it to max_particles, which is what counts.
        c.ok("scene.create", {"name": "f"})
        expect_error(s, c, "scene.set", {"scene": "f", "patch": {"fluid": {
            "enabled": True, "max_particles": 1000000,
            "emitters": [{"position": [0, 1, 0], "rate": 100}]}}}, E_LIMIT, "fluid.max_particles")
        s.eq(c.ok("scene.get", {"scene": "f", "path": "fluid.enabled"})[0], False,
             "a refused fluid change leaves the fluid")
        # Particles set directly count too.
        c.ok("scene.set", {"scene": "f", "patch": {"fluid": {"enabled": True}}})
        n = 30000  # 30000 × 164 bytes ≈ 4.7 MB beside the cloud's 5.5 MB
        pos = base64.b64encode(struct.pack("<%df" % (3 * n), *([0.0, 0.5, 0.0] * n))).decode()
        expect_error(s, c, "fluid.set_particles", {"scene": "f", "positions": pos}, E_LIMIT,
                     "positions")
        s.eq(c.ok("scene.get", {"scene": "f", "path": "fluid.count"})[0], 0,
             "a refused fluid.set_particles sets none")
        # A save of the 64³ scene loaded into a second scene would pass the budget too.
        c.ok("scene.save", {"scene": "a", "file": "a.snap"})
        c.ok("scene.create", {"name": "b"})
        expect_error(s, c, "scene.load", {"scene": "b", "file": "a.snap"}, E_LIMIT, "cloud.grid")
        # Deleting the first makes room.
        c.ok("scene.delete", {"name": "a"})
        c.ok("scene.load", {"scene": "b", "file": "a.snap"}, timeout=120)


@T
def keyframes(s):
    with config_server(s, {"keyframes": 64}) as srv:
        c = srv.connect()
        keys = [{"t": 0.1 * i, "value": 1 + i % 3} for i in range(40)]
        wave = {"a": 1, "animate": [{"field": "a", "keys": keys}]}
        c.ok("scene.set", {"scene": "main", "patch": {"waves": [wave]}})
        more = {"a": 1, "animate": [{"field": "b", "keys": keys[:10]},
                                    {"field": "a", "keys": keys[:30]}]}
        expect_error(s, c, "scene.set", {"scene": "main", "patch": {"waves": [wave, more]}},
                     E_LIMIT, "waves.1.animate.1.keys")
        s.eq(len(c.ok("scene.get", {"scene": "main", "path": "waves"})[0]), 1,
             "a refused scene.set leaves the waves")


# ---- long simulation work ----

@T
def automaton_steps(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "auto"})
    c.ok("scene.set", {"scene": "auto", "patch": {"cloud": {"enabled": True, "grid": [8, 8, 8],
                                                            "steps_per_frame": 64}}})
    limit = c.ok("server.info")[0]["limits"]["automaton_steps"]
    frame = c.ok("scene.get", {"scene": "auto", "path": "sim.frame"})[0]
    expect_error(s, c, "sim.step", {"scene": "auto", "steps": limit // 64 + 1}, E_LIMIT, "steps")
    s.eq(c.ok("scene.get", {"scene": "auto", "path": "sim.frame"})[0], frame,
         "a refused sim.step leaves the clock")
    c.close()


@T
def render_between_slices(s):
    c = s.srv.connect(timeout=120)
    other = s.srv.connect(timeout=120)
    per = big_cloud(c, "long")
    other.ok("scene.create", {"name": "other"})
    n = steps_for(per, 3.0)
    req = c.request("sim.step", {"scene": "long", "steps": n})
    t0 = time.monotonic()
    c.send(req)
    time.sleep(0.3)
    waits = []
    for _ in range(5):
        t1 = time.monotonic()
        other.ok("render", dict(FRAME, scene="other", width=64, height=64))
        waits.append(time.monotonic() - t1)
    s.check(c.quiet(0.01), "the sim.step of %d steps is still running while the other scene's "
            "renders are answered" % n, "renders took %s s" % ["%.3f" % w for w in waits])
    resp, _ = c.recv_response(timeout=300)
    took = time.monotonic() - t0
    s.eq(resp.get("result", {}).get("frame"), 6 + n, "the long sim.step takes every step")
    s.note("sim.step of %d frames (%.1f ms each) took %.1f s; another scene's 64x64 render "
           "waited %s ms" % (n, per * 1000, took, ["%.0f" % (w * 1000) for w in waits]))
    c.close()
    other.close()


@T
def delete_stops_stepping(s):
    c = s.srv.connect(timeout=120)
    other = s.srv.connect(timeout=120)
    per = big_cloud(c, "gone")
    req = c.request("sim.step", {"scene": "gone", "steps": steps_for(per, 20.0)})
    c.send(req)
    time.sleep(0.5)
    other.ok("scene.delete", {"name": "gone"})
    t0 = time.monotonic()
    resp, _ = c.recv_response(timeout=60)
    took = time.monotonic() - t0
    s.eq(resp.get("error", {}).get("code"), E_NOT_FOUND, "a sim.step of a deleted scene ends "
         "with -32004")
    s.check(took < 3, "the sim.step ends soon after scene.delete", "%.2f s" % took)
    s.note("sim.step answered %.0f ms after scene.delete" % (took * 1000))
    c.close()
    other.close()


@T
def pause_stops_stepping(s):
    c = s.srv.connect(timeout=120)
    other = s.srv.connect(timeout=120)
    per = big_cloud(c, "paused")
    n = steps_for(per, 20.0)
    req = c.request("sim.step", {"scene": "paused", "steps": n})
    c.send(req)
    time.sleep(0.5)
    t0 = time.monotonic()
    p = other.ok("sim.pause", {"scene": "paused"}, timeout=60)[0]
    resp, _ = c.recv_response(timeout=60)
    took = time.monotonic() - t0
    r = resp.get("result", {})
    s.eq(r.get("cut_short"), "sim.pause", "a sim.step cut short by sim.pause says so")
    s.check(6 <= r.get("frame", -1) < 6 + n, "it reached part of its steps", r)
    s.check(took < 3, "sim.step ends soon after sim.pause", "%.2f s" % took)
    # The clock and the cells agree: the cells are at the frame the clock shows.
    frame = c.ok("scene.get", {"scene": "paused", "path": "sim.frame"})[0]
    s.eq(p.get("frame"), frame, "sim.pause reports the clock")
    cells = c.ok("cloud.get_cells", {"scene": "paused"})[0]
    s.eq(cells["step"], frame * 8, "the cloud's cells are at the clock's frame")
    c.close()
    other.close()


@T
def sigterm_during_stepping(s):
    with mock.Server(s.bin) as srv:
        c = srv.connect(timeout=120)
        per = big_cloud(c, "term")
        req = c.request("sim.step", {"scene": "term", "steps": steps_for(per, 60.0)})
        c.send(req)
        time.sleep(0.5)
        t0 = time.monotonic()
        srv.proc.send_signal(signal.SIGTERM)
        rc = srv.wait_exit(20)
        took = time.monotonic() - t0
        s.eq(rc, 0, "volfxd exits 0 on SIGTERM during a long sim.step")
        s.check(took < 3, "volfxd exits within seconds of SIGTERM", "%.2f s" % took)
        s.note("SIGTERM during a long sim.step: exit after %.0f ms" % (took * 1000))


# ---- jobs ----

def wait_job(s, c, job_id, timeout=120):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg, _ = c.recv_notification(timeout=deadline - time.monotonic())
        p = msg.get("params", {})
        if msg.get("method") == "job.progress" and p.get("id") == job_id and \
                p.get("state") != "running":
            return p
    s.fail("job %s ends within %d s" % (job_id, timeout))
    return {}


@T
def frames_past_2_32(s):
    c = s.srv.connect(timeout=120)
    far = 2 ** 32 + 5
    # From frame 0: 2^32 + 5 steps, not 5.
    c.ok("scene.create", {"name": "far0"})
    r = c.ok("render.sequence", dict(FRAME, scene="far0", first=far, last=far, dir="far0"))[0]
    p = wait_job(s, c, r["id"], timeout=200)
    s.check(p.get("state") == "done", "a sequence from frame 0 to frame 2^32+5 is done", p)
    s.eq(c.ok("scene.get", {"scene": "far0", "path": "sim.frame"})[0], far,
         "the scene is at frame 2^32+5")
    s.check(os.path.exists(os.path.join(s.srv.data_dir, "far0", "frame_%d.png" % far)),
            "the file is named for frame 2^32+5")
    # A scene whose frames differ (keyframed waves), moved close first: the file holds what
    # render gives at that frame.
    for name in ("far", "far-ref"):
        c.ok("scene.create", {"name": name, "preset": "paper-000"})
        dt = c.ok("scene.get", {"scene": name, "path": "sim.dt"})[0]
        c.ok("scene.set", {"scene": name, "patch": {"sim": {"frame": 2 ** 32, "time": 2 ** 32 * dt}}})
    r = c.ok("render.sequence", dict(FRAME, scene="far", first=far, last=far, dir="far"))[0]
    p = wait_job(s, c, r["id"])
    s.check(p.get("state") == "done", "the sequence at frame 2^32+5 is done", p)
    c.ok("sim.step", {"scene": "far-ref", "steps": 5})
    want = c.ok("render", dict(FRAME, scene="far-ref"))[1]
    path = os.path.join(s.srv.data_dir, "far", "frame_%d.png" % far)
    got = open(path, "rb").read() if os.path.exists(path) else b""
    s.check(got == want, "frame_%d.png holds frame 2^32+5" % far, "%d bytes" % len(got))
    c.close()


@T
def frames_per_job(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "many"})
    limit = c.ok("server.info")[0]["limits"]["job_frames"]
    expect_error(s, c, "render.sequence", dict(FRAME, scene="many", first=0, last=limit, dir="many"),
                 E_LIMIT, "last")
    expect_error(s, c, "render.sequence",
                 dict(FRAME, scene="many", first=0, last=2 ** 53 - 1, dir="many"), E_LIMIT, "last")
    expect_error(s, c, "sim.bake", {"scene": "many", "dir": "many", "last": 2 ** 53 - 1, "every": 1},
                 E_LIMIT, "last")
    s.check(not os.path.exists(os.path.join(s.srv.data_dir, "many")),
            "a refused job makes no directory")
    c.close()


@T
def bytes_per_job(s):
    # 1 MiB a job: four 128x128 rgbaf32 frames (256 KiB each) fit, the fifth does not.
    with config_server(s, {"job_bytes": 1 << 20}) as srv:
        c = srv.connect(timeout=120)
        r = c.ok("render.sequence", {"first": 0, "last": 7, "dir": "b", "width": 128,
                                     "height": 128, "format": "rgbaf32"})[0]
        p = wait_job(s, c, r["id"])
        s.check(p.get("state") == "failed", "a job past limits.job_bytes fails", p)
        s.check("limits.job_bytes" in p.get("error", ""), "its error names limits.job_bytes",
                p.get("error"))
        s.check(p.get("done") == 4, "the files within the limit are written", p)
        s.eq(len(os.listdir(os.path.join(srv.data_dir, "b"))), 4, "four files")


@T
def data_reserve(s):
    # A reserve larger than any disk: nothing can be written.
    with config_server(s, {"data_reserve_bytes": 1e15}) as srv:
        c = srv.connect(timeout=120)
        r = c.ok("render.sequence", dict(FRAME, first=0, last=2, dir="r"))[0]
        p = wait_job(s, c, r["id"])
        s.check(p.get("state") == "failed", "a frame that would eat into the reserve fails the job", p)
        s.check("limits.data_reserve_bytes" in p.get("error", ""),
                "its error names limits.data_reserve_bytes", p.get("error"))
        s.eq(os.listdir(os.path.join(srv.data_dir, "r")), [], "no file is written")
        r = c.ok("sim.bake", {"dir": "k", "last": 3, "every": 2})[0]
        p = wait_job(s, c, r["id"])
        s.check("limits.data_reserve_bytes" in p.get("error", ""),
                "a bake's snapshot fails the same way", p)
        e = expect_error(s, c, "scene.save", {"file": "x.snap"}, E_LIMIT, "file")
        s.check("limits.data_reserve_bytes" in json.dumps(e),
                "scene.save past the reserve is -32003 naming it", e)
        s.check(not os.path.exists(os.path.join(srv.data_dir, "x.snap")), "and writes nothing")


if __name__ == "__main__":
    sys.exit(suite.main())
