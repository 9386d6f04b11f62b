#!/usr/bin/env python3
"""
The particle fluid against a real volfxd: fluid.set_particles / fluid.get_particles round-trip
bit-exact, sim.step moves the particles under gravity inside the bounds, the renderer draws
them (beauty and depth), fluid.initial seeds the paper's Table 1 lattice, fluid.initial is laid out
off the loop thread (other clients are answered meanwhile, requests behind the change wait for
it), emitters fill the fluid over sim.step and sim.play up to fluid.max_particles
(deterministically), bad inputs,
emitters and blocks are refused with data.path and nothing changed, and a scene with a live
fluid can be deleted and the server shut down cleanly.

    python3 tests/integration/test_fluid.py --bin build/bin
"""

import base64
import json
import math
import os
import struct
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, expect_error  # noqa: E402

E_LIMIT = -32003

suite = mock.Suite("test_fluid", timeout_s=400)
suite.server_args = []
T = suite.test

H = 0.61


def block(n_side=10, spacing=H / 2, base=(-1.4, 0.0, -1.4)):
    """n_side³ particles on a cubic lattice starting at 'base'."""
    pts = []
    for k in range(n_side):
        for j in range(n_side):
            for i in range(n_side):
                pts.append((base[0] + i * spacing, base[1] + j * spacing, base[2] + k * spacing))
    return pts


def pack(pts):
    return struct.pack("<%df" % (3 * len(pts)), *[c for p in pts for c in p])


def b64(pts):
    return base64.b64encode(pack(pts)).decode()


