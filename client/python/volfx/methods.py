"""volfx.methods: one Python method per volfxd method, shared by ``Client``, ``AsyncClient``
and their batches.

Every wrapper builds the params its caller gave (None means "not given": the server's method
table fills in the default, docs/protocol.md's method reference) and hands them to
``self._request``, which the blocking client answers at once, the asyncio client with a
coroutine, and a batch by recording the call. ``METHODS`` maps each server method to its
wrapper's name; the client test fails when rpc.discover lists a method missing from it.
"""

import base64

from .wire import batch_answers

METHODS = {}


def _given(**params):
    """The params that are not None: the ones left out take the server's defaults."""
    return {k: v for k, v in params.items() if v is not None}


def _b64(data):
    """Bytes as the base64 text the server reads; text is taken as already encoded."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(data)).decode("ascii")
    return data


def _wraps(rpc_name):
    def mark(fn):
        METHODS[rpc_name] = fn.__name__
        return fn
    return mark


class Methods:
    """The wrappers. A subclass provides ``_request(method, params, post=None, raw=False)``:
    ``raw`` asks for ``(result, bytes)`` instead of the result, and ``post`` maps what the call
    returns to what the wrapper returns."""

    def _forget(self, sid):
        """Drops what is kept of an ended subscription; the clients override it."""

    @_wraps("auth")
    def auth(self, token):
        return self._request("auth", {"token": token})

    @_wraps("server.info")
    def info(self):
        return self._request("server.info", None)

    @_wraps("rpc.discover")
    def discover(self):
        return self._request("rpc.discover", None)

    @_wraps("stats")
    def stats(self):
        return self._request("stats", None)

    @_wraps("server.shutdown")
    def shutdown(self):
        return self._request("server.shutdown", None)

    @_wraps("scene.list")
    def scenes(self):
        """``{"scenes": [{name, frame, time, playing, version}]}``."""
        return self._request("scene.list", None)

    @_wraps("scene.presets")
    def presets(self):
        """``{"presets": [name, ...]}``: what ``create_scene(preset=...)`` accepts."""
        return self._request("scene.presets", None)

    @_wraps("scene.create")
    def create_scene(self, name, preset=None):
        return self._request("scene.create", _given(name=name, preset=preset))

    @_wraps("scene.delete")
    def delete_scene(self, name):
        """Deletes a scene; its subscriptions end with ``frames.ended``."""
        return self._request("scene.delete", {"name": name})

    @_wraps("scene.get")
    def get(self, path=None, scene=None):
        """The scene document, or the value at dotted ``path``."""
        return self._request("scene.get", _given(scene=scene, path=path))

    @_wraps("scene.set")
    def set(self, path, value, scene=None):
        """Sets one value at dotted ``path``; returns ``{"version": n}``."""
        return self._request("scene.set", dict(_given(scene=scene), path=path, value=value))

    def patch(self, patch, scene=None):
        """Applies an RFC 7386 merge patch atomically (scene.set); returns ``{"version": n}``."""
        return self._request("scene.set", dict(_given(scene=scene), patch=patch))

    def changes(self, changes, scene=None, tag=None):
        """Applies ``[{"path", "value"} or {"path", "patch"}, ...]`` in order as one version, or
        nothing (scene.set); returns ``{"version": n}``."""
        return self._request("scene.set", dict(_given(scene=scene, tag=tag), changes=list(changes)))

    def json_patch(self, ops, scene=None, tag=None):
        """Applies an RFC 6902 JSON Patch (a list of operations) as one version, or nothing
        (scene.set); returns ``{"version": n}``."""
        return self._request("scene.set", dict(_given(scene=scene, tag=tag), ops=list(ops)))

    @_wraps("scene.save")
    def save(self, file, scene=None):
        """Writes a snapshot to ``file`` under the server's data directory."""
        return self._request("scene.save", _given(scene=scene, file=file))

    @_wraps("scene.load")
    def load(self, file, scene=None):
        return self._request("scene.load", _given(scene=scene, file=file))

    @_wraps("sim.step")
    def step(self, n=None, dt=None, scene=None):
        return self._request("sim.step", _given(scene=scene, steps=n, dt=dt))

    @_wraps("sim.play")
    def play(self, rate=None, scene=None):
        return self._request("sim.play", _given(scene=scene, rate=rate))

    @_wraps("sim.pause")
    def pause(self, scene=None):
        return self._request("sim.pause", _given(scene=scene))

    @_wraps("render")
    def render(self, width=None, height=None, format=None, **kw):
        """Renders one frame; returns ``(result, bytes)``. ``kw``: scene, aov, layers, camera,
        t, encoding, png_level and whatever else the server's render takes."""
        return self._request("render", _given(width=width, height=height, format=format, **kw),
                             raw=True)

    @_wraps("frames.subscribe")
    def subscribe(self, **kw):
        """Starts a frame stream and returns its id; ``kw`` as frames.subscribe takes them."""
        return self._request("frames.subscribe", _given(**kw), post=lambda r: r["id"])

    @_wraps("frames.update")
    def update_subscription(self, sid, **view):
        """Changes a subscription's view live (frames.update): camera, width, height, fps,
        format, quality, layers."""
        return self._request("frames.update", dict(_given(**view), id=sid))

    @_wraps("frames.unsubscribe")
    def unsubscribe(self, sid):
        """Ends a stream; returns ``{"id", "sent", "dropped"}``. Its unread frame is dropped."""
        def done(result):
            self._forget(sid)
            return result
        return self._request("frames.unsubscribe", {"id": sid}, post=done)

    @_wraps("render.sequence")
    def sequence(self, first, last, dir, step=None, **kw):
        """Starts a job writing frames first..last under ``dir``; returns ``{id, total, files}``.
        ``job.progress`` notifications follow. ``kw``: the frame params as for render."""
        return self._request("render.sequence",
                             _given(first=first, last=last, dir=dir, step=step, **kw))

    @_wraps("sim.bake")
    def bake(self, dir, last, every=None, scene=None):
        """Starts a job writing snapshots up to ``last`` under ``dir``."""
        return self._request("sim.bake", _given(scene=scene, dir=dir, last=last, every=every))

    @_wraps("job.list")
    def jobs(self):
        return self._request("job.list", None)

    @_wraps("job.cancel")
    def cancel_job(self, job_id):
        return self._request("job.cancel", {"id": job_id})

    @_wraps("fluid.set_particles")
    def set_particles(self, positions, velocities=None, scene=None):
        """Replaces the fluid's particles; ``positions``/``velocities`` are little-endian f32
        x, y, z triples, as bytes (or base64 text)."""
        return self._request("fluid.set_particles",
                             _given(scene=scene, positions=_b64(positions),
                                    velocities=_b64(velocities)))

    @_wraps("fluid.get_particles")
    def get_particles(self, field=None, scene=None, encoding=None):
        """Returns ``(result, bytes)``: f32 x, y, z per particle."""
        return self._request("fluid.get_particles",
                             _given(scene=scene, field=field, encoding=encoding), raw=True)

    @_wraps("cloud.get_cells")
    def get_cells(self, field=None, scene=None, encoding=None):
        """Returns ``(result, bytes)``: one u8 (or f32 for density) per cell."""
        return self._request("cloud.get_cells",
                             _given(scene=scene, field=field, encoding=encoding), raw=True)

    @_wraps("cloud.set_cells")
    def set_cells(self, field, data, scene=None):
        """Replaces one field of the cloud's cells from ``data`` (bytes or base64 text)."""
        return self._request("cloud.set_cells", _given(scene=scene, field=field, data=_b64(data)))


