#!/usr/bin/env python3
"""
The cellular-automaton cloud against a real volfxd: cloud.set_cells / cloud.get_cells
round-trip exactly, sim.step changes the cells exactly as a naive reference automaton written
here from SPEC 5.4 says, the density after cloud.set_cells matches a direct Gaussian sum,
dobashi clouds are reproducible per seed, bad inputs are refused with data.path and nothing
changed, fresh cells are seeded off the loop thread (other clients are answered meanwhile,
requests behind the change wait for it), and a scene with a stepping cloud can be deleted and
the server shut down cleanly.

    python3 tests/integration/test_cloud.py --bin build/bin
"""

import base64
import json
import math
import os
import random
import struct
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, expect_error  # noqa: E402

E_LIMIT = -32003

suite = mock.Suite("test_cloud", timeout_s=400)
suite.server_args = []
T = suite.test

NX, NY, NZ = 11, 9, 7
N = NX * NY * NZ


def b64(data):
    return base64.b64encode(bytes(data)).decode()


def make(c, name, grid=(NX, NY, NZ), **cloud):
    cfg = {"enabled": True, "grid": list(grid), "smoothing": 0}
    cfg.update(cloud)
    c.ok("scene.create", {"name": name})
    c.ok("scene.set", {"scene": name, "patch": {"cloud": cfg}})


def get(c, scene, field):
    r, att = c.ok("cloud.get_cells", {"scene": scene, "field": field})
    return r, att


def ref_step(hum, act, cld, n):
    """One step of SPEC 5.4, one cell at a time; cells outside the grid read 0."""
    nx, ny, nz = n

    def a(i, j, k):
        if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
            return act[i + nx * (j + ny * k)]
        return 0

    h2, a2, c2 = [0] * len(hum), [0] * len(hum), [0] * len(hum)
    for k in range(nz):
        for j in range(ny):
            for i in range(nx):
                x = i + nx * (j + ny * k)
                f = (a(i + 1, j, k) or a(i - 1, j, k) or a(i, j + 1, k) or a(i, j - 1, k) or
                     a(i, j, k + 1) or a(i, j, k - 1) or a(i - 2, j, k) or a(i, j - 2, k) or
                     a(i, j, k - 2))
                c2[x] = 1 if (cld[x] or act[x]) else 0
                h2[x] = 1 if (hum[x] and not act[x]) else 0
                a2[x] = 1 if (not act[x] and hum[x] and f) else 0
    return h2, a2, c2


def random_cells(rng):
    hum = [1 if rng.random() < 0.6 else 0 for _ in range(N)]
    act = [1 if rng.random() < 0.03 else 0 for _ in range(N)]
    cld = [1 if rng.random() < 0.05 else 0 for _ in range(N)]
    return hum, act, cld


def random_cloud(c, name, seed):
    """Makes scene 'name' with a cloud of random_cells; returns its (hum, act, cld)."""
    make(c, name)
    cells = random_cells(random.Random(seed))
    for field, vals in zip(("hum", "act", "cld"), cells):
        c.ok("cloud.set_cells", {"scene": name, "field": field, "data": b64(vals)})
    return cells


@T
def round_trip(s):
    c = s.srv.connect()
    make(c, "rt")
    r, att = get(c, "rt", "hum")
    s.eq(r.get("dims"), [NX, NY, NZ], "get_cells dims")
    s.eq(r.get("cells"), N, "get_cells cells")
    s.eq((r.get("attachment") or {}).get("format"), "u8", "hum is u8")
    s.eq(len(att or b""), N, "one byte per cell")
    s.check(set(att) <= {0, 1}, "cells are 0 or 1")
    s.check(sum(att) > N // 3, "the default seeding makes about 60% of the cells humid",
            sum(att))
    rng = random.Random(5)
    for field, vals in zip(("hum", "act", "cld"), random_cells(rng)):
        r, _ = c.ok("cloud.set_cells", {"scene": "rt", "field": field, "data": b64(vals)})
        s.eq(r.get("cells"), N, "set_cells %s reports the cells" % field)
        _, att = get(c, "rt", field)
        s.check(att == bytes(vals), "%s comes back exactly" % field)
    # base64 encoding of the answer.
    r, _ = c.ok("cloud.get_cells", {"scene": "rt", "field": "cld", "encoding": "base64"})
    s.check(base64.b64decode(r.get("data", "")) == bytes(vals), "cld as base64 matches")
    dens = [0.25 * (i % 7) for i in range(N)]
    c.ok("cloud.set_cells", {"scene": "rt", "field": "density",
                             "data": b64(struct.pack("<%df" % N, *dens))})
    r, att = get(c, "rt", "density")
    s.eq((r.get("attachment") or {}).get("format"), "f32", "density is f32")
    s.check(att == struct.pack("<%df" % N, *dens), "density comes back exactly")


