#!/usr/bin/env python3
"""
Files a scene names (OBJ meshes, raw volume grids) are read off the loop thread, against a
real volfxd: while one client's scene.set reads a 59 MB mesh, another client is answered;
requests pipelined behind it on the same connection (and the rest of its batch) wait and see
the change; a scene.load is waited for the same way; a file that fails to parse deep inside
is refused with its path and leaves the document as it was; several new files in one change;
a client that hangs up while its file is read.

    python3 tests/integration/test_files.py --bin build/bin
"""

import os
import struct
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_PARAMS, expect_error  # noqa: E402

suite = mock.Suite("test_files", timeout_s=400)
suite.server_args = []
T = suite.test

# About 59 MB of vertices (what the mesh parser spends its time on) and a few faces: some
# 0.3 s to read on an idle core, far longer than a small request takes.
BIG_VERTS = (b"v 0.123456 0.234567 0.345678\nv 1.123456 0.234567 0.345678\n"
             b"v 0.123456 1.234567 0.345678\n") * 680000
BIG_FACES = b"f 1 2 3\nf 4 5 6\n" * 1000
TRI = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def write(s, name, data):
    path = os.path.join(s.srv.data_dir, name)
    with open(path, "wb") as f:
        f.write(data)
    return path


def big_mesh(s, name):
    """A fresh big OBJ (new mtime, so never cached), its faces 1-2 triangles of the unit square's
    corner."""
    path = write(s, name, BIG_VERTS + BIG_FACES)
    t = time.time() + len(name)
    os.utime(path, (t, t))
    return path


def mesh(file, **kw):
    d = {"shape": "mesh", "file": file}
    d.update(kw)
    return d


@T
def others_served_while_a_file_is_read(s):
    big_mesh(s, "big.obj")
    a = s.srv.connect()
    b = s.srv.connect()
    a.ok("scene.create", {"name": "f"})
    req = a.request("scene.set", {"scene": "f", "patch": {"objects": [mesh("big.obj")]}})
    a.send(req)
    mock.served_meanwhile(s, b, a, "another client is answered while the mesh is read")
    resp, _ = a.recv_response(timeout=120)
    s.eq(resp.get("id"), req["id"], "the scene.set is answered")
    s.check("result" in resp, "the big mesh is accepted", mock.short(resp))
    obj = a.ok("scene.get", {"scene": "f", "path": "objects.0"})[0]
    s.eq(obj.get("file"), "big.obj", "the document names the mesh")
    # Cached now: a second change keeping it is answered without reading it again.
    a.ok("scene.set", {"scene": "f", "path": "objects.0.color", "value": [1, 0, 0]})


@T
def pipelined_requests_wait(s):
    big_mesh(s, "pipe.obj")
    c = s.srv.connect()
    c.ok("scene.create", {"name": "p"})
    v0 = [e for e in c.ok("scene.list")[0]["scenes"] if e["name"] == "p"][0]["version"]
    reqs = [c.request("scene.set", {"scene": "p", "patch": {"objects": [mesh("pipe.obj")]}}),
            c.request("scene.get", {"scene": "p", "path": "objects"}),
            c.request("scene.list")]
    c.send_raw(b"".join(mock.dumps(r).encode() + b"\n" for r in reqs))
    got = [c.recv_response(timeout=120)[0] for _ in reqs]
    s.eq([g.get("id") for g in got], [r["id"] for r in reqs], "answered in order")
    s.check("result" in got[0], "the mesh is accepted", mock.short(got[0]))
    objs = got[1].get("result")
    s.check(isinstance(objs, list) and len(objs) == 1 and objs[0].get("file") == "pipe.obj",
            "the scene.get sent behind the scene.set sees the mesh", mock.short(got[1]))
    v = [e for e in got[2]["result"]["scenes"] if e["name"] == "p"][0]["version"]
    s.eq(v, v0 + 1, "scene.list behind it sees the new version")

    # The rest of a batch waits too.
    big_mesh(s, "batch.obj")
    resp = mock.batch(s, c, [
        c.request("scene.get", {"scene": "p", "path": "objects"}),
        c.request("scene.set", {"scene": "p", "patch": {"objects": [mesh("batch.obj"),
                                                                  mesh("pipe.obj")]}}),
        c.request("scene.get", {"scene": "p", "path": "objects"})])
    if resp:
        s.eq(len(resp[0].get("result") or []), 1, "the get before the set sees one object")
        after = resp[2].get("result") or []
        s.eq([o.get("file") for o in after], ["batch.obj", "pipe.obj"],
             "the get after the set, in the same batch, sees both meshes")


