"""volfx.aio: an asyncio client for volfxd (standard library only: asyncio streams).

    async with await AsyncClient.connect(port=7878) as c:
        sid = await c.subscribe(width=320, height=180, fps=60)
        await c.set("camera.fov_y", 40)
        frame = await c.latest(sid, timeout=1)
        async for params, data in c.frames(count=10):
            ...

One task reads the connection: responses complete the calls waiting for them (calls may run
concurrently; the server answers a connection's requests in order), frames go to the same
``Inbox`` as the blocking client's (the newest unread frame per subscription, the replaced
ones counted), and ``frames.ended`` and ``job.progress`` to its queue. The wrappers are the
blocking client's (``volfx.methods``), each returning a coroutine here.
"""

import asyncio
import socket

from .methods import Batch, Methods
from .wire import (ConnectionLost, Inbox, InboxViews, attachment_need, encode_line, error_of,
                   holders, is_notification, parse_line, request)

LINE_LIMIT = 64 << 20  # The longest line read: an OpenRPC document or a big scene.


class AsyncClient(InboxViews, Methods):
    """One asyncio connection to volfxd; make it with ``await AsyncClient.connect(...)``.

    ``timeout`` (seconds, None for none) bounds each call's wait for its answer; a call that
    times out raises ``ConnectionLost`` and the client should be closed."""

    def __init__(self, reader, writer, timeout=30):
        self._reader = reader
        self._writer = writer
        self.timeout = timeout
        self.inbox = Inbox()
        self._next_id = 1
        self._pending = {}  # request id (a batch's first id) -> Future
        self._wake = asyncio.Event()
        self._lost = None
        self._task = asyncio.get_running_loop().create_task(self._read_loop())

    @classmethod
    async def connect(cls, host="127.0.0.1", port=7878, unix=None, token=None, timeout=30):
        """Opens a connection (TCP, or the Unix socket ``unix``) and sends ``auth`` with
        ``token`` when one is given."""
        if unix:
            opening = asyncio.open_unix_connection(unix, limit=LINE_LIMIT)
        else:
            opening = asyncio.open_connection(host or "127.0.0.1", port or 7878, limit=LINE_LIMIT)
        try:
            reader, writer = await asyncio.wait_for(opening, timeout)
        except asyncio.TimeoutError:
            raise ConnectionLost("timed out connecting to the server") from None
        sock = writer.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = cls(reader, writer, timeout)
        if token:
            try:
                await client.auth(token)
            except BaseException:
                await client.close()
                raise
        return client

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.close()
        return False

    async def close(self):
        """Closes the connection; calls still waiting raise ``ConnectionLost``."""
        self._task.cancel()
        try:
            await self._task
        except (asyncio.CancelledError, Exception):
            pass
        self._fail_all(ConnectionLost("the client was closed"))
        self._writer.close()
        try:
            await self._writer.wait_closed()
        except OSError:
            pass
        self.inbox.clear()

    # -- reading ---------------------------------------------------------------------------

    async def _read_message(self):
        while True:
            try:
                line = await self._reader.readuntil(b"\n")
            except asyncio.IncompleteReadError:
                raise ConnectionLost("connection closed by the server") from None
            except asyncio.LimitOverrunError:
                raise ConnectionLost("a line from the server longer than %d bytes"
                                     % LINE_LIMIT) from None
            if line.strip():
                break
        msg = parse_line(line.rstrip(b"\r\n"))
        datas = []
        for holder in holders(msg):
            need = attachment_need(holder)
            if isinstance(need, int):
                try:
                    need = await self._reader.readexactly(need)
                except asyncio.IncompleteReadError:
                    raise ConnectionLost("connection closed inside an attachment") from None
            datas.append(need)
        return msg, datas

    async def _read_loop(self):
        try:
            while True:
                msg, datas = await self._read_message()
                if is_notification(msg):
                    self.inbox.put(msg, datas[0])
                    self._notify()
                    continue
                if isinstance(msg, list):
                    first = next((r.get("id") for r in msg if isinstance(r, dict)), None)
                    self._resolve(first, (msg, datas))
                elif isinstance(msg, dict):
                    if msg.get("id") is None and "error" in msg:
                        # A refused line: the oldest waiting call is the one it answers.
                        first = next(iter(self._pending), None)
                    else:
                        first = msg.get("id")
                    self._resolve(first, (msg, datas[0] if datas else None))
        except (ConnectionLost, OSError) as e:
            self._fail_all(e if isinstance(e, ConnectionLost) else ConnectionLost(str(e)))
        except asyncio.CancelledError:
            raise

    def _resolve(self, rid, value):
        fut = self._pending.pop(rid, None)
        if fut is not None and not fut.done():
            fut.set_result(value)

    def _fail_all(self, exc):
        self._lost = exc
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(exc)
        self._pending.clear()
        self._notify()

    def _notify(self):
        self._wake.set()
        self._wake = asyncio.Event()

    # -- calls -----------------------------------------------------------------------------

    async def _exchange(self, rid, line_value):
        if self._lost is not None:
            raise self._lost
        fut = asyncio.get_running_loop().create_future()
        self._pending[rid] = fut
        self._writer.write(encode_line(line_value))
        try:
            await self._writer.drain()
            return await asyncio.wait_for(asyncio.shield(fut), self.timeout)
        except asyncio.TimeoutError:
            raise ConnectionLost("timed out waiting for the server") from None
        except OSError as e:
            raise ConnectionLost(str(e)) from None
        finally:
            self._pending.pop(rid, None)

    async def call_raw(self, method, params=None):
        """Sends one request and returns ``(result, attachment bytes or None)``; raises
        ``VolfxError`` for an error response."""
        rid = self._next_id
        self._next_id += 1
        msg, data = await self._exchange(rid, request(rid, method, params))
        err = error_of(msg)
        if err is not None:
            raise err
        return msg.get("result"), data

    async def call(self, method, **params):
        return (await self.call_raw(method, params))[0]

    async def _request_async(self, method, params, post, raw):
        result, data = await self.call_raw(method, params)
        value = (result, data) if raw else result
        return post(value) if post else value

    def _request(self, method, params, post=None, raw=False):
        return self._request_async(method, params, post, raw)

    def batch(self):
        """A ``Batch``; ``await batch.send()`` returns one ``BatchReply`` per call."""
        return Batch(self)

    async def _send_batch(self, batch):
        ids, reqs = batch._ids_and_line(self._next_id)
        self._next_id = ids[-1] + 1
        msg, datas = await self._exchange(ids[0], reqs)
        return batch._replies(ids, msg, datas if isinstance(msg, list) else [])

    # -- frames and notifications ----------------------------------------------------------

    async def _wait_for(self, take, timeout):
        wait = self.timeout if timeout is None else timeout
        loop = asyncio.get_running_loop()
        deadline = None if wait is None else loop.time() + wait
        while True:
            wake = self._wake
            item = take()
            if item is not None:
                return item
            if self._lost is not None:
                raise self._lost
            left = None if deadline is None else deadline - loop.time()
            if left is not None and left <= 0:
                return None
            try:
                await asyncio.wait_for(wake.wait(), left)
            except asyncio.TimeoutError:
                return None

    async def latest(self, sid, timeout=0):
        """The newest unread ``Frame`` of ``sid``, waiting up to ``timeout`` seconds for one;
        None when none came or the subscription has ended (see ``ended``)."""
        return await self._wait_for(
            lambda: self.inbox.take_frame(sid) or (False if sid in self.inbox.ended else None),
            timeout) or None

    async def _each(self, take, timeout, count):
        got = 0
        while count is None or got < count:
            item = await self._wait_for(take, timeout)
            if item is None:
                return
            got += 1
            yield item

    def frames(self, timeout=None, count=None, sid=None):
        """Yields the newest unread ``Frame`` of ``sid`` (any subscription when None), as
        ``Client.frames``; use with ``async for``."""
        return self._each(lambda: self.inbox.take_frame(sid), timeout, count)

    def notifications(self, method=None, timeout=None, count=None):
        """Yields ``(method, params, bytes)`` as ``Client.notifications``; use with
        ``async for``."""
        return self._each(lambda: self.inbox.take(method), timeout, count)
