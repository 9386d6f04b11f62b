#!/usr/bin/env python3
"""
The end of a server as its subscribers see it: SIGTERM and server.shutdown end every
subscription of every connection with a last 'frames.ended' notification, reason "shutdown",
written before the connection closes, and no frame of that subscription follows it. Each test
runs its own server, since each stops it.

    python3 tests/integration/test_shutdown.py --bin build/bin
"""

import os
import signal
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_shutdown", timeout_s=300)
T = suite.test

SMALL = {"width": 16, "height": 16, "fps": 20}


def subscribe(s, c, scene="main"):
    """Subscribes 'c' to small frames of 'scene' and waits for its first frame; returns the id."""
    sub, _ = c.ok("frames.subscribe", dict(SMALL, scene=scene))
    for _ in range(100):
        msg, _ = c.recv(timeout=30)
        if msg.get("method") == "frames" and msg["params"]["id"] == sub["id"]:
            return sub["id"]
    s.fail("a frame of subscription %d arrives" % sub["id"])
    return sub["id"]


def read_to_eof(s, c, what):
    """Every message 'c' receives until the server closes it, in order; a connection left open
    for 20 s is a failure."""
    msgs = []
    try:
        while True:
            msg, _ = c.recv(timeout=20)
            msgs.append(msg)
    except mock.Closed:
        return msgs
    except OSError as e:  # socket.timeout included
        s.fail("%s: the connection closes after the last notification" % what, str(e))
        return msgs


def check_ended(s, msgs, ids, what):
    """Each subscription in 'ids' ended with frames.ended {id, reason: "shutdown"}, and no frame
    of it came after that."""
    for sid in ids:
        ends = [i for i, m in enumerate(msgs)
                if m.get("method") == "frames.ended" and m["params"].get("id") == sid]
        if not s.eq(len(ends), 1, "%s: one frames.ended for subscription %d" % (what, sid)):
            continue
        s.eq(msgs[ends[0]]["params"], {"id": sid, "reason": "shutdown"},
             "%s: the frames.ended of subscription %d gives its reason" % (what, sid))
        later = [m for m in msgs[ends[0] + 1:]
                 if m.get("method") == "frames" and m["params"].get("id") == sid]
        s.eq(len(later), 0, "%s: no frame of subscription %d after its end" % (what, sid))


@T
def sigterm_ends_subscriptions(s):
    with mock.Server(s.bin) as srv:
        c = srv.connect(timeout=30)
        c.ok("scene.create", {"name": "second"})
        ids = [subscribe(s, c), subscribe(s, c, "second")]
        other = srv.connect(timeout=30)
        other_id = subscribe(s, other)
        srv.proc.send_signal(signal.SIGTERM)
        check_ended(s, read_to_eof(s, c, "SIGTERM"), ids, "SIGTERM")
        check_ended(s, read_to_eof(s, other, "SIGTERM, another connection"), [other_id],
                    "SIGTERM, another connection")
        s.eq(srv.wait_exit(30), 0, "volfxd exits 0 after SIGTERM")


@T
def shutdown_method_ends_subscriptions(s):
    with mock.Server(s.bin) as srv:
        c = srv.connect(timeout=30)
        sid = subscribe(s, c)
        other = srv.connect(timeout=30)
        other_id = subscribe(s, other)
        # Frames may come before the answer; the answer comes before the end.
        c.send(c.request("server.shutdown", {}, id=99))
        msgs = read_to_eof(s, c, "server.shutdown")
        answers = [i for i, m in enumerate(msgs) if m.get("id") == 99]
        if s.eq(len(answers), 1, "server.shutdown answered once"):
            s.eq(msgs[answers[0]].get("result"), {"shutting_down": True}, "server.shutdown")
            ends = [i for i, m in enumerate(msgs) if m.get("method") == "frames.ended"]
            s.check(ends and ends[0] > answers[0], "the answer comes before frames.ended",
                    mock.short(msgs))
        check_ended(s, msgs, [sid], "server.shutdown")
        check_ended(s, read_to_eof(s, other, "server.shutdown, another connection"),
                    [other_id], "server.shutdown, another connection")
        s.eq(srv.wait_exit(30), 0, "volfxd exits 0 after server.shutdown")


@T
def unsubscribed_and_plain_connections_end_quietly(s):
    with mock.Server(s.bin) as srv:
        c = srv.connect(timeout=30)
        sid = subscribe(s, c)
        r, _ = c.ok("frames.unsubscribe", {"id": sid})
        s.eq(r["id"], sid, "frames.unsubscribe")
        plain = srv.connect(timeout=30)
        plain.ok("scene.list")
        srv.proc.send_signal(signal.SIGTERM)
        msgs = read_to_eof(s, c, "SIGTERM after unsubscribing")
        s.eq([m for m in msgs if m.get("method") == "frames.ended"], [],
             "no frames.ended for a subscription already ended")
        s.eq(read_to_eof(s, plain, "SIGTERM, no subscription"), [],
             "a connection without subscriptions is closed with nothing more")
        s.eq(srv.wait_exit(30), 0, "volfxd exits 0 after SIGTERM")


if __name__ == "__main__":
    sys.exit(suite.main())
