#!/usr/bin/env python3
"""
rpc.discover against docs/protocol.md: the OpenRPC document names exactly the methods of the
protocol's "Methods" section, every parameter of its reference, with JSON Schemas, defaults
and ranges, and publishes the scene document's schema as components.schemas.Scene.

    python3 tests/integration/test_discover.py --bin build/bin
"""

import os
import re
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402
from mock import short  # noqa: E402

suite = mock.Suite("test_discover", timeout_s=240)
suite.server_args = []
T = suite.test

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PROTOCOL_MD = os.path.join(ROOT, "docs", "protocol.md")
DOC = {}


def parse_protocol_md(path):
    """
    {method: {param: default_or_None}} from the "Methods" section: the methods named in its
    `### ` headings (### `sim.play` / `sim.pause`), and each param with its default from the
    generated reference's param table, whose rows read
    | `render` | `width` | integer (pixels) | `512` | [1, 4096] | Frame width... |
    (the method cell empty on a method's later rows; the default `required` or `optional` when
    there is none).
    """
    with open(path, encoding="utf-8") as f:
        text = f.read()
    m = re.search(r"^## Methods\s*$(.*?)(?=^## |\Z)", text, re.M | re.S)
    if not m:
        raise mock.CheckError("docs/protocol.md has no '## Methods' section")
    methods = {}
    last = None
    for line in m.group(1).splitlines():
        if line.startswith("### "):
            for span in re.findall(r"`([A-Za-z0-9_.]+)`", line):
                methods.setdefault(span, {})
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) != 6:
            continue
        mm = re.fullmatch(r"`([A-Za-z0-9_.]+)`", cells[0])
        if mm:
            last = mm.group(1)
        pm = re.fullmatch(r"`([A-Za-z0-9_]+)`", cells[1])
        if last is None or not pm:
            continue
        default = cells[3]
        default = mock.loads(default.strip("`")) if default.startswith("`") else None
        methods.setdefault(last, {})[pm.group(1)] = default
    return methods


def resolve(doc, schema, depth=0):
    """Follows local $ref pointers ("#/components/schemas/X")."""
    while isinstance(schema, dict) and "$ref" in schema and depth < 20:
        ref = schema["$ref"]
        if not ref.startswith("#/"):
            return schema
        node = doc
        for part in ref[2:].split("/"):
            node = node.get(part) if isinstance(node, dict) else None
        schema = node
        depth += 1
    return schema


@T
def documented_methods(s):
    DOC["methods"] = parse_protocol_md(PROTOCOL_MD)
    names = sorted(DOC["methods"])
    print("    docs/protocol.md methods: %s" % ", ".join(names))
    for must in ("server.info", "rpc.discover", "auth", "scene.list", "scene.create",
                 "scene.delete", "scene.get", "scene.set", "sim.step", "sim.play", "sim.pause",
                 "render", "frames.subscribe", "frames.unsubscribe", "stats", "server.shutdown"):
        s.check(must in DOC["methods"], "the heading parser finds %s" % must)
    s.check("path" in DOC["methods"].get("scene.set", {}) and
            "patch" in DOC["methods"].get("scene.set", {}),
            "scene.set has both forms' params", short(DOC["methods"].get("scene.set")))


