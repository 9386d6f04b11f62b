"""
The mock client harness of the integration tests: starts a real volfxd on 127.0.0.1 with a
fresh data directory, talks to it over a raw socket (so malformed bytes are as easy to send as
well-formed requests) and records failed checks. Python 3 standard library only.

A test file builds a Suite, registers test functions and calls suite.main(): it parses
`--bin DIR`, arms an overall alarm so nothing can hang, runs every test (one failing test does
not stop the others), prints each failed check and exits non-zero when any failed.
"""

import argparse
import base64
import json
import os
import queue
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import zlib

LISTEN_RE = re.compile(r"volfxd listening on (\S+):(\d+)\s*$")
SANITIZER_MARKS = ("ERROR: AddressSanitizer", "ERROR: LeakSanitizer", "runtime error:",
                   "ThreadSanitizer", "SUMMARY: UndefinedBehaviorSanitizer")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
DEFAULT_TIMEOUT = 30.0

# Error codes of docs/protocol.md.
E_PARSE = -32700
E_INVALID_REQUEST = -32600
E_METHOD = -32601
E_PARAMS = -32602
E_INTERNAL = -32603
E_UNAUTHORIZED = -32001
E_BUSY = -32002
E_LIMIT = -32003
E_NOT_FOUND = -32004
E_DEVICE = -32005

_live_servers = []  # Servers to kill when the overall alarm fires.
SUITE = None        # The running Suite, for checks made inside the harness.


class CheckError(Exception):
    """A check that makes the rest of the current test meaningless."""


def _reject_constant(name):
    raise ValueError("server sent the non-JSON literal %s" % name)


def loads(text):
    """Strict JSON: refuses NaN/Infinity, which are not JSON."""
    return json.loads(text, parse_constant=_reject_constant)


def dumps(obj):
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def short(obj, n=300):
    s = obj if isinstance(obj, str) else repr(obj)
    return s if len(s) <= n else s[:n] + "...(%d chars)" % len(s)


# --------------------------------------------------------------------------------------------
# Results and test running


class Suite:
    def __init__(self, name, timeout_s=540):
        global SUITE
        self.name = name
        self.timeout_s = timeout_s
        self.tests = []
        self.failures = []
        self.notes = []
        self.checks = 0
        self.current = None
        self.bin = None
        self.args = None
        self.server_args = None  # When a list, main() starts one shared server: self.srv.
        self.srv = None
        self.codes_seen = set()  # Error codes the server has produced.
        SUITE = self

    # Checks never raise: they record and return the condition, so one test can report many.
    def check(self, cond, what, detail=""):
        self.checks += 1
        if not cond:
            msg = "FAIL [%s] %s" % (self.current or self.name, what)
            if detail:
                msg += ": " + str(detail)
            print(msg, flush=True)
            self.failures.append(msg)
        return bool(cond)

    def eq(self, got, want, what):
        return self.check(got == want, what, "got %s, want %s" % (short(got), short(want)))

    def fail(self, what, detail=""):
        return self.check(False, what, detail)

    def note(self, text):
        msg = "NOTE [%s] %s" % (self.current or self.name, text)
        print(msg, flush=True)
        self.notes.append(msg)

    def test(self, fn):
        """Decorator registering a test function fn(suite)."""
        self.tests.append(fn)
        return fn

    def _run_all(self):
        for fn in self.tests:
            if self.args.only and fn.__name__ not in self.args.only:
                continue
            if self.srv is not None and not self.srv.alive():
                self.fail("the shared server is still running before %s" % fn.__name__,
                          "exit status %s" % self.srv.proc.returncode)
                self.srv.print_log()
                break
            self.run_one(fn)

    def run_one(self, fn):
        self.current = fn.__name__
        t0 = time.monotonic()
        before = len(self.failures)
        try:
            fn(self)
        except CheckError as e:
            self.fail("aborted", str(e))
        except Exception as e:  # A harness or protocol error: the test failed.
            self.fail("exception %s: %s" % (type(e).__name__, e), traceback.format_exc())
        status = "ok" if len(self.failures) == before else "FAILED"
        print("--- %s %s (%.1f s)" % (fn.__name__, status, time.monotonic() - t0), flush=True)
        self.current = None

    def main(self, extra_args=None):
        ap = argparse.ArgumentParser(description=self.name)
        ap.add_argument("--bin", default=os.path.join("build", "bin"),
                        help="directory holding volfxd")
        ap.add_argument("--only", action="append", default=[],
                        help="run only the named tests (repeatable)")
        ap.add_argument("--timeout", type=float, default=self.timeout_s,
                        help="overall time limit in seconds")
        if extra_args:
            extra_args(ap)
        self.args = ap.parse_args()
        self.bin = os.path.abspath(self.args.bin)
        _arm_alarm(self, int(self.args.timeout))
        exe = os.path.join(self.bin, "volfxd")
        if not os.access(exe, os.X_OK):
            print("FAIL [%s] no executable %s" % (self.name, exe), flush=True)
            return 1
        _shared_pocl_cache()
        t0 = time.monotonic()
        if self.server_args is None:
            self._run_all()
        else:
            try:
                with Server(self.bin, *self.server_args) as srv:
                    self.srv = srv
                    self._run_all()
                    self.current = "shared server"
            except CheckError as e:
                self.fail("shared server", str(e))
        print("=== %s: %d checks, %d failed, %d notes, %.1f s" %
              (self.name, self.checks, len(self.failures), len(self.notes),
               time.monotonic() - t0), flush=True)
        for f in self.failures:
            print("  " + f.splitlines()[0][:400], flush=True)
        return 1 if self.failures else 0


