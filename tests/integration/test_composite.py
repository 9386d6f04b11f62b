#!/usr/bin/env python3
"""
Compositing effect-only frames over a game's own picture (docs/protocol.md, "Compositing").

The reference is volfxd's own render of a scene with an opaque box inside a noise volume. The
game-like path renders the same scene's effects only (layers ["volumes"], background
"transparent") with the box's depth buffer, computed here analytically for the same camera,
and composites that premultiplied frame over the game's picture of the box and background
(volfxd's objects-only render): game * (1 - a) + effect. In linear light (rgbaf32) this must
reproduce the reference; in 8 bits (rgba8, tone map "none") blending in linear light after
decoding the sRGB of both pictures must reproduce the 8-bit reference. The light comes from
behind the camera, so that the box's shadow in the volume (which the effect-only frame, knowing
no box, cannot have) lies behind the box, where the reference does not see it either. Pixels on
the box's silhouette may differ: there the analytic depth (double) and the renderer's ray-box
test (float) can disagree on whether a pixel's centre hits the box.

Also: the depth conventions (linear, ray, ndc_gl, ndc_01, reversed) converted to distance along
each ray, checked against a double-precision reference through the depth aov; and bad depth
buffers refused with data.path.

    python3 tests/integration/test_composite.py --bin build/bin
"""

import base64
import math
import os
import struct
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, expect_error  # noqa: E402

suite = mock.Suite("test_composite", timeout_s=400)
suite.server_args = []
T = suite.test

W, H = 96, 64
EYE, TARGET, UP, FOV = (0.3, 1.2, 5.0), (0.0, 0.5, 0.0), (0.0, 1.0, 0.0), 40.0
NEAR, FAR = 0.1, 100.0
BOX_POS, BOX_SCALE = (0.0, 0.5, 0.0), (1.0, 1.0, 1.0)


def sub(a, b):
    return [a[i] - b[i] for i in range(3)]


def norm(a):
    n = math.sqrt(sum(x * x for x in a))
    return [x / n for x in a]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def dot(a, b):
    return sum(a[i] * b[i] for i in range(3))


def rays():
    """Each pixel's unit ray direction and its cosine to the view axis, in double."""
    fw = norm(sub(TARGET, EYE))
    rt = norm(cross(fw, UP))
    up = cross(rt, fw)
    th = math.tan(math.radians(FOV) / 2)
    aspect = W / H
    out = []
    for y in range(H):
        for x in range(W):
            u = (2 * (x + 0.5) / W - 1) * th * aspect
            v = (1 - 2 * (y + 0.5) / H) * th
            d = norm([fw[i] + u * rt[i] + v * up[i] for i in range(3)])
            out.append((d, dot(d, fw)))
    return out


def box_t(d):
    """Distance along ray d from EYE to the box, or +inf (slab test in double)."""
    tin, tout = -math.inf, math.inf
    for i in range(3):
        lo = BOX_POS[i] - BOX_SCALE[i] / 2
        hi = BOX_POS[i] + BOX_SCALE[i] / 2
        if d[i] == 0:
            if not lo <= EYE[i] <= hi:
                return math.inf
            continue
        a, b = (lo - EYE[i]) / d[i], (hi - EYE[i]) / d[i]
        tin, tout = max(tin, min(a, b)), min(tout, max(a, b))
    return tin if tin <= tout and tin > 0 else math.inf


def depth_param(values, convention="linear", type="f32", **kw):
    """A depth param of 'values' stored as 'type': f32, f16 (struct's IEEE half) or u16 (each
    value times 65535, rounded)."""
    if type == "u16":
        packed = struct.pack("<%dH" % len(values), *[int(round(v * 65535)) for v in values])
    else:
        packed = struct.pack("<%d%s" % (len(values), "f" if type == "f32" else "e"), *values)
    p = {"width": W, "height": H, "data": base64.b64encode(packed).decode(),
         "convention": convention}
    if type != "f32":
        p["type"] = type
    return dict(p, **kw)