@T
def steps_match_reference(s):
    c = s.srv.connect()
    hum, act, cld = random_cloud(c, "ref", 11)
    n = (NX, NY, NZ)
    for steps in (1, 3):
        c.ok("sim.step", {"scene": "ref", "steps": steps}, timeout=60)
        for _ in range(steps):
            hum, act, cld = ref_step(hum, act, cld, n)
        for field, want in zip(("hum", "act", "cld"), (hum, act, cld)):
            r, att = get(c, "ref", field)
            s.check(att == bytes(want), "%s after sim.step %d equals the reference" %
                    (field, steps), "%d cells differ" % sum(a != b for a, b in zip(att, want)))
    s.eq(r.get("step"), 4, "four automaton steps taken")
    # steps_per_frame: one simulation step, two automaton steps.
    c.ok("scene.set", {"scene": "ref", "path": "cloud.steps_per_frame", "value": 2})
    c.ok("sim.step", {"scene": "ref"}, timeout=60)
    for _ in range(2):
        hum, act, cld = ref_step(hum, act, cld, n)
    _, att = get(c, "ref", "cld")
    s.check(att == bytes(cld), "steps_per_frame 2 takes two automaton steps")
    # Pipelined steps all count.
    for _ in range(3):
        c.send(c.request("sim.step", {"scene": "ref"}))
    for _ in range(3):
        resp, _ = c.recv_response(timeout=60)
        s.check("result" in resp, "pipelined sim.step answered", mock.short(resp))
    for _ in range(6):
        hum, act, cld = ref_step(hum, act, cld, n)
    _, att = get(c, "ref", "act")
    s.check(att == bytes(act), "three pipelined sim.step calls take six automaton steps")
    # Once no cell is active the cells stay as they are, however many steps are asked for.
    c.ok("cloud.set_cells", {"scene": "ref", "field": "act", "data": b64([0] * N)})
    before = {f: get(c, "ref", f)[1] for f in ("hum", "cld")}
    step0 = get(c, "ref", "cld")[0].get("step")
    r, _ = c.ok("sim.step", {"scene": "ref", "steps": 100000}, timeout=60)
    r, _ = get(c, "ref", "cld")
    s.eq(r.get("step") - step0, 200000, "100000 steps of 2 automaton steps counted")
    s.check(all(get(c, "ref", f)[1] == before[f] for f in ("hum", "cld")),
            "without active cells the cells stay")


def gauss_sum(cells, g, radius):
    """The density of cld 'cells' in grid 'g' by SPEC 5.4 as docs/protocol.md gives it, cell by
    cell in double precision: a Gaussian of sigma = radius / 3 per cell, cut at whole cells
    within the radius and normalised per axis."""
    sigma, r = radius / 3.0, int(radius)
    norm = sum(math.exp(-d * d / (2 * sigma * sigma)) for d in range(-r, r + 1))
    out = [0.0] * (g[0] * g[1] * g[2])
    for (a, b, cc) in cells:
        for k in range(max(cc - r, 0), min(cc + r + 1, g[2])):
            for j in range(max(b - r, 0), min(b + r + 1, g[1])):
                for i in range(max(a - r, 0), min(a + r + 1, g[0])):
                    d2 = (a - i) ** 2 + (b - j) ** 2 + (cc - k) ** 2
                    out[i + g[0] * (j + g[1] * k)] += math.exp(-d2 / (2 * sigma ** 2)) / norm ** 3
    return out


@T
def density_after_set(s):
    c = s.srv.connect()
    g = (15, 13, 11)
    make(c, "dens", grid=g, metaball_radius=3)
    n = g[0] * g[1] * g[2]
    cells = [(4, 5, 6), (9, 6, 5), (10, 6, 5)]
    cld = [0] * n
    for (i, j, k) in cells:
        cld[i + g[0] * (j + g[1] * k)] = 1
    c.ok("cloud.set_cells", {"scene": "dens", "field": "cld", "data": b64(cld)}, timeout=60)
    _, att = get(c, "dens", "density")
    got = struct.unpack("<%df" % n, att)
    worst = max(abs(x - y) for x, y in zip(got, gauss_sum(cells, g, 3)))
    s.check(worst < 1e-6, "density after set_cells cld is the Gaussian sum", "worst %g" % worst)
    s.check(max(got) > 0.05, "the density has a peak", max(got))
    # With smoothing, a step moves the density only part of the way.
    c.ok("scene.set", {"scene": "dens", "path": "cloud.smoothing", "value": 0.5})
    zero = [0] * n
    c.ok("cloud.set_cells", {"scene": "dens", "field": "act", "data": b64(zero)})
    before = got
    c.ok("cloud.set_cells", {"scene": "dens", "field": "density",
                             "data": b64(struct.pack("<%df" % n, *([0.0] * n)))})
    c.ok("sim.step", {"scene": "dens"}, timeout=60)
    _, att = get(c, "dens", "density")
    after = struct.unpack("<%df" % n, att)
    i = max(range(n), key=lambda x: before[x])
    s.check(abs(after[i] - 0.5 * before[i]) < 1e-6, "smoothing 0.5 shows half the new density",
            (after[i], before[i]))
    # The blend is per simulation step, however the steps are grouped into calls: from 0, n
    # steps towards the unchanging density D show D (1 - 0.5^n).
    for steps in (3, 30):
        c.ok("cloud.set_cells", {"scene": "dens", "field": "density",
                                 "data": b64(struct.pack("<%df" % n, *([0.0] * n)))})
        c.ok("sim.step", {"scene": "dens", "steps": steps}, timeout=60)
        after = struct.unpack("<%df" % n, get(c, "dens", "density")[1])
        worst = max(abs(a - b * (1 - 0.5 ** steps)) for a, b in zip(after, before))
        s.check(worst < 1e-6, "sim.step of %d steps blends %d times" % (steps, steps),
                "worst %g" % worst)


@T
def metaball_radius_applies_at_once(s):
    """A new cloud.metaball_radius recomputes the density of the same cells at once, unsmoothed:
    a request pipelined behind the scene.set sees it; the cells stay."""
    c = s.srv.connect()
    g = (17, 13, 11)
    make(c, "mr", grid=g, metaball_radius=3, smoothing=0.5)
    n = g[0] * g[1] * g[2]
    cells = [(8, 6, 5), (3, 3, 3)]
    cld = [0] * n
    for (i, j, k) in cells:
        cld[i + g[0] * (j + g[1] * k)] = 1
    c.ok("cloud.set_cells", {"scene": "mr", "field": "cld", "data": b64(cld)}, timeout=60)
    step = get(c, "mr", "cld")[0].get("step")
    set_r, dens = pipelined(c, ("scene.set", {"scene": "mr", "path": "cloud.metaball_radius",
                                             "value": 6}),
                            ("cloud.get_cells", {"scene": "mr", "field": "density",
                                                 "encoding": "base64"}))
    s.check("version" in (set_r.get("result") or {}), "scene.set answers with the version",
            set_r)
    got = struct.unpack("<%df" % n, cells_of(dens))
    worst = max(abs(x - y) for x, y in zip(got, gauss_sum(cells, g, 6)))
    s.check(worst < 1e-6, "the density read behind the change has the new radius",
            "worst %g" % worst)
    r, att = get(c, "mr", "cld")
    s.check(att == bytes(cld) and r.get("step") == step, "and the cells are the same",
            r.get("step"))
    # A change that leaves the radius as it was answers at once and keeps the density.
    c.ok("scene.set", {"scene": "mr", "path": "cloud.p_ext", "value": 0.01})
    s.check(get(c, "mr", "density")[1] == struct.pack("<%df" % n, *got),
            "another cloud change keeps the density")


