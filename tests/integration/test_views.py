#!/usr/bin/env python3
"""
A view per subscription, checked over a real socket: frames.update changes a subscription's
camera and size live (no frames.ended, no resubscribe, the stream goes on) and a bad update
leaves it as it was; identical subscriptions share one render per frame while different
cameras render apart; a paused, unchanged scene sends nothing, and a tagged scene.set makes
one frame arrive with the tag, the new version and server timestamps in order, at once when
the subscription was idle.

    python3 tests/integration/test_views.py --bin build/bin
"""

import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, E_NOT_FOUND, short  # noqa: E402

suite = mock.Suite("test_views", timeout_s=300)
suite.server_args = []
T = suite.test

W, H = 48, 32


def frames_of(c, seconds, want=None):
    """The 'frames' notification params (with the attachment's length) that arrive on 'c'
    within 'seconds', stopping early once 'want' have come; other notifications are kept
    aside."""
    got = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and (want is None or len(got) < want):
        if not c.notifications and c.quiet(min(0.05, max(0.0, deadline - time.monotonic()))):
            continue
        msg, att = c.recv_notification(timeout=30)
        if msg.get("method") == "frames.ended":
            got.append({"ended": msg.get("params")})
        elif msg.get("method") == "frames":
            p = dict(msg["params"])
            p["received_ms"] = time.time() * 1000.0
            p["nbytes"] = len(att or b"")
            got.append(p)
    return got


def new_scene(c, name):
    c.ok("scene.create", {"name": name, "preset": "demo"})


@T
def update_changes_view_live(s):
    c = s.srv.connect()
    new_scene(c, "upd")
    sid = c.ok("frames.subscribe", {"scene": "upd", "width": W, "height": H, "fps": 30})[0]["id"]
    # A playing scene, so that every tick has something new to show.
    c.ok("sim.play", {"scene": "upd", "rate": 60})
    first = frames_of(c, 20, want=3)
    s.check(len(first) == 3 and all("ended" not in p for p in first), "frames flow",
            short(first))
    c.ok("frames.update", {"id": sid, "width": 64, "height": 40,
                           "camera": {"eye": [0, 3, 9], "target": [0, 0, 0]}, "tag": "look"})
    after = frames_of(c, 20, want=6)
    s.check(all("ended" not in p for p in after), "no frames.ended after frames.update",
            short(after))
    s.check(all(p.get("id") == sid for p in after), "frames keep the subscription id")
    tagged = [i for i, p in enumerate(after) if p.get("tag") == "look"]
    s.check(tagged and tagged[0] <= 2,
            "the update's tag arrives within the frames already in flight", short(after))
    if tagged:
        new = after[tagged[0]:]
        s.check(all((p["width"], p["height"]) == (64, 40) for p in new),
                "frames from the tagged one have the new size", short(new))
        s.check(all(p["tag"] == "look" for p in new), "later frames carry the same tag")
    old = after[:tagged[0]] if tagged else []
    s.check(all((p["width"], p["height"]) == (W, H) for p in old),
            "frames before the tag are the old view", short(old))
    # No gap: the stream goes on at its rate across the update.
    times = [p["received_ms"] for p in first + after]
    gaps = [b - a for a, b in zip(times, times[1:])]
    s.check(max(gaps) < 1000, "no gap in the stream around the update",
            "gaps %s ms" % [round(g) for g in gaps])
    # An fps change re-arms the timer and the stream goes on.
    c.ok("frames.update", {"id": sid, "fps": 10})
    frames_of(c, 1.0)
    slow = frames_of(c, 1.6)
    s.check(8 <= len(slow) <= 22, "fps 10 gives about 10 frames a second",
            "%d in 1.6 s" % len(slow))
    c.ok("sim.pause", {"scene": "upd"})
    c.ok("frames.unsubscribe", {"id": sid})
    c.close()


