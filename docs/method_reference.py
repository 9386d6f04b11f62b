#!/usr/bin/env python3
"""The method reference of docs/protocol.md, generated from volfxd's method table.

volfxd describes every method it answers once, in its method table (server/methods.c and the
methods_*.c files: name, summary, params with their types, ranges and defaults, result,
errors), and publishes that table as the OpenRPC document of rpc.discover. This script starts
a volfxd with the default configuration, reads that document and writes it as Markdown between
the markers

    <!-- BEGIN generated: methods -->
    <!-- END generated: methods -->

in docs/protocol.md. Standard library only.

    python3 docs/method_reference.py --bin build/bin            # print the block
    python3 docs/method_reference.py --bin build/bin --write    # rewrite docs/protocol.md
    python3 docs/method_reference.py --bin build/bin --check    # exit 1 when it is stale

The ctest test integration.test_method_reference fails when the block is stale.
"""

import argparse
import difflib
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PROTOCOL_MD = os.path.join(ROOT, "docs", "protocol.md")
BEGIN = "<!-- BEGIN generated: methods -->"
END = "<!-- END generated: methods -->"
REGENERATE = "python3 docs/method_reference.py --bin build/bin --write"
LISTEN_RE = re.compile(r"volfxd listening on (\S+):(\d+)\s*$")
INT53 = 2 ** 53 - 1


class ReferenceFailure(Exception):
    """docs/protocol.md or the server is not as this script needs it."""


# -- reading the method table ------------------------------------------------------------------


