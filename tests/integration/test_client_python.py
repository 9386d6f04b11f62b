#!/usr/bin/env python3
"""Integration test of the Python clients (client/python/volfx) and libvolfx's method list
against a real volfxd started with volfx.testing:

- latest-wins: while a call blocks, the client holds at most one frame per subscription, the
  one it hands out is the newest, and the replaced ones are counted;
- frames.ended: a deleted scene's subscription ends, and the client says why;
- a batch: one line, a result or an error per call, attachments in their places;
- every wrapper: volfx.METHODS and libvolfx's VOLFX_METHOD_MAP name every method rpc.discover
  lists (a new server method without a wrapper fails here), and each wrapper is called;
- the asyncio client: concurrent calls, a subscription, latest(), frames(), a batch.

Run from the repository root: python3 tests/integration/test_client_python.py --bin build/bin
"""

import argparse
import asyncio
import os
import re
import struct
import sys
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "client", "python"))

import volfx  # noqa: E402
from volfx import testing  # noqa: E402

TOTAL_TIMEOUT = 400  # seconds for the whole test
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class Failure(Exception):
    pass


def check(cond, what):
    if not cond:
        raise Failure(what)


def test_latest_wins(c):
    """Frames pile up on the socket while the client sleeps and then blocks in a call."""
    c.play(rate=60)
    sid = c.subscribe(width=16, height=16, fps=60, repeat=True)  # a steady stream
    time.sleep(1.0)
    c.info()  # reads every frame that arrived meanwhile, keeping only the newest
    held = [k for k in c.inbox.latest if k == sid]
    check(len(held) <= 1, "the client holds %d frames of one subscription" % len(held))
    check(c.replaced(sid) > 0, "no frame was replaced during a blocked second at 60 fps")
    replaced = c.replaced(sid)
    f = c.latest(sid, timeout=10)
    check(f is not None and f.id == sid, "latest() gave %r" % (f,))
    check(f.data[:8] == PNG_SIGNATURE, "the latest frame is not a PNG")
    check(len(c.inbox.latest) == 0, "latest() left a frame behind")
    c.pause()
    # The newest: what latest() gave is at least the frame every earlier one showed.
    time.sleep(0.3)
    g = c.latest(sid, timeout=10)
    check(g is not None and g.params["frame"] >= f.params["frame"],
          "a later latest() went back in time: %r then %r" % (f.params["frame"],
                                                              g and g.params["frame"]))
    check(c.replaced(sid) >= replaced, "the replaced count went down")
    got = list(c.frames(count=2, timeout=10, sid=sid))
    check(len(got) == 2 and all(p["id"] == sid for p, _ in got), "frames() gave %r" % got)
    r = c.unsubscribe(sid)
    check(r.get("id") == sid, "unsubscribe: %r" % r)
    check(sid not in c.inbox.latest, "an unsubscribed stream's frame stayed")


def test_frames_ended(c):
    c.create_scene("ending")
    sid = c.subscribe(scene="ending", width=8, height=8, fps=10)
    check(c.latest(sid, timeout=10) is not None, "no frame before the scene was deleted")
    c.delete_scene("ending")
    notes = list(c.notifications("frames.ended", timeout=10, count=1))
    check(notes and notes[0][1] == {"id": sid, "reason": "scene deleted"},
          "frames.ended: %r" % notes)
    check(c.ended(sid) == "scene deleted", "ended(sid) is %r" % c.ended(sid))
    c.latest(sid, timeout=0)  # a frame sent before the end may still be there
    started = time.monotonic()
    check(c.latest(sid, timeout=5) is None and time.monotonic() - started < 4, "latest() of an ended stream waited or gave a frame")


