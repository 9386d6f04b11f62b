#!/usr/bin/env python3
"""
Scripting a scene: array items addressed and merged by id, scene.set's change lists and JSON
Patch (one version, all or nothing), "did you mean" suggestions, and the CLI's set, scene and
watch commands and the README's examples against a real volfxd, on a scene that has played.

    python3 tests/integration/test_scripting.py --bin build/bin
"""

import os
import shutil
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import E_NOT_FOUND, E_PARAMS, expect_error, short  # noqa: E402

suite = mock.Suite("test_scripting", timeout_s=560)
suite.server_args = []
T = suite.test
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def fresh(c, name, preset="demo"):
    """A new scene from 'preset', replacing one of that name."""
    c.call("scene.delete", {"name": name})
    c.ok("scene.create", {"name": name, "preset": preset})


def version(c, name):
    return [x for x in c.ok("scene.list", {})[0]["scenes"] if x["name"] == name][0]["version"]


def get(c, name, path=None):
    params = {"scene": name}
    if path is not None:
        params["path"] = path
    return c.ok("scene.get", params)[0]


def refused_unchanged(s, c, name, params, code, path, what, says=None):
    """Checks that scene.set 'params' is refused with 'code' at 'path' and changes nothing."""
    before, v = get(c, name), version(c, name)
    resp = expect_error(s, c, "scene.set", dict(params, scene=name), code, path, what)
    msg = (resp.get("error") or {}).get("message", "")
    if says is not None:
        s.check(says in msg, "%s: the message says %r" % (what, says), msg)
    s.eq(version(c, name), v, "%s: the version is unchanged" % what)
    s.check(get(c, name) == before, "%s: the document is unchanged" % what)
    return msg


@T
def paths_by_id(s):
    c = s.srv.connect()
    fresh(c, "ids")
    s.eq(get(c, "ids", "objects.orb.scale"), get(c, "ids", "objects.1.scale"),
         "objects.orb is objects.1")
    s.eq(get(c, "ids", "waves.spark.id"), "spark", "waves.spark.id")
    c.ok("scene.set", {"scene": "ids", "path": "objects.orb.scale", "value": [2, 2, 2]})
    s.eq(get(c, "ids", "objects.1.scale"), [2, 2, 2], "scene.set objects.orb.scale")
    resp = expect_error(s, c, "scene.get", {"scene": "ids", "path": "objects.orbb.scale"},
                        E_NOT_FOUND, "path", "scene.get of an unknown id")
    s.check('did you mean "orb"' in resp["error"]["message"], "unknown id: did you mean orb",
            resp["error"]["message"])
    refused_unchanged(s, c, "ids", {"path": "objects.nosuch.scale", "value": [1, 1, 1]},
                      E_NOT_FOUND, "objects.nosuch.scale", "scene.set of an unknown id",
                      'no item with id "nosuch"')
    refused_unchanged(s, c, "ids", {"path": "objects.40.scale", "value": [1, 1, 1]}, E_NOT_FOUND,
                      "objects.40.scale", "scene.set past the end", "objects has")
    n = len(get(c, "ids", "objects"))
    c.ok("scene.set", {"scene": "ids", "path": "objects.pebble", "value": None})
    s.eq(len(get(c, "ids", "objects")), n - 1, "null removes an item by id")
    refused_unchanged(s, c, "ids", {"path": "objects.pebble", "value": None}, E_NOT_FOUND,
                      "objects.pebble", "removing an item that is gone")


