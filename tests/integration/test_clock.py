#!/usr/bin/env python3
"""
The frame-indexed clock: a scene's state at frame N (the fluid's particles, the cloud's cells
and density, the animated waves, the document) is the same bits however the N steps were
taken: one sim.step of N, N steps of one, uneven groups, a snapshot saved part-way and loaded
into another scene or another process, or sim.play ticks followed by sim.pause. Checked on
the fluid with its initial block and with emitters, on both cloud rules (Dobashi with wind
and its own seed, Kuromiya), and on waves animated toward targets and by keyframes.

    python3 tests/integration/test_clock.py --bin build/bin
"""

import hashlib
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_clock", timeout_s=420)
suite.server_args = []
T = suite.test

N = 24

# Scene variants: a preset and a patch. Each exercises one part of the state.
VARIANTS = {
    # The demo: the fluid pool, a Dobashi cloud with wind, a keyframed wave.
    "demo": ("demo", {}),
    # Emitters filling a small tank: what each step emits depends on the frame alone.
    "emitters": ("paper-001-flow", {
        "fluid": {"max_particles": 1500, "initial": [], "emitters": [
            {"shape": "sphere", "position": [0, 2.5, 0], "radius": 0.4, "rate": 1800,
             "velocity": [0.5, -1, 0]},
            {"shape": "box", "position": [0.8, 2.0, 0.3], "size": [0.5, 0.3, 0.5], "rate": 700,
             "velocity": [0, -2, 0]}]}}),
    # A Kuromiya cloud: it stops changing once no cell is active.
    "kuromiya": ("demo", {"fluid": {"enabled": False},
                          "cloud": {"rules": "kuromiya", "grid": [32, 24, 24], "seed": 11,
                                    "steps_per_frame": 3, "init": {"steps": 4}}}),
    # A Dobashi cloud of another seed, wind and several automaton steps a frame.
    "dobashi": ("paper-003", {"cloud": {"grid": [40, 32, 32], "seed": 77, "wind": 0.37,
                                        "steps_per_frame": 2, "smoothing": 0.8}}),
    # Waves moving toward targets (a position and a unit direction) and keyframes.
    "waves": ("paper-000", {}),
}


def wave_patch(c, name):
    """Adds toward-target animations to the first wave of 'name'."""
    w = c.ok("scene.get", {"scene": name, "path": "waves.0"})[0]
    w["animate"] = [
        {"field": "center", "target": [w["center"][0] + 0.7, w["center"][1] - 0.3, 0.2],
         "rate": 0.37},
        {"field": "direction", "target": [0, 0.6, 0.8], "rate": 1.3},
        {"field": "radius", "keys": [{"t": 0, "value": 0.5}, {"t": 0.3, "value": 0.9}],
         "interp": "smooth", "loop": True},
    ]
    c.ok("scene.set", {"scene": name, "path": "waves.0", "value": w})


def make(c, name, variant):
    preset, patch = VARIANTS[variant]
    c.ok("scene.create", {"name": name, "preset": preset})
    if patch:
        c.ok("scene.set", {"scene": name, "patch": patch})
    if variant == "waves":
        wave_patch(c, name)


def state(c, name):
    """Everything that makes the scene's state, as comparable values."""
    doc = c.ok("scene.get", {"scene": name})[0]
    doc["sim"].pop("playing", None)
    out = {"doc": doc}
    if doc.get("fluid", {}).get("enabled"):
        for field in ("positions", "velocities"):
            r, att = c.ok("fluid.get_particles", {"scene": name, "field": field})
            out[field] = (r["count"], hashlib.sha256(att or b"").hexdigest())
    if doc.get("cloud", {}).get("enabled"):
        for field in ("cld", "hum", "act", "density"):
            r, att = c.ok("cloud.get_cells", {"scene": name, "field": field})
            out["cloud." + field] = (r["step"], hashlib.sha256(att or b"").hexdigest())
    return out


def compare(s, got, want, what):
    for k in sorted(set(got) | set(want)):
        s.eq(got.get(k), want.get(k), "%s: %s" % (what, k))


