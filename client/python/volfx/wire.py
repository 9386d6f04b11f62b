"""volfx.wire: what the blocking and the asyncio client share, apart from their sockets.

Request lines, the errors a response carries, where a message's attachments are, and the
``Inbox`` that keeps what the server pushes: per subscription only the newest unread frame
(the server's latest-wins kept on this side too; each frame it replaces is counted), the
``frames.ended`` reasons, and a bounded queue of the other notifications (``job.progress``).
"""

import base64
import collections
import json

# Notifications other than frames kept while nobody reads them; the oldest are dropped first.
NOTES_MAX = 256

ERROR_NAMES = {
    -32700: "parse error",
    -32600: "invalid request",
    -32601: "method not found",
    -32602: "invalid params",
    -32603: "internal error",
    -32001: "unauthorized",
    -32002: "busy",
    -32003: "limit exceeded",
    -32004: "not found",
    -32005: "device error",
}


class VolfxError(Exception):
    """An error response from the server: JSON-RPC ``code``, ``message`` and ``data.path``."""

    def __init__(self, code, message, path=None, data=None):
        self.code = code
        self.message = message
        self.path = path
        self.data = data
        kind = ERROR_NAMES.get(code, "error %d" % code)
        text = message if message.startswith(kind) else "%s: %s" % (kind, message)
        if path:
            text += " (path %s)" % path
        super().__init__(text)


class ConnectionLost(Exception):
    """The connection closed, timed out or carried something that is not the protocol."""


def request(rid, method, params):
    """One request object; ``params`` None sends none."""
    req = {"jsonrpc": "2.0", "id": rid, "method": method}
    if params is not None:
        req["params"] = params
    return req


def encode_line(value):
    """A request (or a batch array of them) as one protocol line."""
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode() + b"\n"


def parse_line(line):
    """The JSON value of a line from the server; ``ConnectionLost`` when it is not JSON."""
    try:
        return json.loads(line)
    except ValueError:
        raise ConnectionLost("malformed line from the server: %r" % line[:200]) from None


def is_notification(msg):
    return isinstance(msg, dict) and "method" in msg and "id" not in msg


def holders(msg):
    """The objects of ``msg`` that may carry an attachment, in the order their bytes follow the
    line: a notification's params, a response's result, each result of a batch response."""
    if is_notification(msg):
        return [msg.get("params")]
    if isinstance(msg, dict):
        return [msg.get("result")]
    if isinstance(msg, list):
        return [r.get("result") if isinstance(r, dict) else None for r in msg]
    return []


def attachment_need(holder):
    """What ``holder``'s attachment takes: None for none, ``bytes`` when it came inline as
    base64 (removed from the holder), else the number of raw bytes that follow the line."""
    if not isinstance(holder, dict) or not isinstance(holder.get("attachment"), dict):
        return None
    att = holder["attachment"]
    for owner in (att, holder):
        if isinstance(owner.get("data"), str):
            return base64.b64decode(owner.pop("data"))
    n = att.get("bytes")
    if not isinstance(n, int) or n < 0:
        raise ConnectionLost("attachment without a valid byte count")
    return n


def error_of(response):
    """The ``VolfxError`` of an error response, or None for a result."""
    if not isinstance(response, dict) or "error" not in response:
        return None
    e = response["error"] or {}
    d = e.get("data")
    path = d.get("path") if isinstance(d, dict) else None
    return VolfxError(e.get("code", -32603), e.get("message", ""), path, d)


def batch_answers(ids, msg, datas):
    """``[(result, bytes, error)]`` in the order of ``ids`` from a batch response array (or
    the single error object a refused batch gets)."""
    if isinstance(msg, dict):
        err = error_of(msg) or ConnectionLost("a batch answered by %r" % msg)
        return [(None, None, err) for _ in ids]
    by_id = {}
    for r, data in zip(msg, datas):
        if isinstance(r, dict):
            by_id[r.get("id")] = (r.get("result"), data, error_of(r))
    missing = ConnectionLost("the batch response has no answer for this call")
    return [by_id.get(i, (None, None, missing)) for i in ids]


class Frame(collections.namedtuple("Frame", "params data")):
    """One ``frames`` notification: its ``params`` and the frame's bytes (``data``). Unpacks
    as ``params, data``."""

    __slots__ = ()

    @property
    def id(self):
        """The subscription it belongs to."""
        return self.params.get("id")


class Inbox:
    """What the server pushed and nobody has read yet.

    ``put`` keeps, per subscription, only the newest frame: a newer one replaces the unread
    one, and ``replaced[id]`` counts how many were replaced so (the server's ``dropped`` counts
    the ones that never left it). Subscriptions are handed out in the order their waiting
    frame arrived. ``frames.ended`` sets ``ended[id]`` to its reason and is queued with the
    other notifications, at most ``notes_max`` of them (``notes_dropped`` counts the rest).
    """

    def __init__(self, notes_max=NOTES_MAX):
        self.latest = {}
        self.replaced = collections.Counter()
        self.ended = {}
        self.notes = collections.deque()
        self.notes_max = notes_max
        self.notes_dropped = 0

    def put(self, msg, data):
        params = msg.get("params") if isinstance(msg.get("params"), dict) else {}
        method = msg.get("method")
        if method == "frames" and "id" in params:
            sid = params["id"]
            if self.latest.pop(sid, None) is not None:
                self.replaced[sid] += 1
            self.latest[sid] = Frame(params, data)
            return
        if method == "frames.ended":
            self.ended[params.get("id")] = params.get("reason")
        self.notes.append((msg, data))
        while len(self.notes) > self.notes_max:
            self.notes.popleft()
            self.notes_dropped += 1

    def take_frame(self, sid=None):
        """The unread frame of ``sid`` (any subscription's, oldest waiting first, when None),
        or None."""
        if sid is None:
            sid = next(iter(self.latest), None)
        return self.latest.pop(sid, None)

    def take_note(self, method=None):
        """The oldest queued notification (of ``method`` when given) as ``(msg, data)``."""
        for i, (msg, data) in enumerate(self.notes):
            if method is None or msg.get("method") == method:
                del self.notes[i]
                return msg, data
        return None

    def take(self, method):
        """The next thing for ``notifications(method)``: ``(method, params, data)`` or None.
        Queued notifications come before waiting frames."""
        if method != "frames":
            item = self.take_note(method)
            if item is not None:
                return item[0].get("method"), item[0].get("params"), item[1]
        if method in (None, "frames"):
            f = self.take_frame()
            if f is not None:
                return "frames", f.params, f.data
        return None

    def forget(self, sid):
        """Drops the unread frame of a subscription that was ended."""
        self.latest.pop(sid, None)

    def clear(self):
        self.latest.clear()
        self.notes.clear()


class InboxViews:
    """What both clients tell of their ``inbox``."""

    def _forget(self, sid):
        self.inbox.forget(sid)

    def replaced(self, sid=None):
        """Frames of ``sid`` (of all subscriptions when None) that a newer frame replaced here
        before they were read. The server's ``dropped`` counts those it never sent."""
        if sid is None:
            return sum(self.inbox.replaced.values())
        return self.inbox.replaced[sid]

    def ended(self, sid):
        """The reason the server ended ``sid`` with (``frames.ended``), or None."""
        return self.inbox.ended.get(sid)