@T
def merge_by_id(s):
    c = s.srv.connect()
    fresh(c, "merge")
    spark = get(c, "merge", "waves.spark")
    v = version(c, "merge")
    c.ok("scene.set", {"scene": "merge", "patch": {"waves": [{"id": "spark",
                                                               "color": [1, 0, 0]}]}})
    after = get(c, "merge", "waves.spark")
    s.eq(version(c, "merge"), v + 1, "an item patch is one version")
    s.eq(after["color"], [1, 0, 0], "the item patch set the colour")
    for key in ("center", "radius", "direction", "animate"):
        s.eq(after.get(key), spark.get(key), "the item patch kept %s" % key)
    # A new id is appended, and the other items stay.
    n = len(get(c, "merge", "objects"))
    c.ok("scene.set", {"scene": "merge", "patch": {"objects": [
        {"id": "orb", "scale": [0.5, 0.5, 0.5]}, {"id": "new", "shape": "box"}]}})
    objs = get(c, "merge", "objects")
    s.eq(len(objs), n + 1, "a new id is appended")
    s.eq(objs[-1]["id"], "new", "the new item is last")
    s.eq(get(c, "merge", "objects.orb.shape"), "sphere", "the orb keeps its shape")
    # A new item missing a required member is refused.
    refused_unchanged(s, c, "merge", {"patch": {"objects": [{"id": "nosuch", "scale": [1, 1, 1]}]}},
                      E_PARAMS, "objects.%d.shape" % (n + 1), "a new id without a shape")
    # Repeated ids, or an item without one: the array is replaced whole (RFC 7386).
    refused_unchanged(s, c, "merge", {"patch": {"waves": [{"id": "a"}, {"id": "a"}]}}, E_PARAMS,
                      "waves.1.id", "repeated ids in an item patch")
    c.ok("scene.set", {"scene": "merge", "patch": {"objects": [{"shape": "box"}]}})
    s.eq(len(get(c, "merge", "objects")), 1, "items without ids replace the array")


@T
def change_lists(s):
    c = s.srv.connect()
    fresh(c, "chg")
    v = version(c, "chg")
    r, _ = c.ok("scene.set", {"scene": "chg", "changes": [
        {"path": "waves.0.color", "value": [0, 1, 0]},
        {"path": "camera.fov_y", "value": 30},
        {"path": "camera", "patch": {"near": 0.1}},
        {"path": "objects.orb.position.1", "value": 1.5}]})
    s.eq(r.get("version"), v + 1, "four changes are one version")
    s.eq(get(c, "chg", "camera.fov_y"), 30, "changes: fov_y")
    s.eq(get(c, "chg", "camera.near"), 0.1, "changes: a patch at a path merges")
    s.eq(get(c, "chg", "waves.0.color"), [0, 1, 0], "changes: waves.0.color")
    s.eq(get(c, "chg", "objects.orb.position")[1], 1.5, "changes: by id")
    refused_unchanged(s, c, "chg", {"changes": [{"path": "camera.fov_y", "value": 50},
                                                {"path": "camera.fovy", "value": 3}]},
                      E_PARAMS, "camera.fovy", "a bad second change", 'did you mean "fov_y"')
    refused_unchanged(s, c, "chg", {"changes": [{"path": "camera.fov_y", "value": 50},
                                                {"path": "lights.0", "value": 3}]},
                      E_NOT_FOUND, "lights.0", "a change at a missing path", "changes.1")
    refused_unchanged(s, c, "chg", {"changes": [{"path": "camera.fov_y"}]}, E_PARAMS, None,
                      "a change without a value")
    refused_unchanged(s, c, "chg", {"changes": [{"path": "camera", "value": 1, "patch": {}}]},
                      E_PARAMS, None, "a change with both value and patch")
    refused_unchanged(s, c, "chg", {"changes": {"path": "camera.fov_y"}}, E_PARAMS, "changes",
                      "changes that are not a list")
    refused_unchanged(s, c, "chg", {"changes": [], "patch": {}}, E_PARAMS, "changes",
                      "two forms at once")