@T
def freed_grids_kept_a_second(s):
    """A step's big blocks (density, blend, scratch) are kept for reuse by the next steps and
    freed a second after the last one (stats memory.kept_bytes)."""
    c = s.srv.connect()
    make(c, "kept", grid=(96, 96, 96), smoothing=0.5, rules="dobashi")
    for _ in range(4):
        c.ok("sim.step", {"scene": "kept"}, timeout=60)
    kept = c.ok("stats", {})[0]["memory"]["kept_bytes"]
    s.check(kept >= 2 * 4 * 96 ** 3, "stepping keeps the freed grids", kept)
    deadline = time.time() + 5
    while kept and time.time() < deadline:
        time.sleep(0.25)
        kept = c.ok("stats", {})[0]["memory"]["kept_bytes"]
    s.eq(kept, 0, "and frees them once they have not been reused for a second")


@T
def smoothing_per_step(s):
    """A growing Dobashi cloud shows the same density after one sim.step of n steps as after n
    calls of one step, with steps_per_frame 1 and 2: exactly while every step's density counts,
    and within a float's resolution where the oldest weigh less (0.5^24)."""
    c = s.srv.connect()
    cloud = dict(rules="dobashi", p_ext=0.05, p_hum=0.05, p_act=0.02, seed=9, smoothing=0.5,
                 metaball_radius=2)
    for per in (1, 2):
        for steps, exact in ((3, True), (40, False)):
            names = ["sm%d_%d_%s" % (per, steps, k) for k in ("one", "many")]
            for name in names:
                make(c, name, grid=(12, 10, 8), steps_per_frame=per, **cloud)
            c.ok("sim.step", {"scene": names[0], "steps": steps}, timeout=60)
            for _ in range(steps):
                c.ok("sim.step", {"scene": names[1]}, timeout=60)
            one, many = (get(c, name, "density")[1] for name in names)
            s.check(get(c, names[0], "cld")[1] == get(c, names[1], "cld")[1],
                    "the same cells either way (%d steps of %d)" % (steps, per))
            a = struct.unpack("<%df" % (len(one) // 4), one)
            b = struct.unpack("<%df" % (len(many) // 4), many)
            worst = max(abs(x - y) for x, y in zip(a, b))
            s.check(worst == 0 if exact else worst < 1e-6,
                    "one sim.step of %d shows the density of %d calls (steps_per_frame %d)" %
                    (steps, steps, per), "worst %g" % worst)
            s.check(max(a) > 0.01, "the cloud has density", max(a))


@T
def dobashi_reproducible(s):
    c = s.srv.connect()
    opts = dict(rules="dobashi", p_ext=0.05, p_hum=0.05, p_act=0.01, wind=0.5)
    for name, seed in (("d1", 3), ("d2", 3), ("d3", 4)):
        make(c, name, grid=(24, 16, 12), seed=seed, **opts)
        c.ok("sim.step", {"scene": name, "steps": 8}, timeout=60)
    cells = {name: get(c, name, "cld")[1] for name in ("d1", "d2", "d3")}
    s.check(sum(cells["d1"]) > 0, "the dobashi cloud has cloud cells", sum(cells["d1"]))
    s.check(cells["d1"] == cells["d2"], "the same seed gives the same cloud")
    s.check(cells["d1"] != cells["d3"], "another seed gives another cloud")


@T
def bad_inputs(s):
    c = s.srv.connect()
    make(c, "bad")
    rng = random.Random(3)
    hum = [1 if rng.random() < 0.5 else 0 for _ in range(N)]
    c.ok("cloud.set_cells", {"scene": "bad", "field": "hum", "data": b64(hum)})
    before = {f: get(c, "bad", f)[1] for f in ("hum", "act", "cld", "density")}
    p = {"scene": "bad", "field": "hum"}
    expect_error(s, c, "cloud.set_cells", dict(p, data=b64([0] * (N - 1))), E_PARAMS, "data",
                 "one byte short")
    expect_error(s, c, "cloud.set_cells", dict(p, data=b64([0] * (N + 1))), E_PARAMS, "data",
                 "one byte over")
    expect_error(s, c, "cloud.set_cells", dict(p, data=b64([0] * (N - 1) + [2])), E_PARAMS,
                 "data", "a cell that is 2")
    expect_error(s, c, "cloud.set_cells", dict(p, data="!!not base64!!"), E_PARAMS, "data",
                 "bad base64")
    expect_error(s, c, "cloud.set_cells", dict(p, field="ice", data=b64([0] * N)), E_PARAMS,
                 "field", "unknown field")
    expect_error(s, c, "cloud.set_cells", {"scene": "bad", "field": "cld"}, E_PARAMS, "data",
                 "no data")
    d = {"scene": "bad", "field": "density"}
    for bad, what in ((-1.0, "negative"), (float("nan"), "NaN"), (float("inf"), "infinite")):
        vals = [0.5] * N
        vals[N // 2] = bad
        expect_error(s, c, "cloud.set_cells", dict(d, data=b64(struct.pack("<%df" % N, *vals))),
                     E_PARAMS, "data", "a %s density" % what)
    expect_error(s, c, "cloud.set_cells", dict(d, data=b64(bytes(4 * N - 4))), E_PARAMS, "data",
                 "a density short of one float")
    expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"cloud": {"grid": [257, 8, 8]}}},
                 E_LIMIT, "cloud.grid.0", "a grid over limits.cloud_side")
    for huge in (100000, 1e300):
        expect_error(s, c, "scene.set",
                     {"scene": "bad", "patch": {"cloud": {"grid": [1, 1, huge]}}},
                     E_LIMIT, "cloud.grid.2", "a side of %g" % huge)
    expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"cloud": {"grid": [8.5, 8, 8]}}},
                 E_PARAMS, "cloud.grid.0", "a fractional grid")
    r = expect_error(s, c, "scene.set",
                     {"scene": "bad", "patch": {"cloud": {"grid": [8, 16.000001, 8]}}},
                     E_PARAMS, "cloud.grid.1", "a side just off a whole number")
    msg = ((r or {}).get("error") or {}).get("message", "")
    s.check("16.000001" in msg, "the message shows the side as given", msg)
    expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"cloud": {"grid": [0, 8, 8]}}},
                 E_PARAMS, "cloud.grid.0", "an empty grid")
    expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"cloud": {"p_ext": 1.5}}},
                 E_PARAMS, "cloud.p_ext", "a probability over 1")
    expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"cloud": {"rules": "conway"}}},
                 E_PARAMS, "cloud.rules", "unknown rules")
    expect_error(s, c, "scene.set",
                 {"scene": "bad", "patch": {"cloud": {"ellipsoids": [
                     {"center": [0, 0, 0], "radii": [1, 0, 1]}]}}},
                 E_PARAMS, "cloud.ellipsoids.0.radii", "a flat ellipsoid")
    s.eq(c.ok("scene.get", {"scene": "bad", "path": "cloud.grid"})[0], [NX, NY, NZ],
         "refused patches left the grid")
    for f in ("hum", "act", "cld", "density"):
        s.check(get(c, "bad", f)[1] == before[f], "refused inputs left %s unchanged" % f)
    # A scene without a cloud.
    c.ok("scene.create", {"name": "nocloud"})
    # A disabled cloud has no cells: its grid is held to the limit once it is enabled (so that
    # the default grid cannot break a server with a smaller cloud_side), and to the most any
    # server allows (1024) at once.
    c.ok("scene.set", {"scene": "nocloud", "patch": {"cloud": {"grid": [300, 8, 8]}}})
    expect_error(s, c, "scene.set", {"scene": "nocloud", "path": "cloud.enabled", "value": True},
                 E_LIMIT, "cloud.grid.0", "enabling a cloud whose grid is over the limit")
    expect_error(s, c, "scene.set",
                 {"scene": "nocloud", "patch": {"cloud": {"grid": [2000, 8, 8]}}},
                 E_LIMIT, "cloud.grid.0", "a disabled cloud's side over 1024")
    c.ok("scene.set", {"scene": "nocloud", "patch": {"cloud": {"grid": [64, 64, 64]}}})
    expect_error(s, c, "cloud.get_cells", {"scene": "nocloud", "field": "cld"}, E_PARAMS,
                 "scene", "get_cells without a cloud")
    expect_error(s, c, "cloud.set_cells",
                 {"scene": "nocloud", "field": "cld", "data": b64([0] * N)}, E_PARAMS, "scene",
                 "set_cells without a cloud")
    expect_error(s, c, "cloud.get_cells", {"scene": "nosuch", "field": "cld"}, mock.E_NOT_FOUND,
                 None, "an unknown scene")