def test_batch(c):
    b = c.batch()
    i_info = b.info()
    i_render = b.render(12, 6)
    i_bad = b.set("camera.fov_y", 500)
    i_get = b.get("camera.fov_y")
    i_call = b.call("no.such.method")
    i_raw = b.get_cells(field="hum")
    replies = b.send()
    check(len(replies) == 6, "%d replies for 6 calls" % len(replies))
    check(replies[i_info].value()["name"] == "volfxd", "batch info %r" % replies[i_info])
    result, data = replies[i_render].value()
    check(result["width"] == 12 and data[:8] == PNG_SIGNATURE, "batch render %r" % result)
    err = replies[i_bad].error
    check(isinstance(err, volfx.VolfxError) and err.code == -32602 and err.path == "camera.fov_y",
          "batch bad set: %r" % replies[i_bad])
    check(isinstance(replies[i_get].value(), (int, float)), "batch get %r" % replies[i_get])
    check(replies[i_call].error is not None and replies[i_call].error.code == -32601,
          "batch unknown method: %r" % replies[i_call])
    cells, raw = replies[i_raw].value()
    check(len(raw) == cells["cells"], "batch get_cells: %d bytes for %r" % (len(raw), cells))
    try:
        c.batch().send()
        raise Failure("an empty batch was sent")
    except ValueError:
        pass


def c_method_names():
    with open(os.path.join(ROOT, "client", "volfx.h")) as f:
        text = f.read()
    block = text[text.index("#define VOLFX_METHOD_MAP"):]
    block = block[:block.index("\n\n")]
    return set(re.findall(r'XX\(\w+, "([^"]+)"\)', block))


def test_every_method(c):
    names = {m["name"] for m in c.discover()["methods"]}
    missing = names - set(volfx.METHODS)
    check(not missing, "rpc.discover lists methods without a Python wrapper: %s" % sorted(missing))
    missing = names - c_method_names()
    check(not missing, "rpc.discover lists methods missing from libvolfx's VOLFX_METHOD_MAP: %s"
          % sorted(missing))
    extra = set(volfx.METHODS) - names
    check(not extra, "wrappers of no server method: %s" % sorted(extra))

    called = set()

    def run(name, *args, **kw):
        called.add(name)
        return getattr(c, volfx.METHODS[name])(*args, **kw)

    run("server.info")
    run("rpc.discover")
    run("stats")
    run("scene.list")
    presets = run("scene.presets")["presets"]
    run("scene.create", "wrapped", preset=presets[0] if presets else None)
    run("scene.get", "camera", scene="wrapped")
    run("scene.set", "camera.fov_y", 41, scene="wrapped")
    c.patch({"camera": {"fov_y": 43}}, scene="wrapped")
    check(c.get("camera.fov_y", scene="wrapped") == 43, "patch on a named scene")
    run("sim.step", 2, scene="wrapped")
    run("sim.play", 30, scene="wrapped")
    run("sim.pause", scene="wrapped")
    os.makedirs(os.path.join(c.data_dir, "snaps"), exist_ok=True)
    run("scene.save", "snaps/w.snap", scene="wrapped")
    run("scene.load", "snaps/w.snap", scene="wrapped")
    _, data = run("render", 8, 8, scene="wrapped")
    check(data[:8] == PNG_SIGNATURE, "render through METHODS")
    sid = run("frames.subscribe", scene="wrapped", width=8, height=8, fps=5)
    run("frames.update", sid, camera={"fov_y": 30}, tag="moved")
    run("frames.unsubscribe", sid)
    frame = c.get("sim.frame", scene="wrapped")
    job = run("render.sequence", frame, frame + 1, "seq", width=8, height=8, scene="wrapped")
    done = [p for _, p, _ in c.notifications("job.progress", timeout=60)
            if p.get("state") != "running"]
    check(done and done[0]["state"] == "done", "sequence job: %r" % done)
    run("job.list")
    try:
        run("job.cancel", job["id"])
    except volfx.VolfxError as e:
        check(e.code == -32004, "job.cancel of an ended job: %r" % e)
    bake = run("sim.bake", "bake", c.get("sim.frame", scene="wrapped") + 1, scene="wrapped")
    check(bake["total"] >= 1, "sim.bake %r" % bake)
    list(c.notifications("job.progress", timeout=60, count=bake["total"]))
    pos = struct.pack("<6f", 0, 0.5, 0, 0.1, 0.5, 0)
    try:
        run("fluid.set_particles", pos, scene="wrapped")
        r, raw = run("fluid.get_particles", scene="wrapped")
        check(len(raw) == 12 * r["count"], "fluid.get_particles: %r" % r)
    except volfx.VolfxError as e:  # a scene without a fluid says so
        check(e.code in (-32602, -32004), "fluid wrappers: %r" % e)
        called.add("fluid.get_particles")
    cells, raw = run("cloud.get_cells", field="hum", scene="wrapped")
    run("cloud.set_cells", "hum", raw, scene="wrapped")
    run("scene.delete", "wrapped")
    run("auth", c.token)
    skipped = {"server.shutdown"}  # called last, by main
    left = set(volfx.METHODS) - called - skipped
    check(not left, "wrappers not called by the test: %s" % sorted(left))


