#!/usr/bin/env python3
"""
The same fluid rendered by volfx and by POV-Ray (not run by ctest; skipped when `povray` is
not on PATH): the particles of a preset, as volfx holds them, written as the components of one
POV-Ray `blob` with the preset's camera, light, floor and objects, and both renderers timed on
the same image in one run on the same machine. POV-Ray is the CPU ray tracer a user might pick
instead for metaballs.

    python3 tests/bench/bench_povray.py --bin build/bin --out out/povray
    python3 tests/bench/bench_povray.py --bin build/bin --preset paper-001-flow --steps 45

The fields differ, and no choice of POV-Ray's numbers makes them equal. volfx draws the paper's
P(r) = (1 - r/h)² with the surface where sqrt(sum P) = T; a POV-Ray blob component of radius R
and strength s adds s (1 - (r/R)²)² and the surface is where the sum reaches its threshold t.
Here R = h and s = 1, and t = (1 - (1 - T)²)² so that a lone particle's surface has the same
radius h (1 - T) in both. Where particles merge, POV-Ray's kernel is flatter near the centre
and steeper near R than the paper's, so the block's faces sit a little differently (the script
prints where, for a lattice of spacing h/2).

volfx renders with its water material (Fresnel reflection of the background, tinted
transmission, a specular highlight; no refracted rays). POV-Ray is timed twice: 'water', a
transparent filtered pigment with Fresnel reflection and ior 1.33 (true reflected and
refracted rays, so more work per pixel than volfx does), and 'opaque', the same surface as an
opaque specular one (the least POV-Ray can do for this surface). Both use every core
(+WT), no anti-aliasing, and are timed by the wall clock of the povray process, parsing and
bounding included (POV-Ray's own trace time is printed beside).
"""

import argparse
import math
import os
import re
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402

MIRROR = (1, 1, -1)  # volfx is right-handed, POV-Ray left-handed: z flips.


def m3(v):
    return [v[i] * MIRROR[i] for i in range(3)]


def vec(v):
    return "<%.6g, %.6g, %.6g>" % tuple(v)


def rotation(deg):
    """Rz Ry Rx (X applied first), as volfx builds an object's rotation."""
    a, b, c = (math.radians(x) for x in deg)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), \
        math.sin(c)
    return [[cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa],
            [sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa],
            [-sb, cb * sa, cb * ca]]


def pov_matrix(o):
    """POV-Ray's matrix for an object: p' = M (R S p + c), M the z mirror (row-vector form)."""
    r = rotation(o.get("rotation", [0, 0, 0]))
    sc = o.get("scale", [1, 1, 1]) if o["shape"] != "plane" else [1, 1, 1]
    a = [[MIRROR[i] * r[i][j] * sc[j] for j in range(3)] for i in range(3)]
    t = m3(o.get("position", [0, 0, 0]))
    # POV-Ray: x' = v00 x + v10 y + v20 z + t0, so v_ij = A_ji.
    vals = [a[j][i] for i in range(3) for j in range(3)] + t
    return "matrix <%s>" % ", ".join("%.6g" % x for x in vals)


def pov_scene(doc, pos, width, height, water):
    cam, light, fl = doc["camera"], doc["light"], doc["fluid"]
    h, T = fl["h"], fl["threshold"]
    t = (1 - (1 - T) ** 2) ** 2
    aspect = width / height
    hfov = math.degrees(2 * math.atan(math.tan(math.radians(cam["fov_y"]) / 2) * aspect))
    li = [c * light["intensity"] for c in light["color"]]
    out = ["#version 3.7;",
           "global_settings { assumed_gamma 1.0 max_trace_level 6 ambient_light rgb 1 }",
           "background { rgb %s }" % vec(doc["background"]),
           "camera { perspective location %s look_at %s sky %s right x*%.6g up y angle %.6g }"
           % (vec(m3(cam["eye"])), vec(m3(cam["target"])), vec(m3(cam["up"])), aspect, hfov),
           "light_source { %s color rgb %s parallel point_at <0, 0, 0> }"
           % (vec([x * 1e4 for x in m3(light["direction"])]), vec(li))]
    amb = light.get("ambient", 0.15)
    for o in doc.get("objects", []):
        fin = "finish { ambient %.4g diffuse 1 }" % amb
        pig = "pigment { rgb %s }" % vec(o.get("color", [0.8, 0.8, 0.8]))
        if o["shape"] == "plane":
            out.append("plane { y, 0 %s %s %s }" % (pig, fin, pov_matrix(o)))
        elif o["shape"] == "sphere":
            out.append("sphere { 0, 0.5 %s %s %s }" % (pig, fin, pov_matrix(o)))
        elif o["shape"] == "box":
            out.append("box { -0.5, 0.5 %s %s %s }" % (pig, fin, pov_matrix(o)))
    col = fl["material"]["color"]
    if water:
        tex = ("texture { pigment { rgbf <%.4g, %.4g, %.4g, 0.9> } finish { ambient 0 diffuse 0.1 "
               "specular 0.8 roughness 0.002 reflection { 0.02, 1 fresnel on } conserve_energy } }"
               " interior { ior %.4g }" % (col[0], col[1], col[2], fl["material"]["ior"]))
    else:
        tex = ("texture { pigment { rgb <%.4g, %.4g, %.4g> } finish { ambient %.4g diffuse 0.7 "
               "specular 0.8 roughness 0.002 } }" % (col[0], col[1], col[2], amb))
    out.append("blob { threshold %.9g" % t)
    for i in range(0, len(pos), 3):
        out.append("  sphere { %s, %.6g, 1 }" % (vec(m3(pos[i:i + 3])), h))
    out.append("  %s\n}" % tex)
    return "\n".join(out) + "\n"