@T
def json_patch(s):
    c = s.srv.connect()
    fresh(c, "jp")
    v = version(c, "jp")
    n = len(get(c, "jp", "objects"))
    r, _ = c.ok("scene.set", {"scene": "jp", "ops": [
        {"op": "test", "path": "/camera/fov_y", "value": 40},
        {"op": "replace", "path": "/camera/fov_y", "value": 35},
        {"op": "add", "path": "/objects/-", "value": {"id": "added", "shape": "box"}},
        {"op": "copy", "from": "/objects/orb/color", "path": "/objects/added/color"},
        {"op": "move", "from": "/objects/added", "path": "/objects/0"},
        {"op": "remove", "path": "/objects/pebble"},
        {"op": "replace", "path": "/objects/crate/scale", "value": [2, 2, 2]},
        {"op": "add", "path": "/camera/near", "value": 0.2}]})
    s.eq(r.get("version"), v + 1, "eight operations are one version")
    objs = get(c, "jp", "objects")
    s.eq(objs[0]["id"], "added", "move put the item first")
    s.eq(objs[0]["color"], get(c, "jp", "objects.orb.color"), "copy copied the orb's colour")
    s.eq(len(objs), n, "one added, one removed")
    s.check(all(o["id"] != "pebble" for o in objs), "the pebble is removed")
    s.eq(get(c, "jp", "camera"), dict(get(c, "jp", "camera"), fov_y=35, near=0.2),
         "replace and add of members")
    refused_unchanged(s, c, "jp", {"ops": [
        {"op": "replace", "path": "/camera/fov_y", "value": 20},
        {"op": "test", "path": "/camera/fov_y", "value": 40}]}, E_PARAMS, "ops.1",
        "a failing test", "test failed")
    cases = [
        ([{"op": "replace", "path": "camera/fov_y", "value": 1}], E_PARAMS, "ops.0.path",
         "a pointer without '/'"),
        ([{"op": "replace", "path": "/camera/fov~2y", "value": 1}], E_PARAMS, "ops.0.path",
         "a bad ~ escape"),
        ([{"op": "replace", "path": "/camera/fovy", "value": 1}], E_NOT_FOUND, "ops.0.path",
         "replace of a missing member", 'did you mean "fov_y"'),
        ([{"op": "test", "path": "/objects/orbb/scale", "value": 1}], E_NOT_FOUND, "ops.0.path",
         "a pointer through an unknown id", 'did you mean "orb"'),
        ([{"op": "move", "from": "/camera/x", "path": "/camera/x"}], E_NOT_FOUND, "ops.0.from",
         "a move of nothing onto itself"),
        ([{"op": "remove", "path": "/objects/nosuch"}], E_NOT_FOUND, "ops.0.path",
         "remove of an unknown id"),
        ([{"op": "add", "path": "/objects/99", "value": {"shape": "box"}}], E_NOT_FOUND,
         "ops.0.path", "add past the end"),
        ([{"op": "move", "from": "/camera", "path": "/camera/eye"}], E_PARAMS, "ops.0.path",
         "a move into itself"),
        ([{"op": "copy", "path": "/camera/x"}], E_PARAMS, "ops.0.from", "copy without from"),
        ([{"op": "frobnicate", "path": "/camera"}], E_PARAMS, "ops.0", "an unknown op"),
        ([{"op": "add", "path": "/camera/fovy", "value": 3}], E_PARAMS, "camera.fovy",
         "an unknown member added"),
        ([{"op": "remove", "path": ""}], E_PARAMS, "ops.0.path", "removing the document"),
        ([7], E_PARAMS, "ops.0", "an operation that is not an object"),
    ]
    for ops, code, path, what, *says in cases:
        refused_unchanged(s, c, "jp", {"ops": ops}, code, path, what, *says)


@T
def python_client(s):
    sys.path.insert(0, os.path.join(ROOT, "client", "python"))
    import volfx
    c = s.srv.connect()
    fresh(c, "py")
    v = version(c, "py")
    with volfx.Client("127.0.0.1", s.srv.port) as py:
        py.changes([{"path": "camera.fov_y", "value": 31}, {"path": "objects.orb.color",
                                                            "value": [0, 0, 1]}], scene="py")
        py.json_patch([{"op": "replace", "path": "/camera/near", "value": 0.3}], scene="py")
    s.eq(version(c, "py"), v + 2, "the Python client: two calls, two versions")
    s.eq(get(c, "py", "camera.fov_y"), 31, "Client.changes")
    s.eq(get(c, "py", "camera.near"), 0.3, "Client.json_patch")