def pipelined_steps(c, name, groups):
    """Sends sim.step calls back to back, then reads every answer."""
    ids = []
    for n in groups:
        req = c.request("sim.step", {"scene": name, "steps": n})
        c.send(req)
        ids.append(req["id"])
    for i in ids:
        resp, _ = c.recv_response(timeout=120)
        if resp.get("id") != i or "error" in resp:
            raise mock.CheckError("sim.step answer %s: %s" % (i, mock.short(resp)))


def groupings(s, variant):
    c = s.srv.connect(timeout=120)
    base = "g-%s" % variant
    make(c, base + "-one", variant)
    c.ok("sim.step", {"scene": base + "-one", "steps": N}, timeout=120)
    want = state(c, base + "-one")
    s.check(want["doc"]["sim"]["frame"] == N, "%s: at frame %d" % (variant, N))

    make(c, base + "-single", variant)
    pipelined_steps(c, base + "-single", [1] * N)
    compare(s, state(c, base + "-single"), want, "%s: %d single steps" % (variant, N))

    make(c, base + "-uneven", variant)
    for n in (7, 5, 12):
        c.ok("sim.step", {"scene": base + "-uneven", "steps": n}, timeout=120)
    compare(s, state(c, base + "-uneven"), want, "%s: steps of 7, 5, 12" % variant)

    make(c, base + "-snap", variant)
    c.ok("sim.step", {"scene": base + "-snap", "steps": 10}, timeout=120)
    c.ok("scene.save", {"scene": base + "-snap", "file": base + ".snap"})
    make(c, base + "-loaded", variant)
    c.ok("sim.step", {"scene": base + "-loaded", "steps": 3}, timeout=120)
    c.ok("scene.load", {"scene": base + "-loaded", "file": base + ".snap"})
    c.ok("sim.step", {"scene": base + "-loaded", "steps": N - 10}, timeout=120)
    compare(s, state(c, base + "-loaded"), want, "%s: a snapshot at 10, then %d" % (variant, N - 10))
    c.close()
    return want


_wanted = {}


@T
def grouping_of_steps(s):
    for v in VARIANTS:
        _wanted[v] = groupings(s, v)
    # The checks above must be able to fail: a scene one step further is not the same.
    c = s.srv.connect(timeout=120)
    for v in ("demo", "emitters", "dobashi"):
        make(c, "plus-" + v, v)
        c.ok("sim.step", {"scene": "plus-" + v, "steps": N + 1}, timeout=120)
        got = state(c, "plus-" + v)
        got["doc"]["sim"] = _wanted[v]["doc"]["sim"]
        s.check(got != _wanted[v], "%s: one step more changes the state" % v)
    c.close()


@T
def another_process(s):
    """A snapshot carried to a second volfxd continues to the same bits."""
    c = s.srv.connect(timeout=120)
    with mock.Server(s.bin, data_dir=s.srv.data_dir) as other:
        c2 = other.connect(timeout=120)
        for v in ("demo", "emitters", "kuromiya"):
            want = _wanted.get(v)
            if want is None:
                s.fail("%s: grouping_of_steps ran first" % v)
                continue
            name = "p-" + v
            make(c2, name, v)
            c2.ok("scene.load", {"scene": name, "file": "g-%s.snap" % v})
            c2.ok("sim.step", {"scene": name, "steps": N - 10}, timeout=120)
            compare(s, state(c2, name), want, "%s: continued in another process" % v)
        c2.close()
    c.close()


@T
def play_then_pause(s):
    """sim.play ticks (the fluid and the cloud may fall behind while a job runs) and sim.pause
    leave the scene exactly where sim.step to the same frame does."""
    c = s.srv.connect(timeout=120)
    for v in ("demo", "emitters"):
        name = "play-" + v
        make(c, name, v)
        c.ok("sim.play", {"scene": name, "rate": 400})
        time.sleep(0.6)
        r, _ = c.ok("sim.pause", {"scene": name}, timeout=120)
        frame = int(r["frame"])
        s.check(frame > 5, "%s: play took steps" % v, frame)
        got = state(c, name)
        ref = "ref-" + v
        make(c, ref, v)
        c.ok("sim.step", {"scene": ref, "steps": frame}, timeout=120)
        compare(s, got, state(c, ref), "%s: played to frame %d, paused" % (v, frame))
    c.close()


if __name__ == "__main__":
    sys.exit(suite.main())
