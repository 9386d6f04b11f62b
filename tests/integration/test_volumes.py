#!/usr/bin/env python3
"""
Volumes (SPEC §5.3) against a real volfxd: volumes[] set with defaults filled in and rendered
(the frame changes with the volumes layer and reports a "volumes" pass), a raw f32 grid file
under the data directory drawn with exactly exp(-sigma d) of a white background behind a
homogeneous box, u8 files, the paper-002 preset, and bad volumes refused with data.path while
the document stays as it was: wrong byte counts, negative and NaN densities, dims over the
cloud_side limit, paths out of the data directory, inverted bounds, missing file fields.

    python3 tests/integration/test_volumes.py --bin build/bin
"""

import math
import os
import struct
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_LIMIT, E_PARAMS, expect_error  # noqa: E402

suite = mock.Suite("test_volumes", timeout_s=400)
suite.server_args = []
T = suite.test

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def fresh(c, name):
    c.ok("scene.create", {"name": name})


def write(s, name, data):
    path = os.path.join(s.srv.data_dir, name)
    with open(path, "wb") as f:
        f.write(data)


def f32(values):
    return struct.pack("<%df" % len(values), *values)


@T
def set_and_render(s):
    c = s.srv.connect()
    fresh(c, "v")
    c.ok("scene.set", {"scene": "v", "patch": {"volumes": [{"id": "mist"}]}})
    vol = c.ok("scene.get", {"scene": "v", "path": "volumes.0"})[0]
    s.eq(vol.get("source"), "noise", "source defaults to noise")
    s.eq(vol.get("samples"), 32, "samples default")
    s.check(vol.get("density", 0) > 0, "density has a positive default")
    s.eq(vol.get("bounds"), {"min": [-1, 0, -1], "max": [1, 2, 1]}, "bounds default")
    params = {"scene": "v", "width": 64, "height": 64, "format": "png"}
    r, with_vol = c.ok("render", params, timeout=120)
    s.check("volumes" in (r.get("work_ms") or {}), "the render reports a volumes pass",
            str(r.get("work_ms")))
    _, without = c.ok("render", dict(params, layers=["objects", "fluid", "waves"]), timeout=120)
    s.check(with_vol != without, "the volume is visible in the render")
    # Deterministic: the same scene renders the same bytes.
    _, again = c.ok("render", params, timeout=120)
    s.check(again == with_vol, "the noise volume renders the same twice")