def _arm_alarm(suite, seconds):
    def on_alarm(signum, frame):
        print("FAIL [%s] overall timeout of %d s reached in %s; killing the servers" %
              (suite.name, seconds, suite.current), flush=True)
        traceback.print_stack(frame)
        for s in list(_live_servers):
            try:
                s.proc.kill()
                s.print_log()
            except Exception:
                pass
        sys.stdout.flush()
        os._exit(2)

    signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(max(1, seconds))


_pocl_dir = None


def _shared_pocl_cache():
    """One fresh PoCL kernel cache per test process (STYLE §10), shared by its servers, unless
    the caller set POCL_CACHE_DIR."""
    global _pocl_dir
    if "POCL_CACHE_DIR" in os.environ or _pocl_dir:
        return
    _pocl_dir = tempfile.mkdtemp(prefix="volfx-pocl-")
    os.environ["POCL_CACHE_DIR"] = _pocl_dir
    import atexit
    atexit.register(shutil.rmtree, _pocl_dir, True)


# --------------------------------------------------------------------------------------------
# The server under test


class Server:
    """
    `with Server(bin_dir, "--token", "x") as srv:` starts volfxd on 127.0.0.1:0 with a fresh
    data directory and waits for its `volfxd listening on HOST:PORT` line. On exit it sends
    SIGTERM (unless the process already ended) and checks the exit status is 0 and that the
    log holds no sanitizer report; a failure is recorded in the suite and the log printed.
    """

    def __init__(self, bin_dir, *args, env=None, start_timeout=120.0, stop_timeout=30.0,
                 listen="127.0.0.1:0", data_dir=None, expect_rc=0):
        self.bin_dir = bin_dir
        self.args = list(args)
        self.env = dict(os.environ)
        _lsan_suppressions(self.env)
        if env:
            self.env.update(env)
        self.start_timeout = start_timeout
        self.stop_timeout = stop_timeout
        self.listen = listen
        self.data_dir = data_dir
        self.own_data = data_dir is None
        self.expect_rc = expect_rc
        self.proc = None
        self.host = None
        self.port = None
        self.stdout_lines = []
        self.log_path = None
        self.start_s = None  # Seconds from exec to the listening line.
        self._lines = queue.Queue()
        self._conns = []
        self.popen_kw = {}  # More subprocess.Popen arguments (pass_fds, ...).

    def start(self):
        if self.data_dir is None:
            self.data_dir = tempfile.mkdtemp(prefix="volfx-data-")
        fd, self.log_path = tempfile.mkstemp(prefix="volfxd-", suffix=".log")
        self._log = os.fdopen(fd, "w+b")
        cmd = [os.path.join(self.bin_dir, "volfxd"), "--listen", self.listen,
               "--data", self.data_dir] + self.args
        self.cmd = cmd
        t0 = time.monotonic()
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=self._log, env=self.env, **self.popen_kw)
        _live_servers.append(self)
        threading.Thread(target=self._pump_stdout, daemon=True).start()
        deadline = t0 + self.start_timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.print_log()
                self.kill()
                raise CheckError("volfxd printed no 'volfxd listening on HOST:PORT' line within "
                                 "%.0f s: %s" % (self.start_timeout, " ".join(cmd)))
            try:
                line = self._lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                if self.proc.poll() is not None:
                    self.print_log()
                    raise CheckError("volfxd exited with status %s before listening: %s" %
                                     (self.proc.returncode, " ".join(cmd)))
                continue
            if line is None:
                continue
            m = LISTEN_RE.search(line)
            if m:
                self.start_s = time.monotonic() - t0
                self.host = m.group(1).strip("[]")
                self.port = int(m.group(2))
                return self

    def _pump_stdout(self):
        for raw in self.proc.stdout:
            line = raw.decode("utf-8", "replace").rstrip("\n")
            self.stdout_lines.append(line)
            self._lines.put(line)
        self._lines.put(None)

    def __enter__(self):
        # A server already started (by a helper that probed it) is not started a second time.
        if self.proc is not None and self.proc.poll() is None:
            return self
        return self.start()

    def __exit__(self, et, ev, tb):
        for c in self._conns:
            c.close()
        ok = self.stop()
        if et is not None and ok:
            # The test failed; the log may say why.
            self.print_log(tail=40)
        return False

    @property
    def pid(self):
        return self.proc.pid

    def alive(self):
        return self.proc is not None and self.proc.poll() is None

    def rss(self):
        return rss_of(self.proc.pid)

    def connect(self, timeout=DEFAULT_TIMEOUT, **kw):
        c = Conn(self.host, self.port, timeout=timeout, **kw)
        self._conns.append(c)
        return c

    def wait_exit(self, timeout):
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def kill(self):
        if self.alive():
            self.proc.kill()
            self.proc.wait()
        if self in _live_servers:
            _live_servers.remove(self)

    def stop(self):
        """Stops the server (SIGTERM unless already gone) and checks a clean exit. Returns True
        when everything was clean."""
        if self.proc is None:
            return True
        clean = True
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            rc = self.wait_exit(self.stop_timeout)
            if rc is None:
                clean = _record(False, "volfxd stops within %.0f s of SIGTERM" % self.stop_timeout,
                                "still running; killed")
                self.proc.kill()
                self.proc.wait()
        rc = self.proc.returncode
        if clean:
            if rc < 0:
                clean = _record(False, "volfxd exits cleanly",
                                "killed by signal %d (%s) - a crash" %
                                (-rc, signal.Signals(-rc).name))
            else:
                clean = _record(rc == self.expect_rc, "volfxd exit status",
                                "got %d, want %d" % (rc, self.expect_rc))
        log = self.log_text()
        marks = [m for m in SANITIZER_MARKS if m in log]
        if marks:
            clean = _record(False, "no sanitizer report in the server log", ", ".join(marks))
        if not clean:
            self.print_log()
        else:
            try:
                os.unlink(self.log_path)
            except OSError:
                pass
        if self in _live_servers:
            _live_servers.remove(self)
        try:
            self._log.close()
        except Exception:
            pass
        if self.own_data:
            shutil.rmtree(self.data_dir, ignore_errors=True)
        return clean

    def log_text(self):
        try:
            with open(self.log_path, "rb") as f:
                return f.read().decode("utf-8", "replace")
        except OSError:
            return ""

    def print_log(self, tail=200):
        lines = self.log_text().splitlines()
        print("----- volfxd stderr (%s), last %d of %d lines -----" %
              (self.log_path, min(tail, len(lines)), len(lines)), flush=True)
        for ln in lines[-tail:]:
            print("  | " + ln)
        print("----- end of volfxd stderr -----", flush=True)