@T
def bad_updates_change_nothing(s):
    c = s.srv.connect()
    new_scene(c, "bad")
    sid = c.ok("frames.subscribe", {"scene": "bad", "width": W, "height": H, "fps": 30})[0]["id"]
    frames_of(c, 20, want=1)
    cases = [({"width": 0}, E_PARAMS, "width"),
             ({"format": "gif"}, E_PARAMS, "format"),
             ({"format": "f32"}, E_PARAMS, "format"),  # f32 needs a depth or wave_h aov
             ({"camera": {"fov_y": 500}}, E_PARAMS, "camera.fov_y"),
             ({"camera": 3}, E_PARAMS, "camera"),
             ({"layers": ["nope"]}, E_PARAMS, "layers.0"),
             ({"fps": 0}, E_PARAMS, "fps"),
             ({"scene": "main"}, E_PARAMS, "scene"),
             ({"tag": "x" * 300}, E_PARAMS, "tag")]
    for params, code, path in cases:
        params = dict(params, id=sid, width=params.get("width", 80))
        e = c.err("frames.update", params)
        s.eq((e.get("code"), (e.get("data") or {}).get("path")), (code, path),
             "frames.update %s is refused naming the param" % short(params))
    e = c.err("frames.update", {"id": sid + 1000, "width": 10})
    s.eq(e.get("code"), E_NOT_FOUND, "frames.update of an unknown id is -32004")
    # None of them changed anything: the paused scene still sends nothing, and the next frame
    # (made by a render-free update with a tag) has the old size.
    s.check(not frames_of(c, 0.5), "no frame after refused updates")
    c.ok("frames.update", {"id": sid, "tag": 7})
    got = frames_of(c, 20, want=1)
    s.check(got and (got[0]["width"], got[0]["height"], got[0].get("tag")) == (W, H, 7),
            "the subscription kept its view", short(got))
    c.close()


@T
def identical_views_share_renders(s):
    a, b = s.srv.connect(), s.srv.connect()
    new_scene(a, "share")
    view = {"scene": "share", "width": W, "height": H, "fps": 20,
            "camera": {"eye": [0, 2, 8], "target": [0, 0, 0]}}
    a.ok("frames.subscribe", view)
    # The same view with its members in another order and the other encoding.
    b.ok("frames.subscribe", {"encoding": "base64", "fps": 20, "height": H, "width": W,
                              "camera": {"target": [0, 0, 0], "eye": [0, 2, 8]},
                              "scene": "share"})
    frames_of(a, 20, want=1)
    frames_of(b, 20, want=1)
    st0 = a.ok("stats")[0]
    n = 4
    for i in range(n):
        a.ok("scene.set", {"scene": "share", "path": "camera.fov_y", "value": 40 + i,
                           "tag": i})
        fa = frames_of(a, 20, want=1)
        fb = frames_of(b, 20, want=1)
        s.check(fa and fb and fa[0].get("tag") == i and fb[0].get("tag") == i,
                "both viewers get change %d" % i, short((fa, fb)))
    st1 = a.ok("stats")[0]
    renders = st1["frames_rendered"] - st0["frames_rendered"]
    shared = st1["frames_shared"] - st0["frames_shared"]
    s.eq((renders, shared), (n, n), "one render per change for two identical views")
    # A different camera is a different view: rendered apart.
    c = s.srv.connect()
    c.ok("frames.subscribe", dict(view, camera={"eye": [5, 2, 8], "target": [0, 0, 0]}))
    frames_of(c, 20, want=1)
    st2 = a.ok("stats")[0]
    a.ok("scene.set", {"scene": "share", "path": "camera.fov_y", "value": 30})
    for x in (a, b, c):
        s.check(len(frames_of(x, 20, want=1)) == 1, "each viewer gets the change")
    st3 = a.ok("stats")[0]
    s.eq((st3["frames_rendered"] - st2["frames_rendered"],
          st3["frames_shared"] - st2["frames_shared"]), (2, 1),
         "a different camera renders apart, the identical views share")
    for x in (a, b, c):
        x.close()


