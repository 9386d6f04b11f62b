#!/usr/bin/env python3
"""
docs/protocol.md's method reference against the method table: the block between
`<!-- BEGIN generated: methods -->` and `<!-- END generated: methods -->` must be exactly what
docs/method_reference.py writes from this volfxd's rpc.discover, and the Python client must
take its defaults from the server rather than spell them out.

    python3 tests/integration/test_method_reference.py --bin build/bin
"""

import importlib.util
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_method_reference", timeout_s=240)
suite.server_args = []
T = suite.test

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def load(name, *path):
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, *path))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


reference = load("method_reference", "docs", "method_reference.py")
sys.path.insert(0, os.path.join(ROOT, "client", "python"))
import volfx  # noqa: E402


@T
def reference_is_current(s):
    with s.srv.connect() as c:
        doc, _ = c.ok("rpc.discover")
    with open(reference.PROTOCOL_MD, encoding="utf-8") as f:
        text = f.read()
    try:
        diff = reference.stale_diff(text, reference.markdown(doc))
    except reference.ReferenceFailure as e:
        s.fail("docs/protocol.md has its method reference markers", str(e))
        return
    if diff:
        print(diff)
    s.check(not diff, "docs/protocol.md's method reference matches the method table",
            "it is stale; regenerate it with: %s" % reference.REGENERATE)


@T
def every_method_has_a_section(s):
    with s.srv.connect() as c:
        doc, _ = c.ok("rpc.discover")
    with open(reference.PROTOCOL_MD, encoding="utf-8") as f:
        text = f.read()
    headings = [ln for ln in text.splitlines() if ln.startswith("### ")]
    for m in doc.get("methods", []):
        s.check(any("`%s`" % m["name"] in h for h in headings),
                "docs/protocol.md has a '### `%s`' section" % m["name"])


@T
def python_client_takes_the_servers_defaults(s):
    """The client leaves out what its caller did not give, so the table's defaults apply, and
    Client.defaults reports them from rpc.discover."""
    with s.srv.connect() as c:
        doc, _ = c.ok("rpc.discover")
    table = {m["name"]: {p["name"]: p["schema"]["default"] for p in m["params"]
                         if "default" in p["schema"]} for m in doc["methods"]}
    with volfx.Client("127.0.0.1", s.srv.port, timeout=60) as client:
        for name in ("render", "frames.subscribe", "sim.step", "sim.play", "render.sequence"):
            s.eq(client.defaults(name), table[name], "Client.defaults(%r)" % name)
        result, data = client.render()
        want = table["render"]
        s.eq((result.get("width"), result.get("height"), result.get("format")),
             (want["width"], want["height"], want["format"]),
             "a render with no params has the table's size and format")
        s.check(data and data.startswith(mock.PNG_SIGNATURE) == (want["format"] == "png"),
                "the default frame's bytes are its format's")
        try:
            client.defaults("no.such.method")
            s.fail("Client.defaults of an unknown method raises ValueError")
        except ValueError:
            pass


if __name__ == "__main__":
    sys.exit(suite.main())