# PoCL compiles kernels with LLVM and clang, which keep allocations alive on purpose; their
# leaks are not volfxd's. An AddressSanitizer build of volfxd is otherwise held to no leaks.
LSAN_SUPPRESS = ("libpocl", "libLLVM", "libclang", "libclang-cpp", "libOpenCL")
_lsan_file = None


def _lsan_suppressions(env):
    global _lsan_file
    if "suppressions=" in env.get("LSAN_OPTIONS", ""):
        return
    if _lsan_file is None:
        fd, _lsan_file = tempfile.mkstemp(prefix="volfx-lsan-", suffix=".supp")
        with os.fdopen(fd, "w") as f:
            f.write("".join("leak:%s\n" % m for m in LSAN_SUPPRESS))
        import atexit
        atexit.register(os.unlink, _lsan_file)
    opts = env.get("LSAN_OPTIONS", "")
    env["LSAN_OPTIONS"] = (opts + ":" if opts else "") + "suppressions=" + _lsan_file + \
        ":print_suppressions=0"


def _record(cond, what, detail=""):
    if SUITE is not None:
        return SUITE.check(cond, what, detail)
    if not cond:
        print("FAIL %s: %s" % (what, detail), flush=True)
    return cond


def rss_of(pid):
    """Resident set size in bytes from /proc/PID/status (VmRSS), or None."""
    try:
        with open("/proc/%d/status" % pid) as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def volfxd_help(bin_dir):
    try:
        p = subprocess.run([os.path.join(bin_dir, "volfxd"), "--help"], capture_output=True,
                           timeout=20)
        return (p.stdout + p.stderr).decode("utf-8", "replace")
    except Exception:
        return ""