@T
def file_transmittance(s):
    c = s.srv.connect()
    fresh(c, "t")
    write(s, "one.f32", f32([1.0] * 8))
    cam = {"eye": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 20, "near": 0.01,
           "far": 100}
    sigma = 0.8
    c.ok("scene.set", {"scene": "t", "patch": {
        "camera": cam, "background": [1, 1, 1],
        "light": {"intensity": 0, "ambient": 0},
        "render": {"tone_map": "none", "exposure": 0},
        "volumes": [{"source": "file", "file": "one.f32", "format": "f32", "dims": [2, 2, 2],
                     "bounds": {"min": [-1, -1, -1], "max": [1, 1, 1]},
                     "density": sigma, "albedo": [0, 0, 0], "samples": 3}]}})
    _, img = c.ok("render", {"scene": "t", "width": 9, "height": 9, "format": "rgbaf32"},
                  timeout=120)
    px = struct.unpack("<%df" % (len(img) // 4), img)
    # The middle pixel's ray runs along -z through the box: 2 units of medium.
    mid = px[4 * (4 * 9 + 4)]
    s.check(abs(mid - math.exp(-2 * sigma)) < 1e-5, "middle pixel shows exp(-sigma * 2)",
            "%.7f vs %.7f" % (mid, math.exp(-2 * sigma)))
    s.check(abs(px[0] - 1) < 1e-6 or px[0] < 1, "corner pixel no brighter than the background")

    # u8: 255 is density 1, so the same file as bytes renders the same.
    write(s, "one.u8", bytes([255] * 8))
    c.ok("scene.set", {"scene": "t", "path": "volumes.0",
                       "value": {"source": "file", "file": "one.u8", "format": "u8",
                                 "dims": [2, 2, 2], "bounds": {"min": [-1, -1, -1],
                                                               "max": [1, 1, 1]},
                                 "density": sigma, "albedo": [0, 0, 0], "samples": 3}})
    _, img2 = c.ok("render", {"scene": "t", "width": 9, "height": 9, "format": "rgbaf32"},
                   timeout=120)
    s.check(img2 == img, "a u8 file of 255s renders as f32 ones")


@T
def bad_volumes(s):
    c = s.srv.connect()
    fresh(c, "bad")
    write(s, "ok.f32", f32([0.5] * 24))
    good = {"source": "file", "file": "ok.f32", "format": "f32", "dims": [2, 3, 4]}
    c.ok("scene.set", {"scene": "bad", "patch": {"volumes": [good]}})
    doc = c.ok("scene.get", {"scene": "bad"})[0]

    def refused(vol, path, what, code=E_PARAMS):
        return expect_error(s, c, "scene.set",
                            {"scene": "bad", "patch": {"volumes": [good, vol]}}, code, path, what)

    write(s, "short.f32", f32([0.5] * 23))
    refused(dict(good, file="short.f32"), "volumes.1.file", "one float short of dims")
    refused(dict(good, dims=[2, 3, 5]), "volumes.1.file", "dims larger than the file")
    refused(dict(good, format="u8"), "volumes.1.file", "f32 bytes read as u8")
    write(s, "neg.f32", f32([0.5] * 10 + [-0.25] + [0.5] * 13))
    refused(dict(good, file="neg.f32"), "volumes.1.file", "a negative density")
    write(s, "nan.f32", f32([0.5] * 5 + [float("nan")] + [0.5] * 18))
    refused(dict(good, file="nan.f32"), "volumes.1.file", "a NaN density")
    write(s, "inf.f32", f32([0.5] * 23 + [float("inf")]))
    refused(dict(good, file="inf.f32"), "volumes.1.file", "an infinite density")
    refused(dict(good, dims=[300, 1, 1]), "volumes.1.dims.0", "dims over cloud_side (256)",
            E_LIMIT)
    refused(dict(good, dims=[2.5, 3, 4]), "volumes.1.dims.0", "fractional dims")
    r = refused(dict(good, dims=[0, 3, 4]), "volumes.1.dims.0", "zero dims")
    msg = ((r or {}).get("error") or {}).get("message", "")
    s.check("65536" not in msg, "the zero dims' message names no bound but this server's", msg)
    refused({"source": "file", "dims": [2, 3, 4]}, "volumes.1.file", "no file")
    refused({"source": "file", "file": "ok.f32"}, "volumes.1.dims", "no dims")
    refused(dict(good, file="../ok.f32"), "volumes.1.file", "a path out of the data directory")
    refused(dict(good, file="/etc/passwd"), "volumes.1.file", "an absolute path")
    refused(dict(good, file="missing.f32"), "volumes.1.file", "a missing file")
    # A noise volume reads no file, but what it holds is checked all the same.
    refused({"source": "noise", "file": "../../etc/passwd"}, "volumes.1.file",
            "a noise volume naming a file out of the data directory")
    refused({"source": "noise", "dims": [2.5, 1, 1]}, "volumes.1.dims.0",
            "a noise volume with fractional dims")
    refused({"bounds": {"min": [0, 0, 0], "max": [1, -1, 1]}}, "volumes.1.bounds.max",
            "inverted bounds")
    refused({"density": -1}, "volumes.1.density", "negative density")
    refused({"samples": 0}, "volumes.1.samples", "zero samples")
    refused({"albedo": [0.5, 1.5, 0.5]}, "volumes.1.albedo.1", "albedo above 1")
    refused({"source": "smoke"}, "volumes.1.source", "unknown source")
    refused({"id": "x", "colour": [1, 1, 1]}, "volumes.1.colour", "unknown member")
    expect_error(s, c, "scene.set", {"scene": "bad", "patch": {"volumes": [
        dict(good, id="a"), dict(good, id="a")]}}, E_PARAMS, "volumes.1.id", "duplicate ids")
    s.eq(c.ok("scene.get", {"scene": "bad"})[0], doc, "refused volumes left the document unchanged")
    # The scene still renders with its one good volume.
    r, _ = c.ok("render", {"scene": "bad", "width": 16, "height": 16, "format": "png"},
                timeout=120)
    s.check("volumes" in (r.get("work_ms") or {}), "the good volume is still drawn")


@T
def side_limit(s):
    path = mock.config_file({"limits": {"cloud_side": 8}})
    # The demo's cloud grid is over a cloud_side of 8, so the main scene is another preset.
    with mock.Server(s.bin, "--config", path, "--scene", "paper-000") as srv:
        with open(os.path.join(srv.data_dir, "g.f32"), "wb") as f:
            f.write(f32([0.25] * 9 * 2 * 2))
        c = srv.connect()
        before = c.ok("scene.get", {"scene": "main", "path": "volumes"})[0]
        vol = {"source": "file", "file": "g.f32", "dims": [9, 2, 2]}
        expect_error(s, c, "scene.set", {"scene": "main", "patch": {"volumes": [vol]}}, E_LIMIT,
                     "volumes.0.dims.0", "dims over a configured cloud_side of 8")
        s.eq(c.ok("scene.get", {"scene": "main", "path": "volumes"})[0], before,
             "the refused volume was not added")
        with open(os.path.join(srv.data_dir, "h.f32"), "wb") as f:
            f.write(f32([0.25] * 8 * 2 * 2))
        c.ok("scene.set", {"scene": "main", "patch": {"volumes": [
            {"source": "file", "file": "h.f32", "dims": [8, 2, 2]}]}})
        s.eq(c.ok("scene.get", {"scene": "main", "path": "volumes.0.dims"})[0], [8, 2, 2],
             "dims at the configured limit are accepted")


@T
def preset(s):
    c = s.srv.connect()
    with open(os.path.join(ROOT, "scenes", "paper-002.json")) as f:
        text = f.read()
    doc = mock.loads(text)
    fresh(c, "p")
    c.ok("scene.set", {"scene": "p", "patch": doc})
    got = c.ok("scene.get", {"scene": "p", "path": "volumes.0.samples"})[0]
    s.eq(got, 32, "paper-002 samples 32 per ray")
    r, img = c.ok("render", {"scene": "p", "width": 128, "height": 128, "format": "png"},
                  timeout=120)
    s.check(img is not None and img[:4] == b"\x89PNG", "paper-002 renders")
    s.check("volumes" in (r.get("work_ms") or {}), "paper-002 draws its mist")


@T
def low_resolution(s):
    """render.volume_resolution: the paper-002 scene with its volumes pass at half and a quarter
    of the frame's size looks like the full pass, within a few levels on average."""
    c = s.srv.connect()
    with open(os.path.join(ROOT, "scenes", "paper-002.json")) as f:
        doc = mock.loads(f.read())
    fresh(c, "lo")
    c.ok("scene.set", {"scene": "lo", "patch": doc})
    s.eq(c.ok("scene.get", {"scene": "lo", "path": "render.volume_resolution"})[0], "full",
         "volume_resolution defaults to full")
    params = {"scene": "lo", "width": 160, "height": 160, "format": "rgba8"}
    _, full = c.ok("render", params, timeout=120)
    for res in ("half", "quarter"):
        c.ok("scene.set", {"scene": "lo", "path": "render.volume_resolution", "value": res})
        r, img = c.ok("render", params, timeout=120)
        s.check("volumes" in (r.get("work_ms") or {}), "%s: a volumes pass" % res)
        diff = [abs(a - b) for a, b in zip(full, img)]
        mean = sum(diff) / max(len(diff), 1)
        s.check(img != full and mean < 4, "%s: the image differs from the full pass by %.2f "
                "levels on average" % (res, mean))
    expect_error(s, c, "scene.set", {"scene": "lo", "path": "render.volume_resolution",
                                     "value": "eighth"}, E_PARAMS, "render.volume_resolution",
                 "an unknown volume_resolution")
    s.eq(c.ok("scene.get", {"scene": "lo", "path": "render.volume_resolution"})[0], "quarter",
         "the refused value left the setting")


@T
def discover(s):
    c = s.srv.connect()
    doc = c.ok("rpc.discover", {})[0]
    text = mock.dumps(doc)
    for word in ("phase_g", "noise_scale", "1/world unit", "cloud_side"):
        s.check(word in text, "rpc.discover documents %s" % word)
    # The grid sides are published with the server's own limit, as integers.
    scene = doc["components"]["schemas"]["Scene"]["properties"]
    side = c.ok("server.info")[0]["limits"]["cloud_side"]
    for what, v in (("cloud.grid", scene["cloud"]["properties"]["grid"]),
                    ("volumes[].dims", scene["volumes"]["items"]["properties"]["dims"])):
        s.eq(v["items"].get("type"), "integer", "%s sides are integers" % what)
        s.eq(v["items"].get("maximum"), side, "%s sides are bounded by limits.cloud_side" % what)


if __name__ == "__main__":
    sys.exit(suite.main())