async def async_checks(srv):
    c = await volfx.AsyncClient.connect(srv.host, srv.port, token=srv.token, timeout=60)
    async with c:
        info, fov, (result, data), stats = await asyncio.gather(
            c.info(), c.get("camera.fov_y"), c.render(10, 10), c.stats())
        check(info["name"] == "volfxd" and isinstance(fov, (int, float)), "async gather")
        check(result["width"] == 10 and data[:8] == PNG_SIGNATURE, "async render")
        sid = await c.subscribe(width=16, height=16, fps=30, repeat=True)
        f = await c.latest(sid, timeout=20)
        check(f is not None and f.id == sid and f.data[:8] == PNG_SIGNATURE,
              "async latest %r" % (f,))
        n = 0
        async for params, data in c.frames(count=3, timeout=20, sid=sid):
            check(params["id"] == sid, "async frame of %r" % params.get("id"))
            n += 1
        check(n == 3, "async frames gave %d" % n)
        await asyncio.sleep(0.5)
        check(len([k for k in c.inbox.latest if k == sid]) <= 1, "async holds more than one")
        try:
            await c.set("camera.fov_y", 500)
            raise Failure("async bad set did not raise")
        except volfx.VolfxError as e:
            check(e.code == -32602 and e.path == "camera.fov_y", "async error %r" % e)
        b = c.batch()
        b.info()
        b.call("no.such.method")
        replies = await b.send()
        check(replies[0].value()["name"] == "volfxd" and replies[1].error.code == -32601,
              "async batch %r" % replies)
        r = await c.unsubscribe(sid)
        check(r["id"] == sid, "async unsubscribe %r" % r)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bin", required=True, help="directory holding volfxd")
    a = ap.parse_args()

    def watchdog():
        print("FAIL: test_client_python timed out after %d s" % TOTAL_TIMEOUT, flush=True)
        os._exit(1)

    timer = threading.Timer(TOTAL_TIMEOUT, watchdog)
    timer.daemon = True
    timer.start()
    srv = testing.Server(os.path.join(os.path.abspath(a.bin), "volfxd"))
    srv.start()
    try:
        with srv.client() as c:
            c.data_dir = srv.data_dir
            c.token = srv.token
            test_latest_wins(c)
            test_frames_ended(c)
            test_batch(c)
            test_every_method(c)
        asyncio.run(async_checks(srv))
        with srv.client() as c:
            check(c.shutdown() == {"shutting_down": True}, "shutdown")
        print("ok: test_client_python")
        return 0
    except (Failure, volfx.VolfxError, volfx.ConnectionLost) as e:
        print("FAIL: %s" % e)
        print("--- volfxd log (tail) ---\n%s" % srv.log_text()[-4000:])
        return 1
    finally:
        srv.stop(check=False)
        timer.cancel()


if __name__ == "__main__":
    sys.exit(main())
