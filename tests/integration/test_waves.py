#!/usr/bin/env python3
"""
Energy waves (SPEC §4-5.1) checked from outside, over a real socket: the `wave_h` AOV of
volfxd against H computed here from the SPEC's own definitions, in double precision, for
every pixel of small frames. The reference shares nothing with the server: the ray comes from
the SPEC's pinhole camera, the interval inside the capsule is found by bisection on the
distance to the segment, and f is integrated by adaptive Gauss-Kronrod quadrature, split where
f is sharp (the planes s = 0 and s = L, the closest approach to M, to M + L·D and to the axis).
Cases: random waves and cameras (non-square frames), several waves summed, the degenerate
rays (along the axis, through M, the eye inside the capsule, L = 0), a sphere in front that
cuts the integral at its surface, and animation reaching its target through sim.step.

    python3 tests/integration/test_waves.py --bin build/bin
"""

import math
import os
import random
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_waves", timeout_s=500)
suite.server_args = []
T = suite.test

# The float32 H must be within 1e-4 relative of the reference (SPEC §5.1). Pixels whose ray
# only grazes the capsule hold a tiny H whose relative error is that of the interval's ends;
# they are held to an absolute bound of 1e-6 of the frame's largest H instead.
REL = 1e-4
ABS_OF_MAX = 1e-6


def sub(u, v):
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


def add(u, v):
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


def mul(u, k):
    return (u[0] * k, u[1] * k, u[2] * k)


def dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def cross(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def unit(u):
    n = math.sqrt(dot(u, u))
    return mul(u, 1.0 / n)


def camera_rays(cam, w, h):
    """SPEC §4's pinhole: one unit ray per pixel, row 0 at the top, through pixel centres."""
    eye = tuple(cam["eye"])
    fwd = unit(sub(cam["target"], eye))
    right = unit(cross(fwd, cam["up"]))
    up = cross(right, fwd)
    th = math.tan(math.radians(cam["fov_y"]) / 2)
    tw = th * w / h
    rays = []
    for y in range(h):
        for x in range(w):
            px = (2 * (x + 0.5) / w - 1) * tw
            py = (1 - 2 * (y + 0.5) / h) * th
            rays.append(unit(add(add(fwd, mul(right, px)), mul(up, py))))
    return eye, rays


# Gauss-Kronrod 7-15 nodes and weights on [-1, 1].
XK = [0.991455371120812639206854697526329, 0.949107912342758524526189684047851,
      0.864864423359769072789712788640926, 0.741531185599394439863864773280788,
      0.586087235467691130294144845693013, 0.405845151377397166906606412076961,
      0.207784955007898467600689403773245, 0.0]
WK = [0.022935322010529224963732008058970, 0.063092092629978553290700663189204,
      0.104790010322250183839876322541518, 0.140653259715525918745189590510238,
      0.169004726639267902826583426598550, 0.190350578064785409913256402421014,
      0.204432940075298892414161999234649, 0.209482141084727828012999174891714]
WG = [0.129484966168869693270611432679082, 0.279705391489276667901467771423780,
      0.381830050505118944950369775488975, 0.417959183673469387755102040816327]


def gk15(f, a, b):
    c, h = (a + b) / 2, (b - a) / 2
    fc = f(c)
    k, g = WK[7] * fc, WG[3] * fc
    for i in range(7):
        f1, f2 = f(c - h * XK[i]), f(c + h * XK[i])
        k += WK[i] * (f1 + f2)
        if i % 2 == 1:
            g += WG[i // 2] * (f1 + f2)
    return k * h, abs((k - g) * h)


def integrate(f, a, b, tol, depth=0):
    """Adaptive Gauss-Kronrod: splits [a, b] until each piece's error estimate is below tol."""
    v, err = gk15(f, a, b)
    if err <= tol or depth > 40 or b - a < 1e-12 * max(1.0, abs(a)):
        return v
    m = (a + b) / 2
    return integrate(f, a, m, tol / 2, depth + 1) + integrate(f, m, b, tol / 2, depth + 1)


class Wave:
    def __init__(self, w):
        self.M = tuple(w["center"])
        self.D = unit(w["direction"])
        self.a, self.b = w["a"], w["b"]
        self.L, self.R, self.eps = w["length"], w["radius"], w["softening"]
        self.E = add(self.M, mul(self.D, self.L))

    def seg_dist(self, p):
        w = sub(p, self.M)
        s = min(max(dot(w, self.D), 0.0), self.L)
        return math.sqrt(dot(sub(w, mul(self.D, s)), sub(w, mul(self.D, s))))

    def f(self, p):
        w = sub(p, self.M)
        s = dot(w, self.D)
        r2 = dot(w, w)
        if s <= 0:
            q2 = r2
        elif s < self.L:
            q2 = max(r2 - s * s, 0.0)
        else:
            e = sub(p, self.E)
            q2 = dot(e, e)
        e2 = self.eps * self.eps
        return self.a / math.sqrt(r2 + e2) + self.b / math.sqrt(q2 + e2)


def closest_t(o, d, p):
    return dot(sub(p, o), d)


def capsule_interval(wave, o, d, t0, t1):
    """[lo, hi] of the ray inside the capsule within [t0, t1], or None: the distance to the
    segment is convex along the ray, so a golden-section search finds its minimum and
    bisection either side finds where it crosses R."""
    g = (math.sqrt(5) - 1) / 2
    far = t1 if math.isfinite(t1) else closest_t(o, d, wave.M) + wave.L + 2 * wave.R + 1
    far = max(far, t0)
    dist = lambda t: wave.seg_dist(add(o, mul(d, t)))  # noqa: E731
    a, b = t0, far
    for _ in range(200):
        c1, c2 = b - g * (b - a), a + g * (b - a)
        if dist(c1) < dist(c2):
            b = c2
        else:
            a = c1
    tm = (a + b) / 2
    if dist(tm) > wave.R:
        return None

    def root(inside, outside):
        for _ in range(200):
            m = (inside + outside) / 2
            if dist(m) <= wave.R:
                inside = m
            else:
                outside = m
        return (inside + outside) / 2

    lo = t0 if dist(t0) <= wave.R else root(tm, t0)
    hi = far if dist(far) <= wave.R else root(tm, far)
    return lo, min(hi, t1)


def reference_h(wave, o, d, t0, t1):
    span = capsule_interval(wave, o, d, t0, t1)
    if span is None:
        return 0.0
    lo, hi = span
    cuts = {lo, hi}
    dd = dot(d, wave.D)
    if abs(dd) > 1e-15:
        for s in (0.0, wave.L):
            cuts.add(-(dot(sub(o, wave.M), wave.D) - s) / dd)
    for p in (wave.M, wave.E):
        cuts.add(closest_t(o, d, p))
    # Closest approach to the axis line.
    a_ = 1 - dd * dd
    if a_ > 1e-15:
        w = sub(o, wave.M)
        cuts.add(-(dot(d, w) - dd * dot(w, wave.D)) / a_)
    pts = sorted(t for t in cuts if lo <= t <= hi)
    f = lambda t: wave.f(add(o, mul(d, t)))  # noqa: E731
    scale = (wave.a + wave.b) / wave.eps * (hi - lo)
    total = 0.0
    for a, b in zip(pts, pts[1:]):
        if b > a:
            total += integrate(f, a, b, 1e-11 * scale)
    return total


def floats(raw):
    return mock.floats(raw)


def check_frame(s, c, name, cam, waves, w, h, spheres=(), what=""):
    """Renders wave_h of scene 'name' and compares every pixel with the reference."""
    _, raw = c.ok("render", {"scene": name, "width": w, "height": h, "aov": "wave_h",
                             "format": "f32"}, timeout=120)
    got = floats(raw or b"")
    if not s.eq(len(got), w * h, "%s: one float a pixel" % what):
        return
    eye, rays = camera_rays(cam, w, h)
    near = cam.get("near", 0.1)
    ref = []
    for d in rays:
        tmax = cam.get("far", math.inf)  # Nothing is drawn beyond the far distance.
        for centre, radius in spheres:  # The first hit of each opaque sphere ends the ray.
            oc = sub(eye, centre)
            bq = dot(oc, d)
            disc = bq * bq - (dot(oc, oc) - radius * radius)
            if disc >= 0:
                t = -bq - math.sqrt(disc)
                if t > near:
                    tmax = min(tmax, t)
        ref.append(sum(reference_h(Wave(wv), eye, d, near, tmax) for wv in waves))
    hmax = max(ref)
    s.check(hmax > 0, "%s: some pixel meets a wave" % what)
    worst, where = 0.0, None
    for i, (g, e) in enumerate(zip(got, ref)):
        err = abs(g - e)
        bound = REL * e + ABS_OF_MAX * hmax
        if err / bound > worst:
            worst, where = err / bound, (i % w, i // w, g, e)
    s.check(worst <= 1, "%s: wave_h within 1e-4 relative of the double quadrature" % what,
            "worst pixel (x, y, got, want) %s at %.2f of the bound" % (where, worst))
    return got, ref


def scene_with(c, name, cam, waves, objects=()):
    c.ok("scene.create", {"name": name})
    c.ok("scene.set", {"scene": name, "patch": {"camera": cam, "objects": list(objects),
                                                "waves": waves}})


@T
def random_waves(s):
    c = s.srv.connect()
    rng = random.Random(7)
    for k in range(4):
        waves = []
        for _ in range(1 + k % 3):
            waves.append({"center": [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1)],
                          "direction": unit((rng.gauss(0, 1), rng.gauss(0, 1), rng.gauss(0, 1))),
                          "a": rng.uniform(0, 2), "b": rng.uniform(0.1, 2),
                          "length": rng.choice([0.0, rng.uniform(0.2, 3)]),
                          "radius": rng.uniform(0.5, 2.5), "softening": rng.uniform(0.02, 0.5),
                          "clamp": 5})
        eye = [rng.uniform(-6, 6), rng.uniform(-4, 4), rng.uniform(5, 8)]
        cam = {"eye": eye, "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": rng.uniform(30, 60),
               "near": 0.1, "far": 100}
        name = "rw%d" % k
        scene_with(c, name, cam, waves)
        check_frame(s, c, name, cam, waves, 20, 13, what="random set %d (%d waves)" %
                    (k, len(waves)))


@T
def degenerate_rays(s):
    c = s.srv.connect()
    base = {"a": 1.0, "b": 0.7, "length": 2.0, "radius": 1.5, "softening": 0.05, "clamp": 5}
    # The centre pixel of an odd frame looks straight along the axis through M (and M + L·D):
    # the ρ piece is constant there, and the ray passes through both ends of the segment.
    wave = dict(base, center=[0, 0, 0], direction=[0, 0, -1])
    cam = {"eye": [0, 0, 6], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 40, "near": 0.1,
           "far": 100}
    scene_with(c, "axis", cam, [wave])
    got, ref = check_frame(s, c, "axis", cam, [wave], 9, 9, what="rays along the axis") or \
        (None, None)
    if got:
        s.check(math.isfinite(got[4 * 9 + 4]) and got[4 * 9 + 4] > 0,
                "the ray along the axis through M is finite and lit")
    # The same wave looked at from the side, the beam across the view, rays through M.
    cam = {"eye": [0, 0.0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 50, "near": 0.1,
           "far": 100}
    wave = dict(base, center=[0, 0, 0], direction=[1, 0, 0])
    scene_with(c, "side", cam, [wave])
    check_frame(s, c, "side", cam, [wave], 15, 9, what="rays through M and across the beam")
    # The eye inside the capsule: the interval starts at the near distance.
    cam = {"eye": [0.5, 0.2, 0.3], "target": [3, 0, 0], "up": [0, 1, 0], "fov_y": 70,
           "near": 0.05, "far": 100}
    scene_with(c, "inside", cam, [wave])
    check_frame(s, c, "inside", cam, [wave], 11, 9, what="the eye inside the capsule")
    # L = 0: a sphere only, with a beam strength that then acts as a second sphere term.
    wave0 = dict(base, center=[0.3, -0.2, 0], direction=[0, 1, 0], length=0)
    cam = {"eye": [0, 0, 4], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 50, "near": 0.1,
           "far": 100}
    scene_with(c, "l0", cam, [wave0])
    check_frame(s, c, "l0", cam, [wave0], 12, 10, what="L = 0")


@T
def occlusion(s):
    c = s.srv.connect()
    wave = {"center": [-1, 0, 0], "direction": [1, 0, 0], "a": 1, "b": 1, "length": 2,
            "radius": 1.5, "softening": 0.1, "clamp": 5}
    cam = {"eye": [0, 0, 6], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 45, "near": 0.1,
           "far": 100}
    # A sphere of radius 0.6 at the wave's middle, its near half inside the capsule: the
    # integral stops at its surface.
    sphere = {"shape": "sphere", "position": [0, 0, 0.4], "scale": [1.2, 1.2, 1.2]}
    scene_with(c, "occ", cam, [wave], [sphere])
    got, ref = check_frame(s, c, "occ", cam, [wave], 16, 12, spheres=[((0, 0, 0.4), 0.6)],
                           what="a sphere inside the capsule") or (None, None)
    # Without the objects layer nothing occludes: the centre pixels read more.
    _, raw = c.ok("render", {"scene": "occ", "width": 16, "height": 12, "aov": "wave_h",
                             "format": "f32", "layers": ["waves"]}, timeout=120)
    free = floats(raw or b"")
    if got and len(free) == len(got):
        i = 6 * 16 + 8
        s.check(free[i] > got[i] * 1.2, "the sphere cuts the integral short",
                "%g without it, %g with" % (free[i], got[i]))


@T
def far_ends_the_glow(s):
    """camera.far ends the integral as it ends the objects: a far distance through the capsule
    cuts H there, and one before it leaves nothing."""
    c = s.srv.connect()
    wave = {"center": [0, 0, 0], "direction": [1, 0, 0], "a": 1, "b": 1, "length": 1,
            "radius": 1.2, "softening": 0.1, "clamp": 5}
    cam = {"eye": [0.5, 0.3, 6], "target": [0.5, 0, 0], "up": [0, 1, 0], "fov_y": 40,
           "near": 0.1, "far": 6.0}
    scene_with(c, "far", cam, [wave])
    check_frame(s, c, "far", cam, [wave], 14, 10, what="far through the capsule")
    c.ok("scene.set", {"scene": "far", "path": "camera.far", "value": 4.5})
    _, raw = c.ok("render", {"scene": "far", "width": 14, "height": 10, "aov": "wave_h",
                             "format": "f32"}, timeout=120)
    s.check(max(floats(raw or b"")) == 0, "far before the capsule leaves no glow")


@T
def animation_reaches_target(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "anim"})
    c.ok("scene.set", {"scene": "anim", "patch": {"sim": {"dt": 0.1}, "waves": [
        {"a": 1, "length": 0, "animate": [
            {"field": "length", "target": 2.5, "rate": 1.0},
            {"field": "center", "keys": [{"t": 0, "value": [0, 0, 2]}, {"t": 1, "value": [0, 0, -2]}],
             "interp": "linear"}]}]}})
    c.ok("sim.step", {"scene": "anim", "steps": 5})
    w, _ = c.ok("scene.get", {"scene": "anim", "path": "waves.0"})
    s.check(abs(w["length"] - 0.5) < 1e-9, "length grows at its rate", w["length"])
    s.check(abs(w["center"][2] - 0.0) < 1e-6, "the keyed centre is halfway at t = 0.5",
            w["center"])
    c.ok("sim.step", {"scene": "anim", "steps": 40})
    w, _ = c.ok("scene.get", {"scene": "anim", "path": "waves.0"})
    s.eq(w["length"], 2.5, "length stops exactly on its target")
    s.check(abs(w["center"][2] + 2) < 1e-6, "the keyed centre holds its last key",
            w["center"])


@T
def bad_waves_refused(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "bad"})
    c.ok("scene.set", {"scene": "bad", "patch": {"waves": [{"id": "w"}]}})
    before, _ = c.ok("scene.get", {"scene": "bad"})
    for patch, path in [
            ({"direction": [0, 0, 0]}, "waves.0.direction"),
            ({"softening": 0}, "waves.0.softening"),
            ({"radius": -1}, "waves.0.radius"),
            ({"a": "x"}, "waves.0.a"),
            ({"clamp": 1e300}, "waves.0.clamp"),
            ({"animate": [{"field": "a", "target": 2, "rate": -1}]}, "waves.0.animate.0.rate")]:
        w = dict({"id": "w"}, **patch)
        mock.expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"waves": [w]}},
                          mock.E_PARAMS, path=path, what="refused: %s" % patch)
    after, _ = c.ok("scene.get", {"scene": "bad"})
    s.eq(after, before, "the refused patches changed nothing")


if __name__ == "__main__":
    sys.exit(suite.main())