@T
def grid_limit_config(s):
    path = mock.config_file({"limits": {"cloud_side": 80, "output_bytes": 1 << 20}})
    with mock.Server(s.bin, "--config", path) as srv:
        c = srv.connect()
        make(c, "lim", grid=(16, 16, 16))
        expect_error(s, c, "scene.set",
                     {"scene": "lim", "path": "cloud.grid", "value": [81, 16, 16]}, E_LIMIT,
                     "cloud.grid.0", "over a configured limit of 80")
        s.eq(get(c, "lim", "cld")[0].get("dims"), [16, 16, 16], "the refused grid left the cells")
        # 80³ f32 is 2 MB, over an output limit of 1 MiB: one answer may pass it, whole.
        make(c, "big", grid=(80, 80, 80))
        s.eq(len(get(c, "big", "density")[1]), 4 * 512000,
             "a density over limits.output_bytes comes whole")
        s.eq(len(get(c, "big", "hum")[1]), 512000, "the connection still answers")
        # A disabled cloud may keep a larger grid, but cannot be enabled with it.
        c.ok("scene.set", {"scene": "lim", "patch": {"cloud": {"enabled": False,
                                                               "grid": [96, 16, 16]}}})
        expect_error(s, c, "scene.set", {"scene": "lim", "path": "cloud.enabled", "value": True},
                     E_LIMIT, "cloud.grid.0", "enabling a cloud over the limit")
        s.eq(c.ok("scene.get", {"scene": "lim", "path": "cloud.enabled"})[0], False,
             "the refused enable left the cloud disabled")


@T
def reseed_and_render(s):
    c = s.srv.connect()
    make(c, "rs", grid=(32, 32, 32), smoothing=0.5, init={"hum": 0.7, "act": 0.002})
    c.ok("sim.step", {"scene": "rs", "steps": 6}, timeout=60)
    r, att = get(c, "rs", "cld")
    s.check(sum(att) > 0, "the default seeding grows a cloud", sum(att))
    s.eq(r.get("step"), 6, "six automaton steps")
    r, att = c.ok("render", {"scene": "rs", "width": 64, "height": 64, "format": "rgba8"},
                  timeout=60)
    s.eq(len(att or b""), 64 * 64 * 4, "a scene with a cloud renders")
    # Changing the seed seeds fresh cells; changing the density knob keeps them.
    c.ok("scene.set", {"scene": "rs", "path": "cloud.density", "value": 3})
    s.eq(get(c, "rs", "cld")[0].get("step"), 6, "changing cloud.density keeps the cells")
    c.ok("scene.set", {"scene": "rs", "path": "cloud.seed", "value": 9})
    r, att = get(c, "rs", "cld")
    s.eq((r.get("step"), sum(att)), (0, 0), "a new seed gives fresh cells without cloud")
    c.ok("scene.set", {"scene": "rs", "path": "cloud.enabled", "value": False})
    expect_error(s, c, "cloud.get_cells", {"scene": "rs"}, E_PARAMS, "scene",
                 "a disabled cloud has no cells")


