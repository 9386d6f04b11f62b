#!/usr/bin/env python3
"""
The documentation's cloud stills (not run by ctest), rendered through a real volfxd: the
paper-003 preset (a cloud growing on a 64³ grid by Dobashi's rules, blown along +x) as a
contact sheet of frames taken as the simulation steps, and one larger still.

    python3 tests/bench/cloud_images.py --bin build/bin --out docs/images

writes cloud_grow.png (the frames after the steps in --steps, left to right, top to bottom)
and cloud_paper003.png (after --still steps). Standard library only: the frames come back as
rgba8 and are laid out and written as PNG here.
"""

import argparse
import os
import struct
import sys
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
import mock  # noqa: E402


def write_png(path, width, height, rgb):
    """rgb: bytes of width x height x 3."""
    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    stride = 3 * width
    raw = b"".join(b"\0" + rgb[y * stride:(y + 1) * stride] for y in range(height))
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)))
        f.write(chunk(b"IDAT", zlib.compress(raw, 9)))
        f.write(chunk(b"IEND", b""))


def rgb_of(rgba):
    out = bytearray(len(rgba) // 4 * 3)
    out[0::3] = rgba[0::4]
    out[1::3] = rgba[1::4]
    out[2::3] = rgba[2::4]
    return bytes(out)


def frame(c, scene, w, h):
    r, data = c.ok("render", {"scene": scene, "width": w, "height": h, "format": "rgba8"},
                   timeout=120)
    return rgb_of(data), r.get("work_ms", {})


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--out", default="docs/images")
    ap.add_argument("--preset", default="paper-003")
    ap.add_argument("--steps", default="3,6,10,15,20,30,45,60,90,120,180,240",
                    help="simulation steps after which the sheet's frames are taken")
    ap.add_argument("--cols", type=int, default=4)
    ap.add_argument("--tile", type=int, default=256)
    ap.add_argument("--still", type=int, default=40, help="steps before the larger still")
    ap.add_argument("--still-size", type=int, default=768)
    args = ap.parse_args()
    steps = [int(x) for x in args.steps.split(",")]
    tile, cols, gap = args.tile, args.cols, 4
    rows = (len(steps) + cols - 1) // cols
    sw, sh = cols * tile + (cols + 1) * gap, rows * tile + (rows + 1) * gap
    sheet = bytearray(b"\x20" * (sw * sh * 3))
    os.makedirs(args.out, exist_ok=True)
    with mock.Server(args.bin) as srv:
        c = srv.connect(timeout=120)
        c.ok("scene.create", {"name": "grow", "preset": args.preset})
        done = 0
        for i, n in enumerate(steps):
            if n > done:
                c.ok("sim.step", {"scene": "grow", "steps": n - done}, timeout=120)
                done = n
            rgb, work = frame(c, "grow", tile, tile)
            x0 = gap + (i % cols) * (tile + gap)
            y0 = gap + (i // cols) * (tile + gap)
            for y in range(tile):
                at = ((y0 + y) * sw + x0) * 3
                sheet[at:at + tile * 3] = rgb[y * tile * 3:(y + 1) * tile * 3]
            print("step %4d: %s" % (n, work.get("volumes")))
        path = os.path.join(args.out, "cloud_grow.png")
        write_png(path, sw, sh, bytes(sheet))
        print("wrote", path)
        c.ok("scene.create", {"name": "still", "preset": args.preset})
        c.ok("sim.step", {"scene": "still", "steps": args.still}, timeout=120)
        size = args.still_size
        rgb, work = frame(c, "still", size, size)
        path = os.path.join(args.out, "cloud_paper003.png")
        write_png(path, size, size, rgb)
        print("wrote", path, "volumes pass %.1f ms" % work.get("volumes", 0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
