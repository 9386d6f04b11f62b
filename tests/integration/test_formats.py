#!/usr/bin/env python3
"""
The compressed frame formats over a real socket: render, frames.subscribe (with
frames.update switching the format live), render.sequence and volfx batch each give JPEG and
WebP files whose headers name the asked size, much smaller than the PNG of the same frame;
quality changes the bytes; webp at quality 100 is lossless and keeps a transparent
background's alpha; and bad input is refused with the param named: a quality out of range, an
unknown format, a transparent background in jpeg, a jpeg of the depth aov.

    python3 tests/integration/test_formats.py --bin build/bin
"""

import os
import struct
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, expect_error  # noqa: E402

suite = mock.Suite("test_formats", timeout_s=300)
suite.server_args = []
T = suite.test

W, H = 160, 90


def jpeg_size(data):
    """(width, height) from a JPEG's start-of-frame segment, or None when 'data' is not a
    whole JPEG (start and end markers)."""
    if data[:3] != b"\xff\xd8\xff" or data[-2:] != b"\xff\xd9":
        return None
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            return None
        marker, length = data[i + 1], struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2):
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        i += 2 + length
    return None


def webp_info(data):
    """(width, height, kind) of a WebP ('VP8 ' lossy, 'VP8L' lossless, 'VP8X' extended, with
    alpha), or None when 'data' is not a whole WebP."""
    if data[:4] != b"RIFF" or data[8:12] != b"WEBP":
        return None
    if struct.unpack("<I", data[4:8])[0] + 8 != len(data):
        return None
    kind = data[12:16]
    if kind == b"VP8 ":
        w, h = struct.unpack("<HH", data[26:30])
        return w & 0x3FFF, h & 0x3FFF, "lossy"
    if kind == b"VP8L":
        b = int.from_bytes(data[21:25], "little")
        return (b & 0x3FFF) + 1, ((b >> 14) & 0x3FFF) + 1, "lossless"
    if kind == b"VP8X":
        w = int.from_bytes(data[24:27], "little") + 1
        h = int.from_bytes(data[27:30], "little") + 1
        return w, h, "alpha" if data[20] & 0x10 else "extended"
    return None


def render(c, **p):
    params = dict(width=W, height=H)
    params.update(p)
    return c.ok("render", params)


@T
def render_jpeg_and_webp(s):
    c = s.srv.connect()
    png_r, png = render(c, format="png")
    r, jpg = render(c, format="jpeg")
    s.eq(r["format"], "jpeg", "the answer names the format")
    s.eq(jpeg_size(jpg), (W, H), "a whole JPEG of the asked size")
    s.check(len(jpg) * 3 < len(png), "jpeg q85 well under png",
            "jpeg %d bytes, png %d" % (len(jpg), len(png)))
    s.check("encode" in r["work_ms"], "the encoder is timed", r["work_ms"])
    _, low = render(c, format="jpeg", quality=10)
    s.check(jpeg_size(low) == (W, H) and len(low) < len(jpg), "quality 10 is smaller",
            "%d vs %d" % (len(low), len(jpg)))
    _, wp = render(c, format="webp")
    s.eq(webp_info(wp)[:2], (W, H), "a whole WebP of the asked size")
    s.check(len(wp) < len(png), "webp under png", "%d vs %d" % (len(wp), len(png)))
    _, wl = render(c, format="webp", quality=100)
    s.eq(webp_info(wl), (W, H, "lossless"), "quality 100 is lossless WebP")
    # Lossless and transparent: the alpha plane travels (VP8L carries it in every pixel).
    _, wt = render(c, format="webp", quality=100, background="transparent",
                   layers=["volumes", "cloud", "fluid", "waves"])
    s.eq(webp_info(wt)[:2], (W, H), "a transparent lossless WebP")
    _, wa = render(c, format="webp", quality=80, background="transparent",
                   layers=["volumes", "cloud", "fluid", "waves"])
    s.eq(webp_info(wa), (W, H, "alpha"), "lossy WebP of a transparent frame keeps an alpha plane")
    # base64 encoding carries the same bytes.
    r64, _ = render(c, format="jpeg", encoding="base64")
    import base64
    s.eq(jpeg_size(base64.b64decode(r64["data"])), (W, H), "jpeg inline as base64")
    c.close()


@T
def bad_params(s):
    c = s.srv.connect()
    expect_error(s, c, "render", {"format": "jpeg", "quality": 0}, E_PARAMS, "quality")
    expect_error(s, c, "render", {"format": "webp", "quality": 101}, E_PARAMS, "quality")
    expect_error(s, c, "render", {"format": "jpeg", "quality": 85.5}, E_PARAMS, "quality")
    expect_error(s, c, "render", {"format": "jpg"}, E_PARAMS, "format")
    expect_error(s, c, "render", {"format": "jpeg", "background": "transparent"}, E_PARAMS,
                 "background")
    expect_error(s, c, "render", {"format": "jpeg", "aov": "depth"}, E_PARAMS, "format")
    expect_error(s, c, "frames.subscribe", {"format": "webp", "quality": -3}, E_PARAMS, "quality")
    # The server goes on.
    _, jpg = render(c, format="jpeg")
    s.eq(jpeg_size(jpg), (W, H), "a good render after the bad ones")
    c.close()