# --------------------------------------------------------------------------------------------
# The raw client


class Closed(Exception):
    """The server closed the connection (EOF or reset)."""


class Conn:
    """
    A raw client: every message is a line; attachments are read by their announced size.
    Notifications (`frames`) that arrive while call() waits for its response are kept in
    `notifications` as (message, attachment bytes).
    """

    def __init__(self, host, port, timeout=DEFAULT_TIMEOUT, rcvbuf=None, connect=True):
        self.host, self.port = host, port
        self.timeout = timeout
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.settimeout(timeout)
        if connect:
            self.sock.connect((host, port))
        self.buf = bytearray()
        self.next_id = 1
        self.notifications = []
        self.closed = False

    def close(self):
        if not self.closed:
            self.closed = True
            try:
                self.sock.close()
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *a):
        self.close()

    # -- sending
    def send_raw(self, data):
        if isinstance(data, str):
            data = data.encode("utf-8")
        self.sock.sendall(data)

    def send(self, obj):
        """Sends one JSON text followed by '\\n'."""
        self.send_raw(dumps(obj).encode("utf-8") + b"\n")

    def request(self, method, params=None, id=None):
        """Builds a request dict; id=None picks the next number."""
        if id is None:
            id = self.next_id
            self.next_id += 1
        msg = {"jsonrpc": "2.0", "method": method, "id": id}
        if params is not None:
            msg["params"] = params
        return msg

    # -- receiving
    def _fill(self, timeout):
        self.sock.settimeout(timeout)
        try:
            chunk = self.sock.recv(1 << 20)
        except socket.timeout:
            raise
        except (ConnectionResetError, BrokenPipeError) as e:
            raise Closed("connection reset: %s" % e)
        if not chunk:
            raise Closed("connection closed by the server")
        self.buf += chunk

    def read_line(self, timeout=None):
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        start = 0
        while True:
            i = self.buf.find(b"\n", start)
            if i >= 0:
                line = bytes(self.buf[:i])
                del self.buf[:i + 1]
                if line.endswith(b"\r"):
                    line = line[:-1]
                return line
            start = len(self.buf)
            left = deadline - time.monotonic()
            if left <= 0:
                raise socket.timeout("no complete line within %.1f s (%d bytes buffered)" %
                                     (timeout, len(self.buf)))
            self._fill(left)

    def read_exact(self, n, timeout=None):
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while len(self.buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise socket.timeout("attachment: %d of %d bytes within %.1f s" %
                                     (len(self.buf), n, timeout))
            self._fill(left)
        data = bytes(self.buf[:n])
        del self.buf[:n]
        return data

    def _attachment_of(self, msg):
        """The size of the raw bytes following 'msg' (a response or notification), or None."""
        if not isinstance(msg, dict):
            return None
        body = msg.get("result") if "result" in msg else msg.get("params")
        if not isinstance(body, dict):
            return None
        att = body.get("attachment")
        if not isinstance(att, dict) or "data" in body:
            return None
        n = att.get("bytes")
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            raise CheckError("attachment.bytes is not a non-negative integer: %s" % short(msg))
        return n

    def recv(self, timeout=None):
        """
        Reads one message and its attachments. Returns (msg, att): for an object, att is the
        attachment bytes or None; for a batch array, a list of the attachments of the
        responses carrying one, in order.
        """
        line = self.read_line(timeout)
        try:
            text = line.decode("utf-8")
        except UnicodeDecodeError as e:
            raise CheckError("server sent invalid UTF-8: %s (%s)" % (short(line), e))
        try:
            msg = loads(text)
        except ValueError as e:
            raise CheckError("server sent a line that is not JSON: %s (%s)" % (short(text), e))
        if isinstance(msg, list):
            atts = []
            for item in msg:
                n = self._attachment_of(item)
                if n is not None:
                    atts.append(self.read_exact(n, timeout))
            return msg, atts
        n = self._attachment_of(msg)
        return msg, (self.read_exact(n, timeout) if n is not None else None)

    def recv_response(self, timeout=None):
        """Reads until a message that is not a notification; notifications are kept."""
        while True:
            msg, att = self.recv(timeout)
            if isinstance(msg, dict) and "method" in msg and "id" not in msg:
                self.notifications.append((msg, att))
                continue
            return msg, att

    def recv_notification(self, timeout=None):
        if self.notifications:
            return self.notifications.pop(0)
        msg, att = self.recv(timeout)
        if not (isinstance(msg, dict) and "method" in msg and "id" not in msg):
            raise CheckError("expected a notification, got %s" % short(msg))
        return msg, att

    def call(self, method, params=None, id=None, timeout=None):
        """Sends one request and returns (full response dict, attachment bytes or None)."""
        req = self.request(method, params, id)
        self.send(req)
        resp, att = self.recv_response(timeout)
        if not isinstance(resp, dict):
            raise CheckError("%s: response is not an object: %s" % (method, short(resp)))
        if resp.get("id") != req["id"]:
            if "error" in resp and resp.get("id") is None:
                # An error that lost the id: still this request's answer (answers are in order).
                _record(False, "%s: the error response echoes id %r" % (method, req["id"]),
                        short(resp))
                return resp, att
            raise CheckError("%s: response id %s for request id %s: %s" %
                             (method, short(resp.get("id")), req["id"], short(resp)))
        return resp, att

    def ok(self, method, params=None, timeout=None):
        """Calls and returns (result, attachment); a JSON-RPC error is a CheckError."""
        resp, att = self.call(method, params, timeout=timeout)
        check_envelope(resp)
        if "error" in resp or "result" not in resp:
            raise CheckError("%s %s failed: %s" % (method, short(dumps(params), 200),
                                                   short(resp)))
        return resp["result"], att

    def err(self, method, params=None, timeout=None):
        """Calls and returns the error object; a result is a CheckError."""
        resp, att = self.call(method, params, timeout=timeout)
        check_envelope(resp)
        if "error" not in resp:
            raise CheckError("%s %s succeeded but should fail: %s" %
                             (method, short(dumps(params), 200), short(resp)))
        return resp["error"]

    def expect_eof(self, timeout=5.0):
        """True when the server closes the connection within 'timeout' (after any bytes)."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            try:
                self._fill(left)
            except Closed:
                return True
            except socket.timeout:
                return False

    def quiet(self, wait=0.3):
        """True when nothing arrives within 'wait' seconds."""
        if self.buf:
            return False
        try:
            self._fill(wait)
        except socket.timeout:
            return True
        except Closed:
            return True
        return False


def check_envelope(resp):
    """Checks the JSON-RPC 2.0 response envelope; records failures."""
    s = SUITE
    if s is None:
        return
    s.check(isinstance(resp, dict), "response is an object", short(resp))
    if not isinstance(resp, dict):
        return
    s.check(resp.get("jsonrpc") == "2.0", "response has jsonrpc 2.0", short(resp))
    s.check("id" in resp, "response has an id member", short(resp))
    s.check(("result" in resp) != ("error" in resp), "response has exactly one of result/error",
            short(resp))
    if "error" in resp:
        e = resp["error"]
        if isinstance(e, dict) and isinstance(e.get("code"), int):
            s.codes_seen.add(e["code"])
        s.check(isinstance(e, dict) and isinstance(e.get("code"), int) and
                isinstance(e.get("message"), str) and e.get("message") != "",
                "error has an integer code and a non-empty message", short(resp))


def config_file(cfg):
    """A fresh volfxd.json holding 'cfg' (a dict) for `--config`; returns its path."""
    path = os.path.join(tempfile.mkdtemp(prefix="volfx-cfg-"), "volfxd.json")
    with open(path, "w") as f:
        f.write(dumps(cfg))
    return path


def served_meanwhile(suite, other, busy, what, n=5, method="scene.list"):
    """After client 'busy' has sent a request that takes long, checks that client 'other' is
    answered meanwhile: of 'n' requests sent one at a time on 'other', some must be answered
    before any of busy's answer has arrived. Returns how many were."""
    time.sleep(0.02)  # Let the server take up busy's request first.
    served = 0
    for _ in range(n):
        other.ok(method)
        if not select.select([busy.sock], [], [], 0)[0]:
            served += 1
    suite.check(served > 0, what, "%d of %d answers came before the busy client's" % (served, n))
    return served


def batch(suite, conn, requests, timeout=120):
    """Sends 'requests' as one batch on 'conn' and returns the answers, checked to be one array
    answering them in order; None (a failed check) when they are not."""
    conn.send(requests)
    resp, _ = conn.recv_response(timeout=timeout)
    ok = isinstance(resp, list) and [r.get("id") for r in resp] == [q["id"] for q in requests]
    suite.check(ok, "one array answers the batch, in order", short(resp))
    return resp if ok else None


def expect_error(suite, conn, method, params, code, path=None, what=None, raw=None):
    """
    Sends a request (or 'raw' bytes, one line) and checks its error code and data.path.
    Returns the full response.
    """
    what = what or "%s %s" % (method, short(dumps(params) if params is not None else "", 120))
    try:
        if raw is not None:
            conn.send_raw(raw)
            resp, _ = conn.recv_response()
        else:
            resp, _ = conn.call(method, params)
    except socket.timeout:
        raise CheckError("%s: no answer within %.0f s" % (what, conn.timeout))
    except Closed as e:
        raise CheckError("%s: %s" % (what, e))
    check_envelope(resp)
    if not isinstance(resp, dict):
        suite.fail("%s -> one error object" % what, "got %s" % short(resp))
        return {"unexpected": resp}
    codes = code if isinstance(code, tuple) else (code,)
    cname = "/".join(str(x) for x in codes)
    err = resp.get("error") if isinstance(resp, dict) else None
    if not suite.check(isinstance(err, dict), "%s -> error %s" % (what, cname),
                       "got %s" % short(resp)):
        return resp
    suite.check(err.get("code") in codes, "%s -> error %s" % (what, cname),
                "got %s" % short(resp))
    if path is not None:
        data = err.get("data")
        got = data.get("path") if isinstance(data, dict) else None
        suite.check(got == path, "%s -> data.path %r" % (what, path), "got %s" % short(resp))
    return resp


# --------------------------------------------------------------------------------------------
# Image helpers


def png_info(data):
    """(width, height, bit_depth, color_type) from a PNG's IHDR, or None if not a PNG."""
    if len(data) < 33 or data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        return None
    w, h, depth, ctype = struct.unpack(">IIBB", data[16:26])
    return w, h, depth, ctype


def png_decode_rgba8(data):
    """Decodes an 8-bit RGBA non-interlaced PNG into raw RGBA bytes (rows top to bottom), checking
    every chunk's CRC. Raises ValueError on anything else."""
    if data[:8] != PNG_SIGNATURE:
        raise ValueError("no PNG signature")
    pos, idat, ihdr, seen_end = 8, bytearray(), None, False
    while pos + 8 <= len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        crc = struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])[0]
        if zlib.crc32(kind + body) & 0xffffffff != crc:
            raise ValueError("bad CRC in chunk %r" % kind)
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            seen_end = True
            break
        pos += 12 + n
    if ihdr is None or not seen_end:
        raise ValueError("missing IHDR or IEND")
    w, h, depth, ctype, comp, filt, interlace = ihdr
    if depth != 8 or ctype != 6 or interlace != 0:
        raise ValueError("not 8-bit RGBA non-interlaced: depth %d type %d interlace %d" %
                         (depth, ctype, interlace))
    raw = zlib.decompress(bytes(idat))
    stride = 4 * w
    if len(raw) != h * (stride + 1):
        raise ValueError("decompressed %d bytes, want %d" % (len(raw), h * (stride + 1)))
    out = bytearray(h * stride)
    prev = bytearray(stride)
    for y in range(h):
        ft = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        if ft == 0:
            pass
        elif ft == 1:
            for i in range(4, stride):
                line[i] = (line[i] + line[i - 4]) & 255
        elif ft == 2:
            for i in range(stride):
                line[i] = (line[i] + prev[i]) & 255
        elif ft == 3:
            for i in range(stride):
                left = line[i - 4] if i >= 4 else 0
                line[i] = (line[i] + ((left + prev[i]) >> 1)) & 255
        elif ft == 4:
            for i in range(stride):
                a = line[i - 4] if i >= 4 else 0
                b = prev[i]
                c = prev[i - 4] if i >= 4 else 0
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pr = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                line[i] = (line[i] + pr) & 255
        else:
            raise ValueError("bad filter type %d in row %d" % (ft, y))
        out[y * stride:(y + 1) * stride] = line
        prev = line
    return w, h, bytes(out)


def floats(data):
    """Little-endian float32 array from bytes."""
    n = len(data) // 4
    return struct.unpack("<%df" % n, data[:4 * n])


def b64decode(s):
    return base64.b64decode(s, validate=True)