@T
def did_you_mean(s):
    c = s.srv.connect()
    fresh(c, "dym")
    msg = refused_unchanged(s, c, "dym", {"patch": {"camera": {"fovy": 30}}}, E_PARAMS,
                            "camera.fovy", "an unknown member in a patch")
    s.check('did you mean "fov_y"' in msg, "fovy: did you mean fov_y", msg)
    msg = refused_unchanged(s, c, "dym", {"patch": {"camera": {"zoom": 2}}}, E_PARAMS,
                            "camera.zoom", "an unknown member with nothing near it")
    s.check("did you mean" not in msg, "zoom has no suggestion", msg)
    resp = expect_error(s, c, "scene.get", {"scene": "dym", "path": "camera.fovy"}, E_NOT_FOUND,
                        "path", "scene.get camera.fovy")
    s.check('did you mean "fov_y"' in resp["error"]["message"], "scene.get: did you mean fov_y",
            resp["error"]["message"])


def cli(s, *args, cwd=None, ok=True):
    """Runs bin/volfx against the shared server; returns (rc, stdout, stderr)."""
    p = subprocess.run([os.path.join(s.bin, "volfx"), "--port", str(s.srv.port)] + list(args),
                       cwd=cwd, capture_output=True, text=True, timeout=300)
    if ok:
        s.check(p.returncode == 0, "volfx %s succeeds" % " ".join(args), p.stderr)
    return p.returncode, p.stdout, p.stderr


@T
def cli_set_and_messages(s):
    c = s.srv.connect()
    fresh(c, "main")
    v = version(c, "main")
    cli(s, "set", "waves.0.color=[1,0,0]", "camera.fov_y=30", "objects.orb.scale=[2,2,2]")
    s.eq(version(c, "main"), v + 1, "CLI set of three paths is one version")
    s.eq(get(c, "main", "camera.fov_y"), 30, "CLI set camera.fov_y")
    rc, _, err = cli(s, "set", "camera.fov_y=50", "camera.fovy=3", ok=False)
    s.check(rc == 1 and 'did you mean "fov_y"' in err, "CLI set: did you mean", err)
    s.eq(get(c, "main", "camera.fov_y"), 30, "a refused CLI set changes nothing")
    rc, _, err = cli(s, "set", "--patch", '{"camera":{', ok=False)
    s.check(rc == 2 and "invalid JSON" in err and "needs one JSON" not in err,
            "set --patch with broken JSON says invalid JSON", err)
    rc, _, err = cli(s, "set", "camera.eye=[1,2", ok=False)
    s.check(rc == 2 and "invalid JSON" in err, "set PATH=broken JSON says invalid JSON", err)
    rc, _, err = cli(s, "get", "camera.fovy", ok=False)
    s.check(rc == 1 and "(path path)" not in err and 'did you mean "fov_y"' in err,
            "CLI get of a bad path: no '(path path)'", err)
    cli(s, "set", "--ops", '[{"op":"replace","path":"/camera/fov_y","value":33}]')
    s.eq(get(c, "main", "camera.fov_y"), 33, "CLI set --ops")