@T
def init_steps_grow_the_cloud(s):
    """cloud.init.steps: fresh cells grown at seeding exactly as sim.step would grow them."""
    c = s.srv.connect()
    for rules, extra in (("kuromiya", {}),
                         ("dobashi", dict(p_ext=0.05, p_hum=0.05, p_act=0.01, wind=0.5))):
        init = {"hum": 0.6, "act": 0.03}
        a, b = "ia_" + rules, "ib_" + rules
        make(c, a, rules=rules, metaball_radius=2, init=dict(init, steps=5), **extra)
        make(c, b, rules=rules, metaball_radius=2, init=dict(init, steps=0), **extra)
        r, att = get(c, b, "cld")
        s.eq((r.get("step"), sum(att)), (0, 0), "%s: no seeding steps, no cloud" % rules)
        c.ok("sim.step", {"scene": b, "steps": 5}, timeout=60)
        r, att = get(c, a, "cld")
        s.eq(r.get("step"), 5, "%s: init.steps 5 takes five automaton steps" % rules)
        s.check(sum(att) > 0, "%s: the seeded cloud has cloud cells" % rules, sum(att))
        s.eq(c.ok("scene.get", {"scene": a, "path": "sim.frame"})[0], 0,
             "%s: the seeding steps leave the clock at frame 0" % rules)
        for f in ("hum", "act", "cld", "density"):
            s.check(get(c, a, f)[1] == get(c, b, f)[1],
                    "%s: %s after init.steps 5 equals 5 sim.step calls from the seed" % (rules, f))
    # Against the reference automaton as well.
    make(c, "iz", init={"hum": 0.6, "act": 0.03})
    cells = [list(get(c, "iz", f)[1]) for f in ("hum", "act", "cld")]
    for _ in range(3):
        cells = list(ref_step(*cells, (NX, NY, NZ)))
    c.ok("scene.set", {"scene": "iz", "path": "cloud.init.steps", "value": 3})
    for f, want in zip(("hum", "act", "cld"), cells):
        s.check(get(c, "iz", f)[1] == bytes(want),
                "changing init.steps reseeds and grows %s as the reference does" % f)
    # Bounded by the range of init.steps; nothing changes when refused.
    before = get(c, "iz", "cld")[1]
    expect_error(s, c, "scene.set", {"scene": "iz", "path": "cloud.init.steps", "value": 257},
                 E_PARAMS, "cloud.init.steps", "init.steps over 256")
    s.eq(c.ok("scene.get", {"scene": "iz", "path": "cloud.init.steps"})[0], 3,
         "the refused patch left init.steps")
    s.check(get(c, "iz", "cld")[1] == before, "the refused patch left the cells")
    c.ok("scene.set", {"scene": "iz", "patch": {"cloud": {"grid": [64, 64, 64],
                                                         "init": {"steps": 200}}}}, timeout=60)
    s.eq(get(c, "iz", "cld")[0].get("step"), 200, "200 steps of 64^3 are taken at seeding")


@T
def init_steps_limit(s):
    """Past the default limits, a grid's cells times init.steps may not exceed 2^32."""
    path = mock.config_file({"limits": {"cloud_side": 512}})
    with mock.Server(s.bin, "--config", path) as srv:
        c = srv.connect()
        make(c, "lim", grid=(16, 16, 16), init={"steps": 2})
        expect_error(s, c, "scene.set", {"scene": "lim", "patch": {"cloud": {
            "grid": [512, 256, 256], "init": {"steps": 129}}}}, E_LIMIT, "cloud.init.steps",
            "512x256x256 cells x 129 steps, over 2^32 cell-steps")
        s.eq(c.ok("scene.get", {"scene": "lim", "path": "cloud.grid"})[0], [16, 16, 16],
             "the refused patch left the grid")
        s.eq(get(c, "lim", "cld")[0].get("step"), 2, "the refused patch left the cells")

# A 256^3 Dobashi cloud grown 16 steps: a few hundred milliseconds of seeding on an idle core.
BIG_CLOUD = {"enabled": True, "grid": [256, 256, 256], "rules": "dobashi", "p_ext": 0.01,
             "init": {"steps": 16}}