def scene(c, name):
    c.ok("scene.create", {"name": name})
    toward_eye = norm(sub(EYE, TARGET))
    c.ok("scene.set", {"scene": name, "patch": {
        "camera": {"eye": list(EYE), "target": list(TARGET), "up": list(UP), "fov_y": FOV,
                   "near": NEAR, "far": FAR},
        "light": {"direction": toward_eye, "intensity": 0.8, "ambient": 0.2},
        "background": [0.2, 0.3, 0.45],
        "objects": [{"shape": "box", "position": list(BOX_POS), "scale": list(BOX_SCALE),
                     "color": [0.8, 0.4, 0.2]}],
        "waves": [],
        "volumes": [{"id": "mist", "bounds": {"min": [-1.6, 0, -1.2], "max": [1.6, 1.6, 1.2]},
                     "density": 1.2, "albedo": [0.9, 0.9, 0.95], "samples": 48}],
        "render": {"tone_map": "none", "exposure": 0}}})


def floats(att):
    return struct.unpack("<%df" % (len(att) // 4), att)


def srgb_decode(b):
    x = b / 255
    return x / 12.92 if x <= 0.04045 else ((x + 0.055) / 1.055) ** 2.4


def srgb_encode(x):
    x = min(max(x, 0.0), 1.0)
    x = 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055
    return int(math.floor(x * 255 + 0.5))


def silhouette(ts):
    """Pixels next to a pixel whose box hit differs from theirs."""
    edge = set()
    for y in range(H):
        for x in range(W):
            hit = math.isfinite(ts[y * W + x])
            for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                xx, yy = x + dx, y + dy
                if 0 <= xx < W and 0 <= yy < H and math.isfinite(ts[yy * W + xx]) != hit:
                    edge.add(y * W + x)
    return edge


@T
def composite_matches_reference(s):
    c = s.srv.connect()
    scene(c, "g")
    rs = rays()
    ts = [box_t(d) for d, _ in rs]
    s.check(sum(math.isfinite(t) for t in ts) > W * H // 20, "the box covers part of the frame")
    z = [t * cosv if math.isfinite(t) else FAR for t, (_, cosv) in zip(ts, rs)]
    base = {"scene": "g", "width": W, "height": H}
    fx = dict(base, layers=["volumes"], background="transparent",
              depth=depth_param(z, far=FAR))
    edge = silhouette(ts)

    # Linear light: rgbaf32 is the linear picture before exposure and tone map.
    _, ref = c.ok("render", dict(base, format="rgbaf32"), timeout=120)
    _, game = c.ok("render", dict(base, format="rgbaf32", layers=["objects"]), timeout=120)
    r, eff = c.ok("render", dict(fx, format="rgbaf32"), timeout=120)
    s.check("game_depth" in r.get("work_ms", {}), "the frame reports a game_depth pass",
            str(r.get("work_ms")))
    ref, game, eff = floats(ref), floats(game), floats(eff)
    worst, total, n, covered = 0.0, 0.0, 0, 0
    for i in range(W * H):
        a = eff[4 * i + 3]
        covered += a > 0.01
        if i in edge:
            continue
        for k in range(3):
            e = abs(game[4 * i + k] * (1 - a) + eff[4 * i + k] - ref[4 * i + k])
            worst, total, n = max(worst, e), total + e, n + 1
    s.check(covered > W * H // 4, "the volume covers much of the effect-only frame",
            "%d pixels" % covered)
    s.check(worst < 1e-5 and total / n < 1e-6,
            "linear composite matches the reference: mean %.2g, max %.2g off %d silhouette "
            "pixels" % (total / n, worst, len(edge)))
    # Background pixels of the effect frame are transparent black; behind the box nothing.
    far_px = [i for i in range(W * H) if eff[4 * i + 3] == 0]
    s.check(far_px and all(eff[4 * i + k] == 0 for i in far_px for k in range(3)),
            "uncovered pixels are transparent black")

    # 8 bits with tone map none: blend in linear light after decoding sRGB.
    _, ref8 = c.ok("render", dict(base, format="rgba8"), timeout=120)
    _, game8 = c.ok("render", dict(base, format="rgba8", layers=["objects"]), timeout=120)
    _, eff8 = c.ok("render", dict(fx, format="rgba8"), timeout=120)
    worst, total, n = 0, 0, 0
    for i in range(W * H):
        if i in edge:
            continue
        a = eff8[4 * i + 3] / 255
        for k in range(3):
            lin = srgb_decode(game8[4 * i + k]) * (1 - a) + srgb_decode(eff8[4 * i + k])
            e = abs(srgb_encode(lin) - ref8[4 * i + k])
            worst, total, n = max(worst, e), total + e, n + 1
    s.check(worst <= 2 and total / n < 0.25,
            "8-bit composite matches the reference: mean %.3f, max %d levels" % (total / n, worst))
    # PNG carries the same premultiplied pixels.
    _, png = c.ok("render", dict(fx, format="png"), timeout=120)
    s.check(png[:8] == b"\x89PNG\r\n\x1a\n", "the effect-only frame is a PNG too")


def ray_ref(conv, t, cosv, **kw):
    """The value a client of 'conv' sends for ray distance t, in double."""
    if not math.isfinite(t):
        return {"linear": FAR, "ray": FAR, "ndc_gl": 1.0, "ndc_01": 1.0}[conv] \
            if not kw.get("reversed") else {"ndc_gl": -1.0, "ndc_01": 0.0}[conv]
    zv = t * cosv
    if conv == "linear":
        return zv
    if conv == "ray":
        return t
    d01 = FAR * (zv - NEAR) / (zv * (FAR - NEAR))
    if kw.get("reversed"):
        d01 = 1 - d01
        return d01 if conv == "ndc_01" else -(2 * (1 - d01) - 1)
    return d01 if conv == "ndc_01" else 2 * d01 - 1


@T
def depth_conventions(s):
    c = s.srv.connect()
    scene(c, "d")
    rs = rays()
    ts = [box_t(d) for d, _ in rs]
    # f16 rounds to 11 significant bits, a relative error of up to 2^-11 = 4.9e-4; u16 window
    # depth steps by 1/65535, which near z = 5 of a 0.1-100 projection is 0.004 units.
    cases = [("linear", {"far": FAR}, 2e-6), ("ray", {"far": FAR}, 2e-6),
             ("ndc_gl", {"near": NEAR, "far": FAR}, 2e-5),
             ("ndc_01", {"near": NEAR, "far": FAR}, 2e-5),
             ("ndc_01", {"near": NEAR, "far": FAR, "reversed": True}, 2e-5),
             ("ndc_gl", {"near": NEAR, "far": FAR, "reversed": True}, 2e-5),
             ("linear", {"far": FAR, "type": "f16"}, 5e-4),
             ("ray", {"far": FAR, "type": "f16"}, 5e-4),
             ("ndc_01", {"near": NEAR, "far": FAR, "type": "u16"}, 1.5e-3),
             ("ndc_01", {"near": NEAR, "far": FAR, "reversed": True, "type": "u16"}, 1.5e-3)]
    for conv, kw, tol in cases:
        vals = [ray_ref(conv, t, cosv, **kw) for t, (_, cosv) in zip(ts, rs)]
        p = {"scene": "d", "width": W, "height": H, "format": "f32", "aov": "depth",
             "layers": [], "depth": depth_param(vals, conv, **kw)}
        _, att = c.ok("render", p, timeout=120)
        got = floats(att)
        worst, wrong_inf = 0.0, 0
        for t, g in zip(ts, got):
            if math.isfinite(t):
                worst = max(worst, abs(g - t) / t)
            else:
                wrong_inf += math.isfinite(g)
        s.check(worst < tol and wrong_inf == 0,
                "%s %s: ray distances within %.1g relative (worst %.2g), %d misses not +inf" %
                (conv, kw, tol, worst, wrong_inf))


@T
def bad_depth(s):
    c = s.srv.connect()
    scene(c, "b")
    base = {"scene": "b", "width": W, "height": H, "format": "rgba8"}
    good = [1.0] * (W * H)
    expect_error(s, c, "render", dict(base, depth=dict(depth_param(good), width=W + 1)), E_PARAMS,
                 path="depth.width")
    expect_error(s, c, "render", dict(base, depth=dict(depth_param(good), height=1)), E_PARAMS,
                 path="depth.height")
    short = dict(depth_param(good), data=depth_param(good[:-1])["data"])
    expect_error(s, c, "render", dict(base, depth=short), E_PARAMS, path="depth.data")
    for bad in (float("nan"), float("inf"), -1.0):
        vals = list(good)
        vals[7] = bad
        expect_error(s, c, "render", dict(base, depth=depth_param(vals)), E_PARAMS,
                     path="depth.data")
    expect_error(s, c, "render", dict(base, depth=depth_param([0.5] * (W * H), "ndc_01", far=FAR)),
                 E_PARAMS, path="depth.near")
    expect_error(s, c, "render", dict(base, depth=depth_param([1.5] * (W * H), "ndc_01", near=NEAR,
                                                           far=FAR)), E_PARAMS, path="depth.data")
    expect_error(s, c, "render", dict(base, background="clear"), E_PARAMS, path="background")
    # The 2-byte types: a u16 buffer needs the ndc_01 convention; a buffer of f32 bytes given as
    # f16 has twice the bytes; an f16 infinity or NaN is refused like an f32 one.
    expect_error(s, c, "render", dict(base, depth=depth_param(good, type="u16")), E_PARAMS,
                 path="depth.type")
    expect_error(s, c, "render", dict(base, depth=dict(depth_param(good), type="f16")), E_PARAMS,
                 path="depth.data")
    for bad in (float("nan"), float("inf")):
        vals = list(good)
        vals[3] = bad
        expect_error(s, c, "render", dict(base, depth=depth_param(vals, type="f16")), E_PARAMS,
                     path="depth.data")
    expect_error(s, c, "render", dict(base, depth=dict(depth_param(good), type="f64")), E_PARAMS,
                 path="depth.type")
    expect_error(s, c, "frames.subscribe", dict(base, fps=5, depth=dict(depth_param(good), width=3)),
                 E_PARAMS, path="depth.width")


@T
def depth_from_another_camera(s):
    """A buffer drawn with camera A, given with depth.camera A for a frame of camera B, clips as
    B's own buffer would: against volfx's depth aov of the box seen from B, away from the box's
    silhouettes (where the reprojection leaves half a pixel empty and cannot know what A did not
    see) the hits agree and their distances match. A depth.camera equal to the frame's changes
    nothing."""
    c = s.srv.connect()
    scene(c, "rp")
    a = {"eye": [0.3, 1.7, 2.4], "target": list(TARGET)}
    b = {"eye": [0.6, 1.6, 2.3], "target": [0.05, 0.5, 0.0]}
    base = {"scene": "rp", "width": W, "height": H, "format": "f32", "aov": "depth"}

    def depth_of(**kw):
        return floats(c.ok("render", dict(base, **kw), timeout=120)[1])

    seen_a, seen_b = depth_of(camera=a), depth_of(camera=b)
    sent = [t if math.isfinite(t) else FAR for t in seen_a]
    r, att = c.ok("render", dict(base, camera=b, layers=[],
                                 depth=depth_param(sent, "ray", far=FAR, camera=a)), timeout=120)
    got = floats(att)
    s.check(list(r["work_ms"])[:1] == ["reproject"], "work_ms times the reprojection first",
            r["work_ms"])
    near = silhouette(seen_b)
    for _ in range(2):  # Two more pixels around every silhouette pixel.
        near |= {y * W + x for i in near for y in range(i // W - 1, i // W + 2)
                 for x in range(i % W - 1, i % W + 2) if 0 <= x < W and 0 <= y < H}
    rest = [i for i in range(W * H) if i not in near]
    hits = [i for i in rest if math.isfinite(seen_b[i])]
    agree = sum(math.isfinite(got[i]) == math.isfinite(seen_b[i]) for i in rest)
    errs = sorted(abs(got[i] - seen_b[i]) / seen_b[i] for i in hits if math.isfinite(got[i]))
    s.check(len(hits) > W * H // 8, "the box covers an eighth of the frame from B", len(hits))
    s.check(agree == len(rest), "away from silhouettes B's hits and misses agree (%d of %d)" %
            (agree, len(rest)))
    # A face's depth is drawn exactly (a plane); across a crease between two faces, a quad's
    # plane cuts the corner.
    s.check(errs[len(errs) * 9 // 10] < 1e-5 and errs[-1] < 0.02,
            "and the distances: 90%% within 1e-5 relative (%.2g), all within 2%% (worst %.2g)" %
            (errs[len(errs) * 9 // 10], errs[-1]))
    moved = sum(math.isfinite(x) != math.isfinite(y) for x, y in zip(seen_a, seen_b))
    s.check(moved > W, "the move shifts the box by more than a pixel (%d pixels change)" % moved)
    plain = c.ok("render", dict(base, camera=b, layers=[],
                                depth=depth_param(sent, "ray", far=FAR)), timeout=120)[1]
    same = c.ok("render", dict(base, camera=b, layers=[],
                               depth=depth_param(sent, "ray", far=FAR, camera=b)), timeout=120)[1]
    s.check(plain == same, "depth.camera equal to the frame's camera changes nothing")
    expect_error(s, c, "render", dict(base, depth=depth_param(sent, "ray", far=FAR,
                                                              camera={"fov_y": 0})),
                 E_PARAMS, path="depth.camera.fov_y")


def next_frame(c, sid):
    """The next 'frames' notification of subscription 'sid' on 'c': (params, attachment)."""
    while True:
        msg, att = c.recv_notification(timeout=60)
        if msg.get("method") == "frames" and msg["params"].get("id") == sid:
            return msg["params"], att


@T
def subscription_keeps_its_depth(s):
    """A subscription's depth buffer clips every frame: the first, one after a frames.update
    that moves the camera only (the buffer stays), and one after an update with a new buffer;
    each frame is the same as a render with the same params. A bad update changes nothing."""
    c = s.srv.connect()
    scene(c, "sd")
    ts = [box_t(d) for d, _ in rays()]
    wall = [0.5 if x < W // 2 else FAR for y in range(H) for x in range(W)]
    box = [t * cosv if math.isfinite(t) else FAR for t, (_, cosv) in zip(ts, rays())]
    base = {"scene": "sd", "width": W, "height": H, "format": "rgba8", "layers": ["volumes"],
            "background": "transparent"}
    moved = {"eye": [0.6, 1.3, 4.9], "target": list(TARGET)}

    def rendered(**kw):
        return c.ok("render", dict(base, **kw), timeout=120)[1]

    want = [rendered(depth=depth_param(wall)), rendered(depth=depth_param(wall), camera=moved),
            rendered(depth=depth_param(box), camera=moved)]
    s.check(len(set(want)) == 3, "the three views differ")
    v = s.srv.connect()
    sid = v.ok("frames.subscribe", dict(base, fps=20, depth=depth_param(wall)))[0]["id"]
    _, att = next_frame(v, sid)
    s.check(att == want[0], "the first frame is the render with the same depth buffer")
    v.ok("frames.update", {"id": sid, "camera": moved})
    _, att = next_frame(v, sid)
    s.check(att == want[1], "after a camera-only update the depth buffer still clips the frame")
    expect_error(s, v, "frames.update", {"id": sid, "width": W + 2}, E_PARAMS, path="depth.width")
    v.ok("frames.update", {"id": sid, "depth": depth_param(box)})
    _, att = next_frame(v, sid)
    s.check(att == want[2], "an update with a new depth buffer clips with it")
    v.ok("frames.unsubscribe", {"id": sid})


if __name__ == "__main__":
    sys.exit(suite.main())