@T
def cli_scene_commands(s):
    c = s.srv.connect()
    _, out, _ = cli(s, "scene", "presets")
    s.check('"demo"' in out, "scene presets lists demo", out)
    cli(s, "scene", "create", "cs", "--preset", "paper-000")
    _, out, _ = cli(s, "scene", "list")
    s.check('"cs"' in out and '"paper-000"' in out, "scene list shows cs and its preset", out)
    c.ok("sim.step", {"scene": "cs", "steps": 5})
    cli(s, "--scene", "cs", "set", "camera.fov_y=20")
    os.makedirs(os.path.join(s.srv.data_dir, "snaps"), exist_ok=True)
    cli(s, "--scene", "cs", "scene", "save", "snaps/cs.snap")
    cli(s, "--scene", "cs", "set", "camera.fov_y=60")
    cli(s, "--scene", "cs", "scene", "load", "snaps/cs.snap")
    s.eq(get(c, "cs", "camera.fov_y"), 20, "scene load restores the saved scene")
    cli(s, "scene", "reset", "--scene", "cs")
    s.eq(get(c, "cs", "sim.frame"), 0, "scene reset: frame 0")
    s.check(get(c, "cs", "camera.fov_y") != 20, "scene reset: the preset's camera",
            get(c, "cs", "camera"))
    _, out, _ = cli(s, "scene", "list")
    s.check('"paper-000"' in out, "scene reset keeps the preset", out)
    cli(s, "scene", "delete", "cs")
    s.check(all(x["name"] != "cs" for x in c.ok("scene.list", {})[0]["scenes"]),
            "scene delete")
    cli(s, "scene", "create", "cs2", "--preset", "demo")
    rc, _, err = cli(s, "--scene", "cs2", "scene", "reset", "--preset", "nosuch", ok=False)
    s.check(rc == 1 and "not a preset" in err, "scene reset to an unknown preset", err)
    s.check(any(x["name"] == "cs2" for x in c.ok("scene.list", {})[0]["scenes"]),
            "a refused reset leaves the scene")
    cli(s, "scene", "delete", "cs2")
    rc, _, err = cli(s, "scene", "frob", ok=False)
    s.check(rc == 2 and "scene needs one of" in err, "an unknown scene command", err)
    rc, _, err = cli(s, "scene", "create", ok=False)
    s.check(rc == 2 and "NAME" in err, "scene create without a name", err)


@T
def readme_examples(s):
    """The README's client examples, as written but for the port, on a scene that has played."""
    c = s.srv.connect()
    fresh(c, "main")
    c.ok("sim.step", {"scene": "main", "steps": 30})
    work = tempfile.mkdtemp(prefix="volfx-readme-")
    try:
        os.makedirs(os.path.join(work, "deploy", "examples"))
        shutil.copy(os.path.join(ROOT, "deploy", "examples", "orbit.volfx"),
                    os.path.join(work, "deploy", "examples"))
        readme = open(os.path.join(ROOT, "README.md")).read()
        block = readme.split("With the server from `./run.sh` running:")[1].split("```sh")[1]
        lines = [ln.split("  #")[0].strip() for ln in block.split("```")[0].splitlines()]
        # "A && B" runs A, then B.
        lines = [part.strip() for ln in lines for part in ln.split(" && ")]
        lines = [ln for ln in lines if ln.startswith("build/bin/volfx ")]
        s.check(len(lines) >= 10, "the README's examples were found", lines)
        for ln in lines:
            args = subprocess.run(["python3", "-c", "import shlex,sys; print('\\0'.join("
                                   "shlex.split(sys.argv[1])[1:]))", ln],
                                  capture_output=True, text=True).stdout.rstrip("\n").split("\0")
            args = [a.replace("--count 90", "--count 5") for a in args]
            if args and args[0] == "watch":
                args[args.index("90")] = "5"
            cli(s, *args, cwd=work)
        with open(os.path.join(work, "frame.jpg"), "rb") as f:
            s.eq(f.read(3), b"\xff\xd8\xff", "render -o frame.jpg wrote a JPEG")
        s.check(os.path.exists(os.path.join(work, "out", "orbit_3.png")),
                "orbit.volfx made out/ and wrote its frames")
        s.eq(sorted(os.listdir(os.path.join(work, "out")))[:5],
             ["f_000001.png", "f_000002.png", "f_000003.png", "f_000004.png", "f_000005.png"],
             "watch --seq wrote numbered files of the playing scene")
        s.check(os.path.exists(os.path.join(s.srv.data_dir, "shots", "a", "frame_000059.png")),
                "sequence 0 59 after reset wrote its frames",
                os.listdir(os.path.join(s.srv.data_dir)))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    suite.main()