def unpack(data):
    vals = struct.unpack("<%df" % (len(data) // 4), data)
    return [vals[i:i + 3] for i in range(0, len(vals), 3)]


def fresh(c, name):
    c.ok("scene.create", {"name": name})


@T
def round_trip(s):
    c = s.srv.connect()
    fresh(c, "rt")
    pts = block()
    r, _ = c.ok("fluid.set_particles", {"scene": "rt", "positions": b64(pts)})
    s.eq(r.get("count"), 1000, "set_particles reports the count")
    r, att = c.ok("fluid.get_particles", {"scene": "rt"})
    s.eq(r.get("count"), 1000, "get_particles count")
    s.eq(r.get("field"), "positions", "get_particles field defaults to positions")
    s.eq((r.get("attachment") or {}).get("format"), "f32", "get_particles format")
    s.eq((r.get("attachment") or {}).get("bytes"), 12000, "get_particles bytes")
    s.check(att == pack(pts), "positions come back bit-exact")
    r, att = c.ok("fluid.get_particles", {"scene": "rt", "field": "velocities"})
    s.check(att == bytes(12000), "velocities default to rest")
    vel = [(0.5, -0.25, 1.0)] * 1000
    c.ok("fluid.set_particles",
         {"scene": "rt", "positions": b64(pts), "velocities": b64(vel)})
    r, att = c.ok("fluid.get_particles", {"scene": "rt", "field": "velocities"})
    s.check(att == pack(vel), "velocities come back bit-exact")
    s.eq(c.ok("scene.get", {"scene": "rt", "path": "fluid.count"})[0], 1000,
         "fluid.count follows the particles")
    # fluid.count is read-only.
    c.ok("scene.set", {"scene": "rt", "path": "fluid.count", "value": 5})
    s.eq(c.ok("scene.get", {"scene": "rt", "path": "fluid.count"})[0], 1000,
         "a written fluid.count is replaced by the real count")
    r, _ = c.ok("fluid.get_particles", {"scene": "rt", "encoding": "base64"})
    s.check(base64.b64decode(r.get("data", "")) == pack(pts), "base64 encoding of get_particles")
    c.ok("scene.delete", {"name": "rt"})


@T
def step_under_gravity(s):
    c = s.srv.connect()
    fresh(c, "st")
    pts = block()
    c.ok("fluid.set_particles", {"scene": "st", "positions": b64(pts)})
    # Disabled: sim.step leaves the particles alone.
    c.ok("sim.step", {"scene": "st", "steps": 2})
    _, att = c.ok("fluid.get_particles", {"scene": "st"})
    s.check(att == pack(pts), "a disabled fluid does not move")
    c.ok("scene.set", {"scene": "st", "path": "fluid.enabled", "value": True})
    r, _ = c.ok("sim.step", {"scene": "st", "steps": 10}, timeout=120)
    s.eq(r.get("frame"), 12, "sim.step answers with the clock")
    r, att = c.ok("fluid.get_particles", {"scene": "st"})
    s.eq(r.get("count"), 1000, "count unchanged by stepping")
    got = unpack(att)
    s.check(all(math.isfinite(v) for p in got for v in p), "every position finite")
    s.check(all(-5 <= v <= 5 for p in got for v in p), "every particle inside the bounds")
    y0 = sum(p[1] for p in pts) / len(pts)
    y1 = sum(p[1] for p in got) / len(got)
    s.check(y1 < y0 - 1e-3, "the fluid moved down under gravity", "mean y %g -> %g" % (y0, y1))
    _, vatt = c.ok("fluid.get_particles", {"scene": "st", "field": "velocities"})
    vy = sum(v[1] for v in unpack(vatt)) / 1000
    s.check(vy < 0, "the fluid falls", "mean vy %g" % vy)
    s.check(all(math.isfinite(v) for p in unpack(vatt) for v in p), "every velocity finite")
    # A read written right behind sim.step, on the same connection, sees the steps.
    reqs = [c.request("sim.step", {"scene": "st", "steps": 2}),
            c.request("fluid.get_particles", {"scene": "st", "encoding": "base64"})]
    c.send_raw(b"".join(mock.dumps(q).encode() + b"\n" for q in reqs))
    c.recv_response(timeout=120)
    behind, _ = c.recv_response(timeout=120)
    _, alone = c.ok("fluid.get_particles", {"scene": "st"})
    seen = base64.b64decode((behind.get("result") or {}).get("data", ""))
    s.check(seen == alone, "the read behind sim.step sees the stepped particles")
    s.check(seen != att, "which moved")

    # Drawn: the frame differs from one without the fluid layer, and depth sees it.
    params = {"scene": "st", "width": 64, "height": 64, "format": "png"}
    _, with_fluid = c.ok("render", params, timeout=120)
    layers = ["objects", "volumes", "cloud", "waves"]
    _, without = c.ok("render", dict(params, layers=layers), timeout=120)
    s.check(with_fluid is not None and with_fluid[:4] == b"\x89PNG", "render gives a PNG")
    s.check(with_fluid != without, "the fluid is visible in the render")
    dparams = {"scene": "st", "width": 64, "height": 64, "format": "f32", "aov": "depth"}
    _, d1 = c.ok("render", dparams, timeout=120)
    c.ok("scene.set", {"scene": "st", "path": "fluid.enabled", "value": False})
    _, d0 = c.ok("render", dparams, timeout=120)
    f1 = sum(1 for v in struct.unpack("<%df" % (len(d1) // 4), d1) if math.isfinite(v))
    f0 = sum(1 for v in struct.unpack("<%df" % (len(d0) // 4), d0) if math.isfinite(v))
    s.check(f1 > f0, "the depth AOV includes the fluid", "%d vs %d finite pixels" % (f1, f0))

    # sim.play steps it too; pausing leaves it consistent.
    c.ok("scene.set", {"scene": "st", "path": "fluid.enabled", "value": True})
    c.ok("sim.play", {"scene": "st", "rate": 60})
    time.sleep(0.5)
    c.ok("sim.pause", {"scene": "st"})
    r, att = c.ok("fluid.get_particles", {"scene": "st"})
    s.eq(r.get("count"), 1000, "count unchanged by sim.play")
    s.check(all(math.isfinite(v) for p in unpack(att) for v in p), "finite after sim.play")


@T
def bad_inputs(s):
    c = s.srv.connect()
    fresh(c, "bad")
    pts = block(5)
    c.ok("fluid.set_particles", {"scene": "bad", "positions": b64(pts)})
    before = c.ok("fluid.get_particles", {"scene": "bad"})[1]
    doc = c.ok("scene.get", {"scene": "bad"})[0]
    p = {"scene": "bad"}
    expect_error(s, c, "fluid.set_particles", dict(p, positions="!!not base64!!"), E_PARAMS,
                 "positions", "bad base64")
    expect_error(s, c, "fluid.set_particles",
                 dict(p, positions=base64.b64encode(bytes(13)).decode()), E_PARAMS, "positions",
                 "13 bytes")
    expect_error(s, c, "fluid.set_particles",
                 dict(p, positions=b64([(0, 0, 0), (float("nan"), 0, 0)])), E_PARAMS,
                 "positions", "NaN")
    expect_error(s, c, "fluid.set_particles",
                 dict(p, positions=b64([(0, 0, 0), (0, 6, 0)])), E_PARAMS, "positions",
                 "outside the bounds")
    expect_error(s, c, "fluid.set_particles",
                 dict(p, positions=b64([(0, 0, 0)]), velocities=b64([(0, 0, 0)] * 2)), E_PARAMS,
                 "velocities", "velocities of another length")
    expect_error(s, c, "fluid.set_particles",
                 dict(p, positions=b64([(0, 0, 0)]), velocities=b64([(0, float("inf"), 0)])),
                 E_PARAMS, "velocities", "infinite velocity")
    expect_error(s, c, "fluid.get_particles", dict(p, field="colour"), E_PARAMS, "field",
                 "unknown field")
    expect_error(s, c, "scene.set",
                 {"scene": "bad", "path": "fluid.bounds.max", "value": [5, -6, 5]}, E_PARAMS,
                 "fluid.bounds.max", "bounds max below min")
    # Parameters the float32 solver would round to a denormal or to 0 (and then make NaNs of).
    for path, value in (("fluid.particle_mass", 1e-40), ("fluid.rest_density", 1e-300),
                        ("fluid.stiffness", 1e-46)):
        expect_error(s, c, "scene.set", {"scene": "bad", "path": path, "value": value}, E_PARAMS,
                     path, "%s of %g" % (path, value))
    # The tank may not shrink past the particles it holds (they could never be stepped).
    expect_error(s, c, "scene.set",
                 {"scene": "bad", "patch": {"fluid": {"bounds": {"min": [-1, -1, -1],
                                                                 "max": [-0.9, 1, 1]}}}},
                 E_PARAMS, "fluid.bounds", "bounds that leave particles outside")
    s.check(c.ok("fluid.get_particles", {"scene": "bad"})[1] == before,
            "refused inputs left the particles unchanged")
    s.eq(c.ok("scene.get", {"scene": "bad"})[0], doc, "refused inputs left the document unchanged")
    c.ok("scene.delete", {"name": "bad"})


@T
def snapshot_carries_particles(s):
    """scene.save writes the particles (positions and velocities) in a fluid section, and
    scene.load brings them back exactly, into the same scene or another; a bad section is
    refused and nothing changes."""
    c = s.srv.connect()
    fresh(c, "snapf")
    c.ok("scene.set", {"scene": "snapf", "path": "fluid.enabled", "value": True})
    pts = block(6)
    c.ok("fluid.set_particles", {"scene": "snapf", "positions": b64(pts)})
    c.ok("sim.step", {"scene": "snapf", "steps": 3}, timeout=120)
    saved = {f: c.ok("fluid.get_particles", {"scene": "snapf", "field": f})[1]
             for f in ("positions", "velocities")}
    r, _ = c.ok("scene.save", {"scene": "snapf", "file": "fluid.snap"})
    path = os.path.join(s.srv.data_dir, "fluid.snap")
    with open(path, "rb") as f:
        data = f.read()
    head = json.loads(data.split(b"\n", 1)[0])
    secs = {x.get("name"): x for x in head.get("sections") or []}
    s.eq((secs.get("fluid") or {}).get("count"), len(pts), "the fluid section counts the particles")
    s.eq((secs.get("fluid") or {}).get("bytes"), 24 * len(pts), "positions and velocities, f32")
    s.check(data.endswith(saved["positions"] + saved["velocities"]),
            "the section holds the particles' bytes as fluid.get_particles gives them")
    s.eq(r.get("bytes"), len(data), "save reports every byte")
    c.ok("fluid.set_particles", {"scene": "snapf", "positions": b64(pts[:10])})
    c.ok("scene.load", {"scene": "snapf", "file": "fluid.snap"})
    for f in ("positions", "velocities"):
        got = c.ok("fluid.get_particles", {"scene": "snapf", "field": f})[1]
        s.check(got == saved[f], "load restores the %s" % f)
    s.eq(c.ok("scene.get", {"scene": "snapf", "path": "fluid.count"})[0], len(pts),
         "fluid.count follows")
    # Into another scene; a step from there is the step from the saved state.
    c.ok("sim.step", {"scene": "snapf"}, timeout=120)
    stepped = c.ok("fluid.get_particles", {"scene": "snapf"})[1]
    c.ok("scene.create", {"name": "snapg"})
    c.ok("scene.load", {"scene": "snapg", "file": "fluid.snap"})
    s.check(c.ok("fluid.get_particles", {"scene": "snapg"})[1] == saved["positions"],
            "another scene loads the same particles")
    c.ok("sim.step", {"scene": "snapg"}, timeout=120)
    s.check(c.ok("fluid.get_particles", {"scene": "snapg"})[1] == stepped,
            "and steps them as the scene they were saved from")
    # A scene saved without particles loads without them.
    c.ok("scene.create", {"name": "snap0"})
    c.ok("scene.save", {"scene": "snap0", "file": "empty.snap"})
    c.ok("scene.load", {"scene": "snapg", "file": "empty.snap"})
    s.eq(c.ok("scene.get", {"scene": "snapg", "path": "fluid.count"})[0], 0,
         "a snapshot of no particles leaves none")
    # Bad sections: cut short, a NaN, particles outside the saved bounds.
    before = c.ok("fluid.get_particles", {"scene": "snapf"})[1]
    body = data[len(data) - 24 * len(pts):]
    line = data[:len(data) - len(body)]
    bads = {"short.snap": data[:-4],
            "nan.snap": line + body[:8] + struct.pack("<f", float("nan")) + body[12:]}
    hd = json.loads(line)
    hd["scene"]["fluid"]["bounds"] = {"min": [-1, -1, -1], "max": [-0.9, 1, 1]}
    bads["outside.snap"] = (json.dumps(hd) + "\n").encode() + body
    for name, content in bads.items():
        with open(os.path.join(s.srv.data_dir, name), "wb") as f:
            f.write(content)
        expect_error(s, c, "scene.load", {"scene": "snapf", "file": name}, E_PARAMS, "file",
                     "a snapshot %s" % name)
    s.check(c.ok("fluid.get_particles", {"scene": "snapf"})[1] == before,
            "refused snapshots left the particles")
    for name in ("snapf", "snapg", "snap0"):
        c.ok("scene.delete", {"name": name})


def table1_layers(n, origin, spacing, nx=24, nz=24):
    """The paper's Table 1 set-up as fluid.initial describes it: layers of nx x nz, x fastest,
    then z, stacked upwards until n particles (float32 as the server rounds them)."""
    pts = []
    for i in range(n):
        ix, iz, iy = i % nx, i // nx % nz, i // (nx * nz)
        pts.append(tuple(struct.unpack("<f", struct.pack("<f", origin[c] + spacing * k))[0]
                         for c, k in enumerate((ix, iy, iz))))
    return pts


@T
def initial_blocks(s):
    c = s.srv.connect()
    fresh(c, "ini")
    origin = [-3.5, -4.8, -3.5]
    c.ok("scene.set", {"scene": "ini", "path": "fluid.initial",
                       "value": [{"origin": origin, "count": 4096}]})
    s.eq(c.ok("scene.get", {"scene": "ini", "path": "fluid.count"})[0], 4096,
         "fluid.initial gives 4096 particles")
    r, att = c.ok("fluid.get_particles", {"scene": "ini"})
    got = unpack(att)
    want = table1_layers(4096, origin, H / 2)
    s.eq(len(got), 4096, "get_particles returns the block")
    s.check(got == want, "24x24 layers of spacing h/2 stacked to 4096, x fastest, then z, then y",
            "first %s, last %s" % (got[:1], got[-1:]))
    top = max(p[1] for p in got)
    s.check(abs(top - (origin[1] + 7 * H / 2)) < 1e-5, "7 full layers and a partial eighth",
            "top layer at y = %g" % top)

    # Unrelated edits keep the particles; set_particles replaces them; only a new value of
    # fluid.initial seeds again.
    c.ok("fluid.set_particles", {"scene": "ini", "positions": b64(block(4))})
    c.ok("scene.set", {"scene": "ini", "path": "fluid.viscosity", "value": 20})
    s.eq(c.ok("scene.get", {"scene": "ini", "path": "fluid.count"})[0], 64,
         "editing another field keeps set_particles' particles")
    c.ok("scene.set", {"scene": "ini", "path": "fluid.initial.0.count", "value": 100})
    r, att = c.ok("fluid.get_particles", {"scene": "ini"})
    s.check(unpack(att) == want[:100], "a changed fluid.initial seeds the particles again")
    # A second block after the first, with its own spacing, nx, nz and velocity.
    blocks = [{"origin": origin, "count": 100},
              {"origin": [1, 0, 1], "spacing": 0.2, "nx": 3, "nz": 2, "count": 7,
               "velocity": [0, 1.5, 0]}]
    c.ok("scene.set", {"scene": "ini", "path": "fluid.initial", "value": blocks})
    r, att = c.ok("fluid.get_particles", {"scene": "ini"})
    got = unpack(att)
    s.eq(len(got), 107, "two blocks")
    s.check(got[100:] == table1_layers(7, [1, 0, 1], 0.2, 3, 2), "the second block's lattice",
            str(got[100:]))
    _, vatt = c.ok("fluid.get_particles", {"scene": "ini", "field": "velocities"})
    vel = unpack(vatt)
    s.check(vel[:100] == [(0, 0, 0)] * 100 and vel[100:] == [(0, 1.5, 0)] * 7,
            "each block's velocity")
    # Lattice points inside the fluid's colliders are left out: a sphere of radius 0.5 at the
    # centre of a 10 x 10 x 10 block, a box in one corner, and a plane below y = -1.
    c.ok("scene.set", {"scene": "ini", "patch": {
        "objects": [{"shape": "sphere", "position": [0, 0, 0]},
                    {"shape": "box", "position": [1.3, 1.3, 1.3], "rotation": [0, 45, 0]},
                    {"shape": "plane", "position": [0, -1.01, 0]},
                    {"shape": "tetrahedron", "position": [-1.3, 1.3, 1.3]}],
        "fluid": {"initial": [{"origin": [-1.35, -1.35, -1.35], "spacing": 0.3, "nx": 10,
                               "nz": 10, "count": 1000}]}}})
    _, att = c.ok("fluid.get_particles", {"scene": "ini"})
    got = unpack(att)
    lattice = table1_layers(1000, [-1.35] * 3, 0.3, 10, 10)
    co, sn = math.cos(math.radians(45)), math.sin(math.radians(45))

    def in_box(p):
        d = [p[k] - 1.3 for k in range(3)]
        q = (co * d[0] - sn * d[2], d[1], sn * d[0] + co * d[2])  # R_y(45)^T d
        return all(abs(v) < 0.5 for v in q)

    want = [p for p in lattice
            if math.dist(p, (0, 0, 0)) >= 0.5 and not in_box(p) and p[1] >= -1.01]
    s.check(len(want) < 1000 - 100, "the objects cover lattice points", str(len(want)))
    s.eq(len(got), len(want), "points inside the sphere, box and plane are left out")
    s.check(got == want, "the rest of the lattice, in order")
    s.eq(c.ok("scene.get", {"scene": "ini", "path": "fluid.count"})[0], len(want),
         "fluid.count counts what is left")
    c.ok("scene.set", {"scene": "ini", "patch": {"objects": [], "fluid": {"initial": blocks}}})

    # Simulated and rendered like any particles.
    c.ok("scene.set", {"scene": "ini", "path": "fluid.enabled", "value": True})
    c.ok("sim.step", {"scene": "ini", "steps": 3}, timeout=120)
    s.eq(c.ok("scene.get", {"scene": "ini", "path": "fluid.count"})[0], 107,
         "a stepped block keeps its count")
    c.ok("scene.set", {"scene": "ini", "path": "fluid.initial", "value": []})
    s.eq(c.ok("scene.get", {"scene": "ini", "path": "fluid.count"})[0], 0,
         "an empty fluid.initial removes the particles")
    c.ok("scene.delete", {"name": "ini"})


@T
def laid_out_off_the_loop(s):
    """2^20 lattice points, each tested against 40 objects: a few hundred milliseconds."""
    a = s.srv.connect()
    b = s.srv.connect()
    fresh(a, "big")
    objects = [{"shape": "box", "position": [-4 + 0.2 * i, 7, 4], "scale": [0.1, 0.1, 0.1]}
               for i in range(40)]
    block = {"origin": [-4, 0.01, -4], "spacing": 0.01, "nx": 512, "nz": 512, "count": 1 << 20}
    req = a.request("scene.set", {"scene": "big", "patch": {"objects": objects, "fluid": {
        "max_particles": 1 << 20, "bounds": {"min": [-5, 0, -5], "max": [5, 8, 5]},
        "initial": [block]}}})
    behind = a.request("scene.get", {"scene": "big", "path": "fluid.count"})
    a.send_raw(b"".join(mock.dumps(r).encode() + b"\n" for r in (req, behind)))
    mock.served_meanwhile(s, b, a, "another client is answered while the particles are laid out")
    got = [a.recv_response(timeout=120)[0] for _ in range(2)]
    s.eq([g.get("id") for g in got], [req["id"], behind["id"]], "answered in order")
    s.check("result" in got[0], "the change is made", mock.short(got[0]))
    s.eq(got[1].get("result"), 1 << 20, "the scene.get behind it counts the new particles")
    # The rest of a batch waits too.
    resp = mock.batch(s, a, [
        a.request("scene.get", {"scene": "big", "path": "fluid.count"}),
        a.request("scene.set", {"scene": "big", "path": "fluid.initial.0.count",
                                "value": (1 << 20) - 1}),
        a.request("scene.get", {"scene": "big", "path": "fluid.count"})])
    if resp:
        s.eq([resp[0].get("result"), resp[2].get("result")], [1 << 20, (1 << 20) - 1],
             "the get after the change, in the same batch, sees it")
    # 12 MiB of positions as base64 are encoded off the loop; the same as the attachment.
    req = a.request("fluid.get_particles", {"scene": "big", "encoding": "base64"})
    a.send(req)
    mock.served_meanwhile(s, b, a, "another client is answered while the positions are encoded")
    resp, _ = a.recv_response(timeout=120)
    data = base64.b64decode((resp.get("result") or {}).get("data", ""))
    _, att = a.ok("fluid.get_particles", {"scene": "big"}, timeout=120)
    s.eq(len(data), 12 * ((1 << 20) - 1), "every position")
    s.check(data == att, "base64 and the attachment carry the same positions")
    a.ok("scene.delete", {"name": "big"})


@T
def emitters_fill(s):
    c = s.srv.connect()
    em = {"shape": "sphere", "position": [0, 3, 0], "radius": 0.3, "rate": 600,
          "velocity": [0, -2, 0]}
    # 10 particles a step: the step that reaches 255 adds 5 too many, which go.
    patch = {"fluid": {"enabled": True, "emitters": [em], "max_particles": 255}}
    for name in ("em", "em2"):
        fresh(c, name)
        c.ok("scene.set", {"scene": name, "patch": patch})
    doc = c.ok("scene.get", {"scene": "em", "path": "fluid.emitters"})[0]
    s.eq(doc, [dict(em, size=[0.5, 0.5, 0.5])], "an emitter gets its defaults filled in")
    s.eq(c.ok("scene.get", {"scene": "em", "path": "fluid.count"})[0], 0, "no particles yet")
    r, _ = c.ok("sim.step", {"scene": "em", "steps": 6}, timeout=120)
    s.eq(r.get("frame"), 6, "sim.step answers once the emitter ran")
    # 600 particles/s for 6/60 s: 60 particles.
    s.eq(c.ok("scene.get", {"scene": "em", "path": "fluid.count"})[0], 60,
         "the emitter adds rate x time particles")
    r, att = c.ok("fluid.get_particles", {"scene": "em"})
    got = unpack(att)
    s.eq(r.get("count"), 60, "fluid.get_particles sees the emitted particles")
    s.check(all(math.isfinite(v) for p in got for v in p), "emitted positions finite")
    # Born within 0.3 of (0, 3, 0), faster than rest density allows, so they spread; their
    # centre still falls from there at 2 m/s and more for at most 0.1 s.
    mid = [sum(p[k] for p in got) / len(got) for k in range(3)]
    s.check(abs(mid[0]) < 0.3 and abs(mid[2]) < 0.3 and 2.6 < mid[1] < 3.05,
            "emitted where the emitter is", "centre %s" % mid)
    _, vatt = c.ok("fluid.get_particles", {"scene": "em", "field": "velocities"})
    s.check(sum(v[1] for v in unpack(vatt)) / 60 < -1.5, "emitted moving down")
    # Filling stops at max_particles; the tank keeps them.
    c.ok("sim.step", {"scene": "em", "steps": 40}, timeout=120)
    r, att = c.ok("fluid.get_particles", {"scene": "em"})
    s.eq(r.get("count"), 255, "the emitter stops at fluid.max_particles")
    got = unpack(att)
    s.check(all(-5 <= v <= 5 and math.isfinite(v) for p in got for v in p),
            "emitted particles stay inside the bounds")
    # The same seed and steps give the same particles, bit for bit.
    c.ok("sim.step", {"scene": "em2", "steps": 6}, timeout=120)
    c.ok("sim.step", {"scene": "em2", "steps": 40}, timeout=120)
    s.check(c.ok("fluid.get_particles", {"scene": "em2"})[1] == att,
            "emitting is deterministic for a seed")
    # sim.play emits too.
    fresh(c, "em3")
    c.ok("scene.set", {"scene": "em3", "patch": patch})
    c.ok("sim.play", {"scene": "em3", "rate": 60})
    time.sleep(0.6)
    c.ok("sim.pause", {"scene": "em3"})
    time.sleep(0.3)
    n = c.ok("scene.get", {"scene": "em3", "path": "fluid.count"})[0]
    s.check(n > 0, "sim.play runs the emitters", "count %s" % n)
    for name in ("em", "em2", "em3"):
        c.ok("scene.delete", {"name": name})


@T
def bad_emitters_and_blocks(s):
    c = s.srv.connect()
    fresh(c, "bade")
    c.ok("scene.set", {"scene": "bade", "patch": {"fluid": {
        "emitters": [{"position": [0, 2, 0]}],
        "initial": [{"origin": [-1, -1, -1], "nx": 5, "nz": 5, "count": 50}]}}})
    c.ok("fluid.set_particles", {"scene": "bade", "positions": b64(block(3))})
    before = c.ok("fluid.get_particles", {"scene": "bade"})[1]
    doc = c.ok("scene.get", {"scene": "bade"})[0]
    em = {"position": [0, 0, 0]}
    cases = [
        ({"emitters": [dict(em, position=[0, 5.5, 0])]}, "fluid.emitters.0.position",
         "emitter outside the bounds"),
        ({"emitters": [em, dict(em, shape="cone")]}, "fluid.emitters.1.shape", "unknown shape"),
        ({"emitters": [dict(em, rate=-1)]}, "fluid.emitters.0.rate", "negative rate"),
        (None, None, "infinite radius"),
        ({"emitters": [dict(em, size=[1, 1])]}, "fluid.emitters.0.size", "size of two numbers"),
        ({"emitters": [dict(em, velocity=[0, 1e6, 0])]}, "fluid.emitters.0.velocity.1",
         "velocity out of range"),
        ({"emitters": [dict(em, colour=1)]}, "fluid.emitters.0.colour", "unknown member"),
        ({"emitters": [em] * 17}, "fluid.emitters", "17 emitters"),
        ({"emitters": {"position": [0, 0, 0]}}, "fluid.emitters", "not an array"),
        ({"initial": [{"origin": [0, 0, 0]}]}, "fluid.initial.0.count", "block without count"),
        ({"initial": [{"origin": [0, 0, 0], "count": 0}]}, "fluid.initial.0.count",
         "block of 0 particles"),
        ({"initial": [{"origin": [0, 0, 0], "count": 2.5}]}, "fluid.initial.0.count",
         "fractional count"),
        ({"initial": [{"origin": [0, -6, 0], "count": 1}]}, "fluid.initial.0.origin",
         "block starting outside"),
        ({"initial": [{"origin": [0, 0, 0], "count": 100000}]}, "fluid.initial.0.count",
         "block reaching past the tank's top"),
        ({"initial": [{"origin": [4.9, 0, 0], "count": 2}]}, "fluid.initial.0.count",
         "block reaching past x max"),
        ({"max_particles": 10}, "fluid.initial.0.count", "blocks over max_particles"),
        ({"max_particles": 0}, "fluid.max_particles", "max_particles 0"),
    ]
    for patch, path, what in cases:
        if patch is None:
            # JSON has no infinity: a literal too large for a double reads as one.
            expect_error(s, c, "scene.set", None, E_PARAMS, "fluid.emitters.0.radius", what,
                         raw=(b'{"jsonrpc":"2.0","id":1,"method":"scene.set","params":'
                              b'{"scene":"bade","patch":{"fluid":{"emitters":[{"radius":1e999}]'
                              b'}}}}\n'))
            continue
        expect_error(s, c, "scene.set", {"scene": "bade", "patch": {"fluid": patch}}, E_PARAMS,
                     path, what)
    s.check(c.ok("fluid.get_particles", {"scene": "bade"})[1] == before,
            "refused emitters and blocks left the particles unchanged")
    s.eq(c.ok("scene.get", {"scene": "bade"})[0], doc,
         "refused emitters and blocks left the document unchanged")
    c.ok("scene.delete", {"name": "bade"})


@T
def presets(s):
    """The paper's presets and the demo seed their particles from fluid.initial."""
    c = s.srv.connect()
    for preset, n in (("paper-001", 4096), ("paper-001-16384", 16384),
                      ("paper-001-65536", 65536), ("paper-001-flow", 4096),
                      ("paper-001-flow-16384", 16384)):
        c.ok("scene.create", {"name": preset, "preset": preset})
        f = c.ok("scene.get", {"scene": preset, "path": "fluid"})[0]
        s.eq(f.get("count"), n, "%s holds %d particles" % (preset, n))
        s.check(f.get("enabled") is True and f.get("h") == H and f.get("threshold") == 0.765625,
                "%s: an enabled fluid with the paper's h and T" % preset)
        if not preset.startswith("paper-001-flow"):
            blk = f["initial"][0]
            s.eq((blk["nx"], blk["nz"], blk["spacing"]), (24, 24, 0.305),
                 "%s: layers of 24 x 24 at spacing h/2" % preset)
        c.ok("scene.delete", {"name": preset})
    c.ok("scene.create", {"name": "dm", "preset": "demo"})
    f = c.ok("scene.get", {"scene": "dm", "path": "fluid"})[0]
    s.check(f.get("enabled") is True and f.get("count", 0) > 100, "the demo has a pool of water",
            "count %s" % f.get("count"))
    r, _ = c.ok("sim.step", {"scene": "dm", "steps": 5}, timeout=120)
    _, att = c.ok("fluid.get_particles", {"scene": "dm"})
    lo, hi = f["bounds"]["min"], f["bounds"]["max"]
    s.check(all(math.isfinite(p[k]) and lo[k] <= p[k] <= hi[k] for p in unpack(att)
                for k in range(3)), "the demo's pool stays in its basin")
    c.ok("scene.delete", {"name": "dm"})


@T
def particle_limit(s):
    path = mock.config_file({"limits": {"particles": 100}})
    with mock.Server(s.bin, "--config", path) as srv:
        c = srv.connect()
        fresh(c, "lim")
        c.ok("fluid.set_particles", {"scene": "lim", "positions": b64(block(4))})
        expect_error(s, c, "fluid.set_particles", {"scene": "lim", "positions": b64(block(5))},
                     E_LIMIT, "positions", "over limits.particles")
        s.eq(c.ok("scene.get", {"scene": "lim", "path": "fluid.count"})[0], 64,
             "the refused set left the particles")


@T
def delete_and_shutdown(s):
    with mock.Server(s.bin) as srv:
        c = srv.connect()
        for name in ("d1", "d2"):
            fresh(c, name)
            c.ok("fluid.set_particles", {"scene": name, "positions": b64(block(6))})
            c.ok("scene.set", {"scene": name, "path": "fluid.enabled", "value": True})
            c.ok("sim.step", {"scene": name, "steps": 2}, timeout=120)
        # A step still running when its scene goes away is dropped quietly.
        c.send(c.request("sim.step", {"scene": "d1", "steps": 3}))
        c.send(c.request("scene.delete", {"name": "d1"}))
        c.recv_response(timeout=120)
        c.recv_response(timeout=120)
        c.ok("sim.play", {"scene": "d2", "rate": 120})
        r, _ = c.ok("server.shutdown", {})
        s.eq(r, {"shutting_down": True}, "server.shutdown")
        s.eq(srv.wait_exit(30), 0, "volfxd exits 0 after deleting a fluid scene and shutting down")


if __name__ == "__main__":
    sys.exit(suite.main())