@T
def seeding_off_the_loop(s):
    a = s.srv.connect()
    b = s.srv.connect()
    a.ok("scene.create", {"name": "seed"})
    req = a.request("scene.set", {"scene": "seed", "patch": {"cloud": dict(BIG_CLOUD, seed=1)}})
    # Requests pipelined behind the change wait for it, and see it.
    behind = [a.request("scene.get", {"scene": "seed", "path": "cloud.grid"}),
              a.request("cloud.get_cells", {"scene": "seed", "field": "hum"})]
    a.send_raw(b"".join(mock.dumps(r).encode() + b"\n" for r in [req] + behind))
    mock.served_meanwhile(s, b, a, "another client is answered while the cloud is seeded")
    got = [a.recv_response(timeout=120) for _ in range(3)]
    s.eq([g[0].get("id") for g in got], [req["id"]] + [r["id"] for r in behind],
         "answered in order")
    s.check("result" in got[0][0], "the change is made", mock.short(got[0][0]))
    s.eq(got[1][0].get("result"), [256, 256, 256], "the scene.get behind it sees the new grid")
    s.eq(len(got[2][1] or b""), 256 ** 3, "the cells behind it are the new grid's")
    # The rest of a batch waits too.
    resp = mock.batch(s, a, [
        a.request("scene.get", {"scene": "seed", "path": "cloud.seed"}),
        a.request("scene.set", {"scene": "seed", "path": "cloud.seed", "value": 2}),
        a.request("scene.get", {"scene": "seed", "path": "cloud.seed"})])
    if resp:
        s.eq([r.get("result") for r in (resp[0], resp[2])], [1, 2],
             "the get after the reseeding change, in the same batch, sees it")
        s.check("result" in resp[1], "the batch's change is made", mock.short(resp[1]))
    # Big answers are made off the loop too: 16 MiB of cells as base64, 22 MB of text.
    req = a.request("cloud.get_cells", {"scene": "seed", "field": "cld", "encoding": "base64"})
    a.send(req)
    mock.served_meanwhile(s, b, a, "another client is answered while 16 MiB of cells are encoded")
    resp, _ = a.recv_response(timeout=120)
    data = base64.b64decode((resp.get("result") or {}).get("data", ""))
    s.eq(len(data), 256 ** 3, "the base64 answer holds every cell")
    s.check(data == get(a, "seed", "cld")[1], "base64 and the attachment carry the same cells")
    # In a batch, between small answers.
    resp = mock.batch(s, a, [
        a.request("scene.get", {"scene": "seed", "path": "cloud.seed"}),
        a.request("cloud.get_cells", {"scene": "seed", "field": "hum", "encoding": "base64"}),
        a.request("scene.get", {"scene": "seed", "path": "cloud.grid"})])
    if resp:
        s.eq([resp[0].get("result"), resp[2].get("result")], [2, [256, 256, 256]],
             "the small answers around a big one")
        hum = base64.b64decode((resp[1].get("result") or {}).get("data", ""))
        s.check(hum == get(a, "seed", "hum")[1], "the big answer in the batch carries the cells")
    # Refused changes still seed nothing and change nothing.
    expect_error(s, a, "scene.set", {"scene": "seed", "patch": {"cloud": {"seed": 3,
                 "p_ext": 2}}}, E_PARAMS, "cloud.p_ext", "a bad field beside a new seed")
    s.eq(a.ok("scene.get", {"scene": "seed", "path": "cloud.seed"})[0], 2,
         "the refused change left the seed")
    a.ok("scene.delete", {"name": "seed"})


@T
def seeding_while_others_change_the_scene(s):
    """Another client's change lands while this one's cells are seeded: the retry merges this
    patch into the document as it then is, and the cells are those of the settings that won."""
    a = s.srv.connect()
    b = s.srv.connect()
    make(a, "cc", grid=(16, 16, 16))
    a.send(a.request("scene.set", {"scene": "cc", "patch": {"cloud": {
        "grid": [128, 128, 128], "rules": "dobashi", "init": {"steps": 8}}}}))
    time.sleep(0.005)
    b.ok("scene.set", {"scene": "cc", "path": "cloud.seed", "value": 77}, timeout=120)
    resp, _ = a.recv_response(timeout=120)
    s.check("result" in resp, "the first change is made", mock.short(resp))
    cloud = a.ok("scene.get", {"scene": "cc", "path": "cloud"})[0]
    s.eq((cloud.get("grid"), cloud.get("seed"), cloud.get("init", {}).get("steps")),
         ([128, 128, 128], 77, 8), "both changes are in the document")
    make(b, "cc_ref", grid=(128, 128, 128), rules="dobashi", seed=77, init={"steps": 8})
    for f in ("hum", "cld", "density"):
        s.check(get(a, "cc", f)[1] == get(b, "cc_ref", f)[1],
                "%s equals a fresh seeding of the final settings" % f)
    for name in ("cc", "cc_ref"):
        a.ok("scene.delete", {"name": name})


@T
def hang_up_while_seeding(s):
    a = s.srv.connect()
    a.ok("scene.create", {"name": "gone"})
    a.send(a.request("scene.set", {"scene": "gone", "patch": {"cloud": dict(BIG_CLOUD)}}))
    a.send(a.request("scene.list"))
    time.sleep(0.02)
    a.close()
    b = s.srv.connect()
    deadline = time.time() + 60
    grid = None
    while time.time() < deadline:
        grid = b.ok("scene.get", {"scene": "gone", "path": "cloud"})[0]
        if grid.get("enabled"):
            break
        time.sleep(0.05)
    s.eq((grid.get("enabled"), grid.get("grid")), (True, [256, 256, 256]),
         "the change of a client that left is made")
    s.eq(get(b, "gone", "cld")[0].get("step"), 16, "with its cells grown")
    b.ok("scene.delete", {"name": "gone"})
    s.check(s.srv.alive(), "the server is still up")


