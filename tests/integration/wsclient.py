"""
A small RFC 6455 WebSocket client for the tests of volfxd's --http listener, standard library
only: the opening handshake (with any Origin), masked text and binary frames (fragmented when
asked), and reading messages back with their continuation frames joined. call() speaks volfx's
WebSocket transport: one JSON request per text message, an attachment as the binary message
after the text message that announces it.
"""

import base64
import json
import os
import socket
import struct

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0, 1, 2, 8, 9, 10


class HandshakeRefused(Exception):
    """The server did not answer the upgrade with 101."""


class WsClosed(Exception):
    """The server closed the WebSocket; 'code' and 'reason' are its close frame's."""

    def __init__(self, code, reason):
        super().__init__("closed by the server: %s %s" % (code, reason))
        self.code, self.reason = code, reason


class WsConn:
    def __init__(self, host, port, origin=None, path="/ws", timeout=30.0):
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        key = base64.b64encode(os.urandom(16)).decode()
        lines = ["GET %s HTTP/1.1" % path, "Host: %s:%d" % (host, port), "Upgrade: websocket",
                 "Connection: Upgrade", "Sec-WebSocket-Key: " + key,
                 "Sec-WebSocket-Version: 13"]
        if origin:
            lines.append("Origin: " + origin)
        self.sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise HandshakeRefused("connection closed during the handshake")
            self.buf += chunk
        head, self.buf = self.buf.split(b"\r\n\r\n", 1)
        status = head.split(b"\r\n", 1)[0].decode("latin-1")
        if " 101 " not in status + " ":
            raise HandshakeRefused(status)
        self.next_id = 1
        self.notifications = []

    def close(self):
        self.sock.close()  # Closing a socket twice is harmless.

    def __enter__(self):
        return self

    def __exit__(self, *a):
        self.close()

    # -- sending
    def send_frame(self, opcode, payload, fin=True):
        if isinstance(payload, str):
            payload = payload.encode("utf-8")
        n = len(payload)
        head = bytes([(0x80 if fin else 0) | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 65536:
            head += bytes([0x80 | 126]) + struct.pack("!H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack("!Q", n)
        mask = os.urandom(4)
        masked = _mask_fast(payload, mask)
        self.sock.sendall(head + mask + masked)

    def send_text(self, text, fragments=1):
        data = text.encode("utf-8") if isinstance(text, str) else text
        step = max(1, -(-len(data) // fragments))
        parts = [data[i:i + step] for i in range(0, len(data), step)] or [b""]
        for i, part in enumerate(parts):
            self.send_frame(OP_TEXT if i == 0 else OP_CONT, part, fin=i == len(parts) - 1)

    def send(self, obj):
        self.send_text(json.dumps(obj))

    # -- receiving
    def _need(self, n):
        while len(self.buf) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise WsClosed(None, "connection closed without a close frame")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv_frame(self):
        b0, b1 = self._need(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack("!H", self._need(2))[0]
        elif n == 127:
            n = struct.unpack("!Q", self._need(8))[0]
        if b1 & 0x80:
            raise AssertionError("the server masked a frame")
        return b0 & 0x80, b0 & 0x0F, self._need(n)

    def recv_message(self):
        """(opcode, payload) of the next data message; raises WsClosed on a close frame."""
        data, opcode = b"", None
        while True:
            fin, op, payload = self.recv_frame()
            if op == OP_CLOSE:
                code = struct.unpack("!H", payload[:2])[0] if len(payload) >= 2 else None
                raise WsClosed(code, payload[2:].decode("utf-8", "replace"))
            if op == OP_PING:
                self.send_frame(OP_PONG, payload)
                continue
            if op == OP_PONG:
                continue
            if opcode is None:
                opcode = op
            data += payload
            if fin:
                return opcode, data

    def recv_json(self):
        """The next text message as JSON, and the binary message after it when it announces an
        attachment."""
        op, data = self.recv_message()
        if op != OP_TEXT:
            raise AssertionError("expected a text message, got opcode %d" % op)
        msg = json.loads(data)
        att = None
        body = msg.get("result") if isinstance(msg, dict) else None
        if not isinstance(body, dict) and isinstance(msg, dict):
            body = msg.get("params")
        if isinstance(body, dict) and isinstance(body.get("attachment"), dict) and \
                body["attachment"].get("bytes", 0) > 0 and "data" not in body:
            op, att = self.recv_message()
            if op != OP_BINARY:
                raise AssertionError("expected the attachment as a binary message")
        return msg, att

    def recv_response(self):
        while True:
            msg, att = self.recv_json()
            if isinstance(msg, dict) and "method" in msg and "id" not in msg:
                self.notifications.append((msg, att))
                continue
            return msg, att

    def call(self, method, params=None):
        req = {"jsonrpc": "2.0", "id": self.next_id, "method": method}
        self.next_id += 1
        if params is not None:
            req["params"] = params
        self.send(req)
        return self.recv_response()


def _mask_fast(payload, mask):
    n = len(payload)
    full = (mask * (n // 4 + 1))[:n]
    return (int.from_bytes(payload, "big") ^ int.from_bytes(full, "big")).to_bytes(n, "big")


def http_get(host, port, path, timeout=10.0):
    """(status, headers dict with lower-case names, body) of a GET sent as written (no path
    cleaning), for the static files."""
    s = socket.create_connection((host, port), timeout=timeout)
    s.sendall(("GET %s HTTP/1.1\r\nHost: %s:%d\r\nConnection: close\r\n\r\n" %
               (path, host, port)).encode())
    data = b""
    while True:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    s.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {}
    for line in lines[1:]:
        k, _, v = line.partition(":")
        headers[k.strip().lower()] = v.strip()
    return status, headers, body