@T
def openrpc_document(s):
    with s.srv.connect() as c:
        r, _ = c.ok("rpc.discover", {})
        # Without params too.
        r2, _ = c.ok("rpc.discover")
        s.eq(r2, r, "rpc.discover without params gives the same document")
        lim = c.ok("server.info", {})[0].get("limits", {})
    DOC["openrpc"] = r
    s.eq(r.get("openrpc"), "1.2.6", "openrpc version")
    info = r.get("info")
    s.check(isinstance(info, dict) and isinstance(info.get("title"), str) and
            isinstance(info.get("version"), str), "info has title and version", short(info))
    methods = r.get("methods")
    if not s.check(isinstance(methods, list) and methods, "methods is a non-empty array"):
        return
    byname = {}
    for m in methods:
        if s.check(isinstance(m, dict) and isinstance(m.get("name"), str), "method has a name",
                   short(m)):
            s.check(m["name"] not in byname, "method %s listed once" % m["name"])
            byname[m["name"]] = m
    documented = DOC.get("methods") or parse_protocol_md(PROTOCOL_MD)
    for name in sorted(documented):
        s.check(name in byname, "documented method %s is in rpc.discover" % name)
    for name in sorted(byname):
        s.check(name in documented, "rpc.discover method %s is documented in docs/protocol.md"
                % name)
    # Integer bounds past 10^15 are published exactly (cJSON alone prints 2^53 - 1 rounded).
    unsub = {p.get("name"): p for p in byname.get("frames.unsubscribe", {}).get("params", [])}
    idmax = resolve(r, (unsub.get("id") or {}).get("schema") or {}).get("maximum")
    s.eq(idmax, 2 ** 53 - 1, "frames.unsubscribe id's maximum is 2^53 - 1 exactly")
    for name, m in sorted(byname.items()):
        params = m.get("params")
        if not s.check(isinstance(params, list), "%s params is an array" % name, short(m)):
            continue
        pnames = {}
        for p in params:
            p = resolve(r, p)
            ok = isinstance(p, dict) and isinstance(p.get("name"), str) and \
                isinstance(resolve(r, p.get("schema")), dict)
            s.check(ok, "%s param has a name and a schema" % name, short(p))
            if ok:
                pnames[p["name"]] = p
        s.check("result" in m and isinstance(resolve(r, m["result"]), dict) and
                "schema" in resolve(r, m["result"]), "%s has a result with a schema" % name,
                short(m.get("result")))
        s.check(isinstance(m.get("errors", []), list), "%s errors is an array" % name)
        for pname, default in documented.get(name, {}).items():
            if not s.check(pname in pnames, "%s param %s (documented) is in rpc.discover" %
                           (name, pname), "has %s" % sorted(pnames)):
                continue
            if default is not None:
                sch = resolve(r, pnames[pname]["schema"])
                s.eq(sch.get("default"), default, "%s.%s default as documented" % (name, pname))
        for pname in pnames:
            s.check(pname in documented.get(name, {}) or name not in documented,
                    "%s param %s from rpc.discover is documented" % (name, pname))
        if name in documented:
            s.eq(m.get("paramStructure", "by-name"), "by-name",
                 "%s paramStructure by-name" % name)
    # render's width: range and default.
    rm = byname.get("render")
    if rm:
        width = [resolve(r, p) for p in rm.get("params", [])
                 if isinstance(resolve(r, p), dict) and resolve(r, p).get("name") == "width"]
        if s.check(width, "render has a width param"):
            sch = resolve(r, width[0].get("schema")) or {}
            s.eq(sch.get("default"), 512, "render width default")
            s.eq(sch.get("minimum"), 1, "render width minimum")
            s.eq(sch.get("maximum"), lim.get("frame_side", 4096),
                 "render width maximum is limits.frame_side")
            s.check(sch.get("type") == "integer", "render width is an integer", short(sch))
        codes = {e.get("code") for e in (resolve(r, e) for e in rm.get("errors", []))
                 if isinstance(e, dict)}
        for code in (mock.E_PARAMS, mock.E_LIMIT, mock.E_NOT_FOUND):
            s.check(code in codes, "render lists error %d" % code, sorted(codes, key=str))
    # The scene schema.
    comps = r.get("components") or {}
    scene = resolve(r, (comps.get("schemas") or {}).get("Scene"))
    if not s.check(isinstance(scene, dict), "components.schemas.Scene exists", short(comps)):
        return
    props = scene.get("properties") or {}
    # waves, fluid, cloud and volumes join the schema with the effects that use them.
    for k in ("camera", "background", "light", "objects", "sim", "render"):
        s.check(k in props, "Scene has property %s" % k, sorted(props))
    cam = resolve(r, props.get("camera")) or {}
    fov = resolve(r, (cam.get("properties") or {}).get("fov_y"))
    if s.check(isinstance(fov, dict), "Scene camera.fov_y schema", short(cam)):
        s.check("default" in fov, "camera.fov_y has a default", short(fov))
        s.eq(fov.get("x-unit"), "degrees", "camera.fov_y x-unit")
        s.check("minimum" in fov or "exclusiveMinimum" in fov, "camera.fov_y has a minimum",
                short(fov))
        s.check("maximum" in fov or "exclusiveMaximum" in fov, "camera.fov_y has a maximum",
                short(fov))
    s.eq(scene.get("additionalProperties"), False, "Scene refuses unknown members")
    # The scene's defaults are what a new scene holds.
    with s.srv.connect() as c:
        c.ok("scene.create", {"name": "defaults"})
        doc, _ = c.ok("scene.get", {"scene": "defaults"})
        c.ok("scene.delete", {"name": "defaults"})
    want = fov.get("default") if isinstance(fov, dict) else None
    if doc.get("camera", {}).get("fov_y") != want:
        s.note("a new scene's camera.fov_y %r is not the published default %r" %
               (doc.get("camera", {}).get("fov_y"), want))


if __name__ == "__main__":
    sys.exit(suite.main())