@T
def snapshot_load_waits(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "l"})
    big_mesh(s, "snap.obj")
    c.ok("scene.set", {"scene": "l", "patch": {"objects": [mesh("snap.obj")]}}, timeout=120)
    c.ok("scene.save", {"scene": "l", "file": "l.snap"})
    # Drop the mesh (the cache forgets it) and touch it, so the load reads it again.
    c.ok("scene.set", {"scene": "l", "patch": {"objects": []}})
    big_mesh(s, "snap.obj")
    reqs = [c.request("scene.load", {"scene": "l", "file": "l.snap"}),
            c.request("scene.get", {"scene": "l", "path": "objects"})]
    c.send_raw(b"".join(mock.dumps(r).encode() + b"\n" for r in reqs))
    got = [c.recv_response(timeout=120)[0] for _ in reqs]
    s.check("result" in got[0], "the snapshot loads", mock.short(got[0]))
    objs = got[1].get("result") or []
    s.eq([o.get("file") for o in objs], ["snap.obj"], "the get behind scene.load sees its mesh")


@T
def bad_files_refused(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "b"})
    c.ok("scene.set", {"scene": "b", "patch": {"objects": [{"shape": "box"}]}})
    before = c.ok("scene.get", {"scene": "b"})[0]
    # A fault at the very end of a big file: found only by reading all of it.
    write(s, "tail.obj", BIG_VERTS + b"f 1 2 99999999\n")
    e = expect_error(s, c, "scene.set",
                     {"scene": "b", "patch": {"objects": [{"shape": "box"}, mesh("tail.obj")]}},
                     E_PARAMS, path="objects.1.file", what="a face past the vertices").get("error")
    if e:
        s.check("tail.obj" in e.get("message", ""), "the message names the file",
                e.get("message"))
        s.check(s.srv.data_dir not in e.get("message", ""),
                "the message does not reveal the data directory", e.get("message"))
    n = 64 * 64 * 64
    write(s, "nan.f32", struct.pack("<%df" % n, *([0.5] * (n - 1) + [float("nan")])))
    vol = {"source": "file", "file": "nan.f32", "format": "f32", "dims": [64, 64, 64]}
    e = expect_error(s, c, "scene.set", {"scene": "b", "patch": {"volumes": [vol]}}, E_PARAMS,
                     path="volumes.0.file", what="a NaN in the last voxel").get("error")
    if e:
        s.check("(63, 63, 63)" in e.get("message", ""), "the message names the voxel",
                e.get("message"))
    s.eq(c.ok("scene.get", {"scene": "b"})[0], before, "the document is unchanged")
    c.ok("scene.list")


@T
def snapshot_with_a_bad_file(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "sb"})
    write(s, "later_bad.obj", TRI)
    c.ok("scene.set", {"scene": "sb", "patch": {"objects": [mesh("later_bad.obj")]}})
    c.ok("scene.save", {"scene": "sb", "file": "sb.snap"})
    c.ok("scene.set", {"scene": "sb", "patch": {"objects": [{"shape": "box"}]}})
    before = c.ok("scene.get", {"scene": "sb"})[0]
    # The mesh the snapshot names goes bad (a big file, read off the loop thread).
    path = write(s, "later_bad.obj", BIG_VERTS + b"f 1 2 99999999\n")
    t = time.time() + 100
    os.utime(path, (t, t))
    e = expect_error(s, c, "scene.load", {"scene": "sb", "file": "sb.snap"}, E_PARAMS,
                     path="objects.0.file", what="a snapshot naming a bad mesh").get("error")
    if e:
        s.check('snapshot "sb.snap"' in e.get("message", ""),
                "scene.load's error names the snapshot, as for any bad field", e.get("message"))
    s.eq(c.ok("scene.get", {"scene": "sb"})[0], before, "the scene is as it was")