class BatchReply:
    """One call's answer in a batch: ``result`` (what the wrapper returns) or ``error`` (a
    ``VolfxError``, or ``ConnectionLost`` when the server left it unanswered)."""

    __slots__ = ("result", "error")

    def __init__(self, result, error):
        self.result = result
        self.error = error

    def value(self):
        """The result, or raises the error."""
        if self.error is not None:
            raise self.error
        return self.result

    def __repr__(self):
        return "BatchReply(%s)" % ("error=%r" % self.error if self.error else repr(self.result))


class Batch(Methods):
    """Calls collected to go out as one JSON-RPC batch line. Each wrapper (and ``call`` /
    ``call_raw``) returns the call's index; ``send()`` sends them all and returns one
    ``BatchReply`` per call, in order (a coroutine for the asyncio client). The server runs
    the parts in order; one failing part does not stop the others."""

    def __init__(self, client):
        self._client = client
        self._calls = []

    def __len__(self):
        return len(self._calls)

    def _request(self, method, params, post=None, raw=False):
        self._calls.append((method, params, post, raw))
        return len(self._calls) - 1

    def _forget(self, sid):
        self._client._forget(sid)

    def call(self, method, **params):
        return self._request(method, params)

    def call_raw(self, method, params=None):
        return self._request(method, params, raw=True)

    def send(self):
        return self._client._send_batch(self)

    def _ids_and_line(self, first_id):
        """The ids the calls go out with and the batch as request objects."""
        if not self._calls:
            raise ValueError("an empty batch: add calls before send()")
        ids = list(range(first_id, first_id + len(self._calls)))
        reqs = [{"jsonrpc": "2.0", "id": i, "method": m, **({} if p is None else {"params": p})}
                for i, (m, p, _, _) in zip(ids, self._calls)]
        return ids, reqs

    def _replies(self, ids, msg, datas):
        replies = []
        for (_, _, post, raw), (result, data, error) in zip(self._calls,
                                                           batch_answers(ids, msg, datas)):
            if error is not None:
                replies.append(BatchReply(None, error))
                continue
            value = (result, data) if raw else result
            replies.append(BatchReply(post(value) if post else value, None))
        return replies