@T
def demo_opens_on_a_cloud(s):
    """The demo preset's cloud is grown at seeding, so its first frame shows it."""
    c = s.srv.connect()
    c.ok("scene.create", {"name": "demo", "preset": "demo"})
    r, att = get(c, "demo", "cld")
    s.check(r.get("step", 0) > 0 and sum(att) > 0, "the demo's cloud has grown at frame 0",
            (r.get("step"), sum(att or b"")))
    p = {"scene": "demo", "width": 96, "height": 54, "format": "rgba8"}
    with_cloud, a = c.ok("render", p, timeout=60)
    without, b = c.ok("render", dict(p, layers=["objects", "volumes", "fluid", "waves"]),
                      timeout=60)
    s.check("volumes" in with_cloud.get("work_ms", {}), "the demo's first frame draws volumes")
    differ = sum(1 for i in range(0, len(a), 4) if abs(a[i] - b[i]) > 8)
    s.check(0 < differ < len(a) // 16, "the cloud covers part of the demo's sky", differ)


def pipelined(c, *requests):
    """Sends 'requests' (method, params) in one write; returns their answers in order."""
    reqs = [c.request(m, p) for m, p in requests]
    c.send_raw(b"".join(mock.dumps(q).encode() + b"\n" for q in reqs))
    return [c.recv_response(timeout=60)[0] for _ in reqs]


def cells_of(resp):
    return base64.b64decode((resp.get("result") or {}).get("data", ""))


@T
def requests_behind_a_step_see_it(s):
    """Requests written right behind sim.step or cloud.set_cells on the same connection,
    pipelined or in the same batch, are answered from the cloud after it (SPEC 3: answered in
    order): a read sees the steps, a write cannot undo them, the density follows new cld."""
    c = s.srv.connect()
    hum, act, cld = random_cloud(c, "pipe", 23)
    n = (NX, NY, NZ)
    read = ("cloud.get_cells", {"scene": "pipe", "field": "cld", "encoding": "base64"})
    step, got = pipelined(c, ("sim.step", {"scene": "pipe"}), read)
    hum, act, cld = ref_step(hum, act, cld, n)
    s.check("result" in step, "the pipelined sim.step is answered", mock.short(step))
    s.eq((got.get("result") or {}).get("step"), 1, "the read behind sim.step sees its step")
    s.check(cells_of(got) == bytes(cld), "the read behind sim.step sees the stepped cells")
    # A write behind a step lands on the stepped cells; the step is not thrown away.
    zeros = b64([0] * N)
    pipelined(c, ("sim.step", {"scene": "pipe"}),
              ("cloud.set_cells", {"scene": "pipe", "field": "hum", "data": zeros}))
    hum, act, cld = ref_step(hum, act, cld, n)
    hum = [0] * N
    r, att = get(c, "pipe", "act")
    s.eq(r.get("step"), 2, "a set_cells behind sim.step keeps the step")
    s.check(att == bytes(act), "the cells are the stepped ones, then hum set")
    s.check(get(c, "pipe", "hum")[1] == bytes(N), "and hum is what the write set")
    # In a batch: two steps, then a read.
    resp = mock.batch(s, c, [c.request("sim.step", {"scene": "pipe", "steps": 2}),
                             c.request(*read)])
    for _ in range(2):
        hum, act, cld = ref_step(hum, act, cld, n)
    if resp:
        s.eq((resp[1].get("result") or {}).get("step"), 4, "the read in the batch sees 2 steps")
        s.check(cells_of(resp[1]) == bytes(cld), "and their cells")
    # cloud.set_cells of cld recomputes the density before the next request is served.
    ones = b64([1] * N)
    _, dens = pipelined(c, ("cloud.set_cells", {"scene": "pipe", "field": "cld", "data": ones}),
                        ("cloud.get_cells", {"scene": "pipe", "field": "density",
                                             "encoding": "base64"}))
    d = struct.unpack("<%df" % N, cells_of(dens))
    _, alone = get(c, "pipe", "density")
    s.check(max(d) > 0.5, "the density read behind set_cells cld sees the new cells", max(d))
    s.check(cells_of(dens) == alone, "and equals the density read afterwards")
    # Another connection is not held: it is answered while this one waits for a long step.
    big = s.srv.connect()
    make(big, "pipe_big", grid=(128, 128, 128), rules="dobashi", p_act=0.01, p_hum=0.01)
    big.send_raw(mock.dumps(big.request("sim.step", {"scene": "pipe_big", "steps": 20})) + "\n")
    mock.served_meanwhile(s, c, big, "another client is served while a connection waits for "
                          "its step")
    big.recv_response(timeout=120)


@T
def snapshot_carries_cells(s):
    c = s.srv.connect()
    make(c, "snap", grid=(40, 24, 20), rules="dobashi", p_ext=0.02, wind=0.5, smoothing=0.5)
    c.ok("sim.step", {"scene": "snap", "steps": 7}, timeout=60)
    saved = {f: get(c, "snap", f) for f in ("hum", "act", "cld", "density")}
    r, _ = c.ok("scene.save", {"scene": "snap", "file": "cloud.snap"})
    path = os.path.join(s.srv.data_dir, "cloud.snap")
    with open(path, "rb") as f:
        data = f.read()
    head = json.loads(data.split(b"\n", 1)[0])
    secs = head.get("sections") or []
    s.eq([x.get("name") for x in secs], ["cloud", "fluid"], "the snapshot lists its sections")
    s.eq(r.get("bytes"), len(data), "save reports every byte, sections included")
    c.ok("sim.step", {"scene": "snap", "steps": 3}, timeout=60)
    s.check(get(c, "snap", "cld")[1] != saved["cld"][1], "the cloud moved on after the save")
    c.ok("scene.load", {"scene": "snap", "file": "cloud.snap"})
    for f in ("hum", "act", "cld", "density"):
        r, att = get(c, "snap", f)
        s.check(att == saved[f][1], "load restores %s" % f)
    s.eq(r.get("step"), 7, "load restores the automaton's step")
    # The same steps after the load give what they gave before it.
    c.ok("sim.step", {"scene": "snap", "steps": 3}, timeout=60)
    after_load = get(c, "snap", "cld")[1]
    c.ok("scene.load", {"scene": "snap", "file": "cloud.snap"})
    c.ok("sim.step", {"scene": "snap", "steps": 3}, timeout=60)
    s.check(get(c, "snap", "cld")[1] == after_load, "a loaded cloud steps reproducibly")
    # A section whose dims promise a huge grid the bytes do not hold is refused (before the
    # grid is allocated).
    line = json.loads(data.split(b"\n", 1)[0])
    line["sections"][0]["dims"] = [1024, 1024, 1024]
    with open(os.path.join(s.srv.data_dir, "huge.snap"), "wb") as f:
        f.write((json.dumps(line) + "\n").encode() + data.split(b"\n", 1)[1])
    expect_error(s, c, "scene.load", {"scene": "snap", "file": "huge.snap"}, E_PARAMS, "file",
                 "a cloud section of 1024³ dims and a 40 × 24 × 20 grid's bytes")
    # A truncated section is refused and nothing changes.
    with open(os.path.join(s.srv.data_dir, "short.snap"), "wb") as f:
        f.write(data[:-10])
    before = get(c, "snap", "cld")[1]
    expect_error(s, c, "scene.load", {"scene": "snap", "file": "short.snap"}, E_PARAMS, "file",
                 "a truncated cloud section")
    s.check(get(c, "snap", "cld")[1] == before, "the refused load left the cells")


@T
def wind_drifts_smoothly(s):
    """A cloud blown at a quarter of a cell per step moves a quarter of a cell on screen each
    step, not a whole cell every fourth: the cells move by whole cells, and the renderer draws
    them the rest of the way (the centroid of its light over a black background, from rgbaf32
    frames of the cloud alone)."""
    c = s.srv.connect()
    g = (24, 8, 8)
    make(c, "wind", grid=g, rules="dobashi", wind=0.25, p_ext=0, p_hum=0, p_act=0,
         metaball_radius=2, voxel=0.25, origin=[-3, -1, -1])
    n = g[0] * g[1] * g[2]
    cld = [1 if 6 <= i % g[0] < 10 and 2 <= (i // g[0]) % g[1] < 6 and 2 <= i // (g[0] * g[1]) < 6
           else 0 for i in range(n)]
    for field, vals in (("hum", [0] * n), ("act", [0] * n), ("cld", cld)):
        c.ok("cloud.set_cells", {"scene": "wind", "field": field, "data": b64(vals)})
    c.ok("scene.set", {"scene": "wind", "patch": {"camera": {
        "eye": [0, 0, 9], "target": [0, 0, 0], "fov_y": 40}, "light": {"ambient": 1},
        "background": [0, 0, 0]}})
    w, h = 96, 48
    cell_px = 0.25 * w / (2 * 9 * math.tan(math.radians(20)) * w / h)
    # Smoothed, the density shown moves with the cells too: no ghost left a cell behind.
    for smoothing in (0, 0.6):
        c.ok("scene.set", {"scene": "wind", "path": "cloud.smoothing", "value": smoothing})
        xs = []
        for step in range(9):
            if step:
                c.ok("sim.step", {"scene": "wind"}, timeout=60)
            _, raw = c.ok("render", {"scene": "wind", "width": w, "height": h,
                                     "format": "rgbaf32", "layers": ["cloud"]}, timeout=60)
            px = struct.unpack("<%df" % (4 * w * h), raw)
            light = [px[4 * i] for i in range(w * h)]  # What it scatters over black.
            total = sum(light)
            xs.append(sum(a * (i % w) for i, a in enumerate(light)) / total if total else 0)
        moves = [b - a for a, b in zip(xs, xs[1:])]
        what = "smoothing %g: " % smoothing
        s.check(all(m > 0 for m in moves), what + "the cloud moves every step", moves)
        s.check(max(moves) < 1.5 * min(moves), what + "by about the same amount each step",
                moves)
        s.check(abs(sum(moves) / 8 - 0.25 * cell_px) < 0.1 * 0.25 * cell_px,
                what + "a quarter of a cell a step", (sum(moves) / 8, 0.25 * cell_px))


@T
def play_steps_the_cloud(s):
    c = s.srv.connect()
    make(c, "play", grid=(32, 32, 32), rules="dobashi", wind=0.5)
    step0 = get(c, "play", "cld")[0].get("step")
    c.ok("sim.play", {"scene": "play", "rate": 60})
    time.sleep(0.6)
    c.ok("sim.pause", {"scene": "play"})
    time.sleep(0.3)  # A job still running when paused lands after the pause.
    r, _ = get(c, "play", "cld")
    s.check(r.get("step", 0) > step0, "sim.play steps the cloud", (step0, r.get("step")))
    frame = c.ok("scene.get", {"scene": "play", "path": "sim.frame"})[0]
    s.check(r.get("step", 0) <= frame, "the cloud never runs ahead of the clock",
            (r.get("step"), frame))


@T
def delete_and_shutdown(s):
    with mock.Server(s.bin) as srv:
        c = srv.connect()
        for name in ("c1", "c2"):
            make(c, name, grid=(48, 48, 48))
            c.ok("sim.step", {"scene": name, "steps": 2}, timeout=120)
        # A step still running when its scene goes away is dropped quietly.
        c.send(c.request("sim.step", {"scene": "c1", "steps": 3}))
        c.send(c.request("scene.delete", {"name": "c1"}))
        c.recv_response(timeout=120)
        c.recv_response(timeout=120)
        make(c, "c1", grid=(8, 8, 8))
        s.eq(get(c, "c1", "cld")[0].get("dims"), [8, 8, 8], "a new scene of the same name")
        c.ok("sim.play", {"scene": "c2", "rate": 120})
        r, _ = c.ok("server.shutdown", {})
        s.eq(r, {"shutting_down": True}, "server.shutdown")
        s.eq(srv.wait_exit(30), 0, "volfxd exits 0 after deleting a cloud scene and shutting down")


@T
def delete_or_shut_down_while_seeding(s):
    """A scene deleted, or the server shut down, while a change's cells are being seeded."""
    with mock.Server(s.bin) as srv:
        a = srv.connect()
        b = srv.connect()
        a.ok("scene.create", {"name": "gone"})
        req = a.request("scene.set", {"scene": "gone", "patch": {"cloud": dict(BIG_CLOUD)}})
        a.send(req)
        time.sleep(0.01)
        b.ok("scene.delete", {"name": "gone"})
        resp, _ = a.recv_response(timeout=120)
        code = (resp.get("error") or {}).get("code")
        # Seeded before the delete came, or refused after: never half made.
        s.check("result" in resp or code == mock.E_NOT_FOUND,
                "the change is made before the delete, or refused for the missing scene",
                mock.short(resp))
        s.check(not any(e["name"] == "gone" for e in b.ok("scene.list")[0]["scenes"]),
                "the scene is gone")
        # Shut down while seeding: the server waits for the work, then exits cleanly.
        a.ok("scene.create", {"name": "late"})
        a.send(a.request("scene.set", {"scene": "late", "patch": {"cloud": dict(BIG_CLOUD)}}))
        time.sleep(0.01)
        r, _ = b.ok("server.shutdown", {})
        s.eq(r, {"shutting_down": True}, "server.shutdown while a cloud is seeded")
        s.eq(srv.wait_exit(60), 0, "volfxd exits 0 after shutting down during a seeding")


if __name__ == "__main__":
    sys.exit(suite.main())