@T
def unchanged_scene_sends_nothing(s):
    c = s.srv.connect()
    new_scene(c, "still")
    sid = c.ok("frames.subscribe", {"scene": "still", "width": W, "height": H, "fps": 60})[0]["id"]
    first = frames_of(c, 20, want=1)
    s.check(len(first) == 1, "a first frame arrives", short(first))
    v0 = first[0]["version"] if first else 0
    s.check(not frames_of(c, 0.6), "a paused, unchanged scene sends no more frames")
    t_set = time.time() * 1000.0
    r = c.ok("scene.set", {"scene": "still", "patch": {"camera": {"fov_y": 35}},
                           "tag": {"move": 1}})[0]
    got = frames_of(c, 1.0)
    s.eq(len(got), 1, "exactly the changed frame arrives")
    if got:
        p = got[0]
        s.eq(p.get("tag"), {"move": 1}, "the frame echoes the scene.set tag")
        s.eq(p.get("version"), r["version"], "the frame shows the version scene.set answered")
        s.check(p["version"] > v0, "the version increased", "%s -> %s" % (v0, p["version"]))
        # The server's clock and this one are the same host's CLOCK_REALTIME; allow a little
        # for rounding to 0.1 ms.
        s.check(t_set - 1 <= p["render_start"] <= p["encode_end"] <= p["received_ms"] + 1,
                "render_start <= encode_end <= receive",
                "%.1f %.1f %.1f %.1f" % (t_set, p["render_start"], p["encode_end"],
                                         p["received_ms"]))
    # Scene-wide tags from the sim calls arrive too: a tagged pause of a paused scene is a frame.
    c.ok("sim.pause", {"scene": "still", "tag": "paused"})
    got = frames_of(c, 20, want=1)
    s.check(got and got[0].get("tag") == "paused", "a tagged sim.pause is echoed", short(got))
    version = got[0]["version"] if got else None
    s.check(not frames_of(c, 0.4), "and then nothing again")
    # The render method carries the same sync members.
    r, _ = c.ok("render", {"scene": "still", "width": 8, "height": 8})
    now = time.time() * 1000.0
    s.check(r.get("version") == version and
            r["render_start"] <= r["encode_end"] <= now + 1, "render answers carry version and "
            "timestamps", short(r))
    c.ok("frames.unsubscribe", {"id": sid})
    c.close()


@T
def change_ticks_idle_subscription_at_once(s):
    c = s.srv.connect()
    new_scene(c, "slow")
    # At 1 fps a change would wait up to a second for the next tick; an idle subscription ticks
    # as the change is answered instead.
    c.ok("frames.subscribe", {"scene": "slow", "width": W, "height": H, "fps": 1})
    s.check(len(frames_of(c, 20, want=1)) == 1, "a first frame arrives")
    time.sleep(1.2)
    t0 = time.monotonic()
    c.ok("scene.set", {"scene": "slow", "path": "camera.fov_y", "value": 33, "tag": "now"})
    got = frames_of(c, 5, want=1)
    el = time.monotonic() - t0
    s.check(got and got[0].get("tag") == "now" and el < 0.6,
            "the change arrives at once, not at the next tick", "%.3f s %s" % (el, short(got)))
    # The next change within the interval waits for the tick: frames stay an interval apart.
    t0 = time.monotonic()
    c.ok("scene.set", {"scene": "slow", "path": "camera.fov_y", "value": 34, "tag": "later"})
    got = frames_of(c, 5, want=1)
    el = time.monotonic() - t0
    s.check(got and got[0].get("tag") == "later" and el > 0.5,
            "a change within the interval waits for the tick", "%.3f s %s" % (el, short(got)))
    c.close()


if __name__ == "__main__":
    sys.exit(suite.main())