@T
def subscription_switches_format(s):
    c = s.srv.connect()
    c.ok("sim.play", {"rate": 60})
    sid = c.ok("frames.subscribe", {"width": W, "height": H, "fps": 20, "format": "jpeg",
                                    "quality": 70})[0]["id"]
    msg, att = c.recv_notification(timeout=30)
    s.eq((msg["params"]["format"], jpeg_size(att)), ("jpeg", (W, H)), "a jpeg frame")
    c.ok("frames.update", {"id": sid, "format": "webp", "quality": 60, "tag": "to-webp"})
    deadline = time.monotonic() + 20
    seen = None
    while time.monotonic() < deadline:
        msg, att = c.recv_notification(timeout=20)
        if msg.get("method") == "frames" and msg["params"].get("format") == "webp":
            seen = (webp_info(att)[:2], msg["params"].get("tag"))
            break
    s.eq(seen, ((W, H), "to-webp"), "after frames.update the frames are WebP, tagged")
    err = c.err("frames.update", {"id": sid, "quality": 0})
    s.eq(err["code"], E_PARAMS, "a bad quality in frames.update")
    c.ok("frames.unsubscribe", {"id": sid})
    c.ok("sim.pause", {})
    c.close()


@T
def sequence_and_batch(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "seqj", "preset": "demo"})
    r, _ = c.ok("render.sequence", {"scene": "seqj", "first": 0, "last": 2, "dir": "jpg",
                                    "width": W, "height": H, "format": "jpeg", "quality": 60})
    s.check(r["files"].endswith(".jpeg"), "the files are named .jpeg", r["files"])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        msg, _ = c.recv_notification(timeout=120)
        if msg.get("method") == "job.progress" and msg["params"]["state"] != "running":
            s.eq(msg["params"]["state"], "done", "the jpeg sequence finishes")
            break
    d = os.path.join(s.srv.data_dir, "jpg")
    names = sorted(os.listdir(d))
    s.eq(names, ["frame_000000.jpeg", "frame_000001.jpeg", "frame_000002.jpeg"], "three files")
    for n in names:
        with open(os.path.join(d, n), "rb") as f:
            s.eq(jpeg_size(f.read()), (W, H), "%s is a whole JPEG" % n)
    c.close()

    # volfx batch with WebP names and a quality; a second run finds every frame complete.
    out = os.path.join(s.srv.data_dir, "batch")
    cmd = [os.path.join(suite.bin, "volfx"), "batch", "--start", "0", "--end", "1",
           "-o", os.path.join(out, "f_###.webp"), "--format", "webp", "--quality", "70",
           "-W", str(W), "-H", str(H), "demo"]
    env = dict(os.environ, VOLFX_VOLFXD=os.path.join(suite.bin, "volfxd"))
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    s.check(p.returncode == 0, "volfx batch --format webp", p.stderr[-500:])
    for n in ("f_000.webp", "f_001.webp"):
        with open(os.path.join(out, n), "rb") as f:
            s.eq(webp_info(f.read())[:2], (W, H), "%s is a whole WebP" % n)
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    s.check(p.returncode == 0 and "nothing left to do" in p.stdout + p.stderr,
            "a second batch skips the complete WebP files", p.stdout + p.stderr)
    p = subprocess.run(cmd[:-1] + ["--quality", "0", "demo"], capture_output=True, text=True,
                       timeout=60, env=env)
    s.check(p.returncode == 2 and "quality" in p.stderr, "batch --quality 0 is a usage error",
            p.stderr)

    # Without --format the file names' extension picks the format; a name that contradicts
    # --format is refused before anything is rendered.
    jpg = cmd[:-1]
    at = jpg.index("--format")
    del jpg[at:at + 2]
    jpg[jpg.index("-o") + 1] = os.path.join(out, "g_###.JPG")
    p = subprocess.run(jpg + ["demo"], capture_output=True, text=True, timeout=120, env=env)
    s.check(p.returncode == 0, "volfx batch -o g_###.JPG without --format", p.stderr[-500:])
    for n in ("g_000.JPG", "g_001.JPG"):
        with open(os.path.join(out, n), "rb") as f:
            s.eq(jpeg_size(f.read()), (W, H), "%s is a whole JPEG" % n)
    clash = cmd[:-1]
    clash[clash.index("-o") + 1] = os.path.join(out, "h_###.png")
    p = subprocess.run(clash + ["demo"], capture_output=True, text=True, timeout=60, env=env)
    s.check(p.returncode == 2 and "names png files" in p.stderr and "webp" in p.stderr,
            "batch -o h_###.png --format webp is a usage error naming both", p.stderr)
    s.check(not any(n.startswith("h_") for n in os.listdir(out)), "and writes nothing")


if __name__ == "__main__":
    suite.main()