@T
def fault_outlives_other_commits(s):
    """scene.load reads its snapshot again before its retry: other clients' changes meanwhile
    (each prunes the cache) must not drop the fault its read left, or the retry would read the
    bad file again on the loop thread, holding every client for as long as the read."""
    a = s.srv.connect()
    b = s.srv.connect()
    a.ok("scene.create", {"name": "fo"})
    b.ok("scene.create", {"name": "fo_other"})
    write(s, "fo.obj", TRI)
    a.ok("scene.set", {"scene": "fo", "patch": {"objects": [mesh("fo.obj")]}})
    a.ok("scene.save", {"scene": "fo", "file": "fo.snap"})
    a.ok("scene.set", {"scene": "fo", "patch": {"objects": []}})
    path = write(s, "fo.obj", BIG_VERTS + b"f 1 2 99999999\n")
    t = time.time() + 200
    os.utime(path, (t, t))
    req = a.request("scene.load", {"scene": "fo", "file": "fo.snap"})
    t0 = time.monotonic()
    a.send(req)
    worst, n = 0.0, 0
    while not mock.select.select([a.sock], [], [], 0)[0]:
        t1 = time.monotonic()
        b.ok("scene.set", {"scene": "fo_other", "path": "camera.fov_y", "value": 40 + n % 10})
        worst = max(worst, time.monotonic() - t1)
        n += 1
    took = time.monotonic() - t0
    resp, _ = a.recv_response(timeout=120)
    s.eq((resp.get("error") or {}).get("data", {}).get("path"), "objects.0.file",
         "the load is refused for its bad mesh")
    s.check(worst < took / 4, "other clients' changes are answered while the load waits",
            "longest %.3f s of %.3f s, %d changes" % (worst, took, n))


@T
def several_new_files(s):
    c = s.srv.connect()
    c.ok("scene.create", {"name": "m"})
    big_mesh(s, "one.obj")
    write(s, "tri.obj", TRI)
    write(s, "half.u8", bytes([128] * 27))
    patch = {"objects": [mesh("one.obj"), mesh("tri.obj", position=[2, 0, 0])],
             "volumes": [{"source": "file", "file": "half.u8", "format": "u8",
                          "dims": [3, 3, 3]}]}
    c.ok("scene.set", {"scene": "m", "patch": patch}, timeout=120)
    doc = c.ok("scene.get", {"scene": "m"})[0]
    s.eq([o.get("file") for o in doc["objects"]], ["one.obj", "tri.obj"], "both meshes")
    s.eq(doc["volumes"][0].get("file"), "half.u8", "and the volume file")
    r, png = c.ok("render", {"scene": "m", "width": 32, "height": 32, "format": "png"},
                  timeout=120)
    s.check(png is not None and png.startswith(mock.PNG_SIGNATURE), "the scene renders")


@T
def hang_up_while_reading(s):
    big_mesh(s, "gone.obj")
    a = s.srv.connect()
    a.ok("scene.create", {"name": "g"})
    a.send(a.request("scene.set", {"scene": "g", "patch": {"objects": [mesh("gone.obj")]}}))
    a.send(a.request("scene.list"))
    time.sleep(0.02)
    a.close()
    b = s.srv.connect()
    b.ok("scene.list")
    # The change was received before the client left, so it is made.
    deadline = time.time() + 60
    objs = []
    while time.time() < deadline:
        objs = b.ok("scene.get", {"scene": "g", "path": "objects"})[0]
        if objs:
            break
        time.sleep(0.05)
    s.eq([o.get("file") for o in objs], ["gone.obj"], "the change of a client that left is made")
    s.check(s.srv.alive(), "the server is still up")


if __name__ == "__main__":
    suite.main()