def discover_from_server(bin_dir, timeout=120.0):
    """The rpc.discover document of a volfxd from 'bin_dir', started with the default
    configuration on a free port and stopped afterwards."""
    exe = os.path.join(bin_dir, "volfxd")
    env = dict(os.environ)
    env.pop("VOLFX_TOKEN", None)
    env.setdefault("POCL_CACHE_DIR", tempfile.mkdtemp(prefix="volfx-pocl-"))
    proc = subprocess.Popen([exe, "--listen", "127.0.0.1:0"], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
    try:
        deadline = time.monotonic() + timeout
        port = None
        for raw in proc.stdout:
            m = LISTEN_RE.search(raw.decode("utf-8", "replace"))
            if m:
                port = int(m.group(2))
                break
            if time.monotonic() > deadline:
                break
        if port is None:
            raise ReferenceFailure("%s did not start listening (exit status %s)" %
                                  (exe, proc.poll()))
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
            s.sendall(b'{"jsonrpc":"2.0","id":1,"method":"rpc.discover"}\n')
            buf = b""
            while b"\n" not in buf:
                chunk = s.recv(1 << 20)
                if not chunk:
                    raise ReferenceFailure("volfxd closed the connection before answering")
                buf += chunk
        answer = json.loads(buf.split(b"\n", 1)[0])
        if "result" not in answer:
            raise ReferenceFailure("rpc.discover failed: %r" % answer.get("error"))
        return answer["result"]
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# -- writing Markdown --------------------------------------------------------------------------


def _cell(text):
    """Text for one Markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def _number(v):
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    if v == INT53:
        return "2^53 − 1"
    return json.dumps(v)


def _code_list(values):
    return ", ".join("`%s`" % v for v in values)


def param_type(schema):
    """'integer (pixels)', 'one of `png`, ...', 'array of ...', 'any' for one param's schema."""
    t = schema.get("type")
    if "enum" in schema:
        text = "one of " + _code_list(schema["enum"])
    elif t == "array":
        items = schema.get("items") or {}
        text = "array of " + (_code_list(items["enum"]) if "enum" in items
                              else items.get("type", "any"))
        if "maxItems" in schema:
            text += ", at most %s" % _number(schema["maxItems"])
    elif t:
        text = t
    else:
        text = "any JSON value"
    if schema.get("x-unit"):
        text += " (%s)" % schema["x-unit"]
    return text


def param_range(schema):
    """The bounds of one param's schema: '[1, 4096]', '(0, 1]', 'up to 63 bytes', or ''."""
    if "maxLength" in schema:
        return "up to %s bytes" % _number(schema["maxLength"])
    lo = hi = None
    if "minimum" in schema:
        lo = "[" + _number(schema["minimum"])
    elif "exclusiveMinimum" in schema:
        lo = "(" + _number(schema["exclusiveMinimum"])
    if "maximum" in schema:
        hi = _number(schema["maximum"]) + "]"
    elif "exclusiveMaximum" in schema:
        hi = _number(schema["exclusiveMaximum"]) + ")"
    if lo is None and hi is None:
        return ""
    return "%s, %s" % (lo or "(−∞", hi or "∞)")


def param_default(param):
    schema = param.get("schema") or {}
    if param.get("required"):
        return "required"
    if "default" in schema:
        return "`%s`" % json.dumps(schema["default"])
    return "optional"


def markdown(doc):
    """The method reference (without its markers) for OpenRPC document 'doc'."""
    methods = doc.get("methods") or []
    out = [
        "<!-- Generated from volfxd's method table by docs/method_reference.py; do not edit",
        "     here: change the table, then run `%s`. -->" % REGENERATE,
        "",
        "| method | summary | result | errors |",
        "| --- | --- | --- | --- |",
    ]
    for m in methods:
        codes = [str(e.get("code")) for e in m.get("errors") or []]
        out.append("| `%s` | %s | %s | %s |" % (
            m["name"], _cell(m.get("summary", "")),
            _cell((m.get("result") or {}).get("description", "")), _code_list(codes)))
    out += [
        "",
        "Every param of every method, in the table's order. A param left out takes the default",
        "shown. A range bounded by a limit shows the limit's default; rpc.discover publishes the",
        "server's configured value.",
        "",
        "| method | param | type | default | range | description |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for m in methods:
        first = True
        for p in m.get("params") or []:
            schema = p.get("schema") or {}
            out.append("| %s | `%s` | %s | %s | %s | %s |" % (
                "`%s`" % m["name"] if first else "", p["name"], _cell(param_type(schema)),
                _cell(param_default(p)), _cell(param_range(schema)),
                _cell(p.get("description", ""))))
            first = False
    return "\n".join(out) + "\n"


# -- docs/protocol.md ---------------------------------------------------------------------------


def split_document(text):
    """(before, block, after) of 'text' around the markers, the markers kept in before/after."""
    b = text.find(BEGIN)
    e = text.find(END)
    if b < 0 or e < 0 or e < b or text.count(BEGIN) != 1 or text.count(END) != 1:
        raise ReferenceFailure("docs/protocol.md needs exactly one '%s' line followed by one "
                              "'%s' line" % (BEGIN, END))
    head = b + len(BEGIN) + 1
    return text[:head], text[head:e], text[e:]


def stale_diff(text, block):
    """A unified diff from the block in 'text' to 'block', or '' when they are the same."""
    _, have, _ = split_document(text)
    if have == block:
        return ""
    return "".join(difflib.unified_diff(have.splitlines(True), block.splitlines(True),
                                        "docs/protocol.md (generated: methods)",
                                        "the method table (rpc.discover)"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bin", default=os.path.join(ROOT, "build", "bin"),
                    help="the directory holding volfxd (default build/bin)")
    ap.add_argument("--discover", help="read this saved rpc.discover document instead")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--write", action="store_true", help="rewrite docs/protocol.md's block")
    mode.add_argument("--check", action="store_true", help="exit 1 when the block is stale")
    a = ap.parse_args(argv)
    try:
        if a.discover:
            with open(a.discover, encoding="utf-8") as f:
                doc = json.load(f)
        else:
            doc = discover_from_server(a.bin)
        block = markdown(doc)
        if not (a.write or a.check):
            sys.stdout.write(block)
            return 0
        with open(PROTOCOL_MD, encoding="utf-8") as f:
            text = f.read()
        diff = stale_diff(text, block)
        if a.check:
            if diff:
                sys.stdout.write(diff)
                print("docs/protocol.md's method reference is stale; regenerate it with: %s"
                      % REGENERATE, file=sys.stderr)
                return 1
            return 0
        if diff:
            head, _, tail = split_document(text)
            with open(PROTOCOL_MD, "w", encoding="utf-8") as f:
                f.write(head + block + tail)
            print("docs/protocol.md: method reference rewritten", file=sys.stderr)
        return 0
    except (ReferenceFailure, OSError, ValueError) as e:
        print("method_reference.py: %s" % e, file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