def face_offsets(h, T, spacing):
    """Where each field's surface crosses the normal through a particle of the top layer of a
    deep lattice (the distance above that layer), by bisection."""
    t = (1 - (1 - T) ** 2) ** 2
    k = int(math.ceil(h / spacing)) + 1
    pts = [(i * spacing, j * spacing, -l * spacing) for i in range(-k, k + 1)
           for j in range(-k, k + 1) for l in range(0, k + 1)]

    def ours(z):
        s = sum(max(0.0, 1 - math.dist((0, 0, z), p) / h) ** 2 for p in pts)
        return math.sqrt(s) - T

    def pov(z):
        return sum(max(0.0, 1 - (math.dist((0, 0, z), p) / h) ** 2) ** 2 for p in pts) - t

    def root(f):
        lo, hi = 0.0, h
        for _ in range(60):
            mid = (lo + hi) / 2
            if f(mid) >= 0:
                lo = mid
            else:
                hi = mid
        return lo

    return root(ours), root(pov)


def run_povray(pov_path, png_path, width, height):
    cmd = ["povray", "+I" + pov_path, "+O" + png_path, "+W%d" % width, "+H%d" % height, "+FN",
           "-D", "-P", "+A0.0", "-A", "+WT%d" % (os.cpu_count() or 1), "-V"]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit("povray failed:\n" + p.stdout[-2000:])
    m = re.search(r"Trace Time:\s+(\d+) hours\s+(\d+) minutes\s+(\d+) seconds \((\d+\.\d+) seconds",
                  p.stdout)
    trace = float(m.group(4)) if m else float("nan")
    return wall, trace


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join("build", "bin"))
    ap.add_argument("--preset", default="paper-001")
    ap.add_argument("--steps", type=int, default=0, help="sim.step the preset first")
    ap.add_argument("--sizes", default="256,512")
    ap.add_argument("--runs", type=int, default=5, help="volfx renders per size (median)")
    ap.add_argument("--out", default=None, help="keep the images and .pov files here")
    args = ap.parse_args()
    if shutil.which("povray") is None:
        print("povray is not on PATH: nothing to compare (apt-get install povray)")
        return 0
    sizes = [int(x) for x in args.sizes.split(",")]
    out = args.out or tempfile.mkdtemp(prefix="volfx-povray-")
    os.makedirs(out, exist_ok=True)
    suite = mock.Suite("bench_povray")  # The harness records into a suite; none is checked.
    suite.args = args
    rows = []
    with mock.Server(os.path.abspath(args.bin), "--log-level", "warn") as srv:
        c = srv.connect(timeout=600)
        c.ok("scene.create", {"name": "pov", "preset": args.preset})
        if args.steps:
            c.ok("sim.step", {"scene": "pov", "steps": args.steps}, timeout=600)
        doc = c.ok("scene.get", {"scene": "pov"})[0]
        r, att = c.ok("fluid.get_particles", {"scene": "pov"})
        pos = struct.unpack("<%df" % (len(att) // 4), att)
        n = r["count"]
        for size in sizes:
            params = {"scene": "pov", "width": size, "height": size, "format": "png",
                      "png_level": 6}
            work, wall, fluid = [], [], []
            for i in range(args.runs + 1):
                t0 = time.perf_counter()
                res, png = c.ok("render", params, timeout=600)
                if i == 0:
                    continue  # warm-up
                wall.append(time.perf_counter() - t0)
                work.append(res["work_ms"]["total"])
                fluid.append(res["work_ms"].get("fluid", 0))
            ours = os.path.join(out, "volfx_%d.png" % size)
            with open(ours, "wb") as f:
                f.write(png)
            pov = {}
            for kind in ("water", "opaque"):
                path = os.path.join(out, "povray_%s_%d" % (kind, size))
                with open(path + ".pov", "w") as f:
                    f.write(pov_scene(doc, pos, size, size, kind == "water"))
                pov[kind] = run_povray(path + ".pov", path + ".png", size, size)
            rows.append((size, statistics.median(wall), statistics.median(work),
                         statistics.median(fluid), pov))
    fl = doc["fluid"]
    ours_off, pov_off = face_offsets(fl["h"], fl["threshold"], fl["h"] / 2)
    print("`%s`" % " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]))
    print()
    print("%d particles of preset %s%s; images in %s" %
          (n, args.preset, " after %d steps" % args.steps if args.steps else "", out))
    print()
    print("| size | volfx ms (round trip) | volfx work ms | of which fluid | POV-Ray water s "
          "(trace) | POV-Ray opaque s (trace) | POV-Ray opaque / volfx |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for size, wall, work, fluid, pov in rows:
        print("| %d² | %.1f | %.1f | %.1f | %.2f (%.2f) | %.2f (%.2f) | %.0f× |" %
              (size, 1e3 * wall, work, fluid, pov["water"][0], pov["water"][1],
               pov["opaque"][0], pov["opaque"][1], pov["opaque"][0] / wall))
    print()
    print("volfx: median of %d renders through the server (PNG, read by the client). POV-Ray: "
          "one run each, %d threads. Lone particle surface radius %.4f in both; over a lattice "
          "of spacing h/2 the top face lies %.4f (volfx) and %.4f (POV-Ray) above the last "
          "layer." % (args.runs, os.cpu_count() or 1, fl["h"] * (1 - fl["threshold"]), ours_off,
                      pov_off))
    return 0


if __name__ == "__main__":
    sys.exit(main())
