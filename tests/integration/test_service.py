#!/usr/bin/env python3
"""
volfxd as a systemd service (deploy/volfxd.service), checked without systemd as PID 1:
readiness, status and stop sent to a NOTIFY_SOCKET the test binds (READY=1 only once the
socket accepts), SIGHUP re-reading the log level and never stopping the server (also while the
kernels compile, and with a broken config file), journald priorities on each line when stderr
is the stream JOURNAL_STREAM names and the plain format otherwise, the unit file passing
`systemd-analyze verify` with an exposure score of at most 3.0, the sysusers.d file creating
the volfx user, and volfxd with the shipped example config rendering a frame, compiling its
kernels into an empty cache, under the unit's file-system and privilege settings rebuilt with
unshare and setpriv (tests/integration/service_sandbox.sh). Where systemd can be booted in
private namespaces (root, cgroup2, overlayfs: tests/integration/service_systemd.sh), the unit
itself runs there too: active only once ready, every sandboxing setting applied, a reload with a
broken config file logged at priority err, a clean stop. The checks that need systemd-analyze,
systemd-sysusers, root or a bootable systemd are skipped (with a note) where those are missing.

    python3 tests/integration/test_service.py --bin build/bin
"""

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mock  # noqa: E402

suite = mock.Suite("test_service", timeout_s=400)
T = suite.test

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
UNIT = os.path.join(ROOT, "deploy", "volfxd.service")
SYSUSERS = os.path.join(ROOT, "deploy", "volfx.sysusers.conf")
EXAMPLE_CONFIG = os.path.join(ROOT, "deploy", "volfxd.example.json")
SANDBOX = os.path.join(ROOT, "tests", "integration", "service_sandbox.sh")
SYSTEMD_BOOT = os.path.join(ROOT, "tests", "integration", "service_systemd.sh")
MAX_EXPOSURE = 3.0


class Notify:
    """A Unix datagram socket standing in for systemd's notification socket."""

    def __init__(self):
        self.dir = tempfile.mkdtemp(prefix="volfx-notify-")
        self.path = os.path.join(self.dir, "notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.messages = []

    def next(self, timeout):
        """The next message as a dict of its assignments, or None after 'timeout' seconds."""
        self.sock.settimeout(timeout)
        try:
            data = self.sock.recv(65536)
        except socket.timeout:
            return None
        msg = dict(line.split("=", 1) for line in data.decode().split("\n") if "=" in line)
        self.messages.append(msg)
        return msg

    def wait_for(self, key, timeout):
        """Reads messages until one sets 'key'; returns it, or None."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            msg = self.next(left)
            if msg is None:
                return None
            if key in msg:
                return msg

    def close(self):
        self.sock.close()
        shutil.rmtree(self.dir, ignore_errors=True)


class Daemon:
    """volfxd started directly, with stderr in a file (optionally named by JOURNAL_STREAM)."""

    def __init__(self, s, args, env=None, journal=False):
        self.dir = tempfile.mkdtemp(prefix="volfx-service-")
        self.err_path = os.path.join(self.dir, "stderr")
        self.err = open(self.err_path, "w+b")
        e = dict(os.environ)
        e.pop("VOLFX_TOKEN", None)
        e.pop("NOTIFY_SOCKET", None)
        e.pop("JOURNAL_STREAM", None)
        mock._lsan_suppressions(e)
        st = os.fstat(self.err.fileno())
        if journal:
            e["JOURNAL_STREAM"] = "%d:%d" % (st.st_dev, st.st_ino)
        elif journal is None:  # Inherited from a parent whose stderr was the journal.
            e["JOURNAL_STREAM"] = "%d:%d" % (st.st_dev, st.st_ino + 1)
        e.update(env or {})
        self.proc = subprocess.Popen([os.path.join(s.bin, "volfxd")] + list(args),
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=self.err, env=e)

    def stderr(self):
        with open(self.err_path, "rb") as f:
            return f.read().decode("utf-8", "replace")

    def wait(self, timeout=60):
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return None

    def close(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()
        self.err.close()
        shutil.rmtree(self.dir, ignore_errors=True)


def unix_info(path, timeout=10):
    """Sends server.info over the Unix socket at 'path'; returns the parsed answer."""
    c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    c.settimeout(timeout)
    try:
        c.connect(path)
        c.sendall(b'{"jsonrpc":"2.0","id":1,"method":"server.info"}\n')
        buf = b""
        while not buf.endswith(b"\n"):
            chunk = c.recv(65536)
            if not chunk:
                break
            buf += chunk
        return json.loads(buf)
    finally:
        c.close()


def write_config(path, cfg):
    with open(path + ".new", "w") as f:
        json.dump(cfg, f)
    os.replace(path + ".new", path)


@T
def readiness(s):
    n = Notify()
    d = tempfile.mkdtemp(prefix="volfx-ready-")
    sock = os.path.join(d, "volfxd.sock")
    v = Daemon(s, ["--listen", "none", "--unix", sock, "--data", d],
               env={"NOTIFY_SOCKET": n.path})
    try:
        first = n.next(60)
        s.check(first is not None and first.get("STATUS", "").startswith("starting"),
                "a STATUS= line while the kernels compile", first)
        ready = n.wait_for("READY", 120)
        if not s.check(ready is not None and ready["READY"] == "1", "READY=1 is sent",
                       n.messages):
            return
        # Ready means serving: the socket answers at once.
        info = unix_info(sock)
        s.eq(info.get("result", {}).get("name"), "volfxd", "serving when READY=1 arrives")
        s.check("serving on unix:" + sock in ready.get("STATUS", ""),
                "READY=1 comes with a STATUS= naming the address", ready)
        v.proc.send_signal(signal.SIGTERM)
        stop = n.wait_for("STOPPING", 30)
        s.check(stop is not None and stop["STOPPING"] == "1", "STOPPING=1 on SIGTERM",
                n.messages)
        s.eq(v.wait(), 0, "exit status after SIGTERM")
    finally:
        v.close()
        n.close()
        shutil.rmtree(d, ignore_errors=True)

    # server.shutdown stops it too, and says so.
    n = Notify()
    with mock.Server(s.bin, env={"NOTIFY_SOCKET": n.path}) as srv:
        s.check(n.wait_for("READY", 30) is not None, "READY=1 (TCP)", n.messages)
        srv.connect().ok("server.shutdown", {})
        s.check(n.wait_for("STOPPING", 30) is not None, "STOPPING=1 after server.shutdown",
                n.messages)
        s.eq(srv.wait_exit(30), 0, "exit status after server.shutdown")
    n.close()

    # Without NOTIFY_SOCKET (or with one nobody listens on) nothing changes.
    gone = os.path.join(tempfile.mkdtemp(prefix="volfx-gone-"), "notify")
    for env in ({}, {"NOTIFY_SOCKET": gone}):
        with mock.Server(s.bin, env=env) as srv:
            s.eq(srv.connect().ok("server.info", {})[0]["name"], "volfxd",
                 "serves with NOTIFY_SOCKET %r" % env.get("NOTIFY_SOCKET"))
    shutil.rmtree(os.path.dirname(gone), ignore_errors=True)


@T
def sighup(s):
    cfg = mock.config_file({"log-level": "info"})
    n = Notify()
    v = Daemon(s, ["--listen", "127.0.0.1:0", "--config", cfg, "--data", os.path.dirname(cfg)],
               env={"NOTIFY_SOCKET": n.path})
    try:
        # A SIGHUP while the kernels compile (after the first STATUS=) is ignored.
        s.check(n.next(60) is not None, "a STATUS= line at start", n.messages)
        v.proc.send_signal(signal.SIGHUP)
        if not s.check(n.wait_for("READY", 120) is not None,
                       "READY=1 after a SIGHUP during the start", v.stderr()[-2000:]):
            return
        line = v.proc.stdout.readline().decode()
        m = mock.LISTEN_RE.search(line)
        if not s.check(m is not None, "the listening line", line):
            return
        c = mock.Conn("127.0.0.1", int(m.group(2)))

        write_config(cfg, {"log-level": "debug"})
        v.proc.send_signal(signal.SIGHUP)
        msg = n.wait_for("RELOADING", 10)
        s.check(msg is not None and "MONOTONIC_USEC" in msg, "RELOADING=1 with MONOTONIC_USEC",
                n.messages)
        msg = n.wait_for("READY", 10)
        s.check(msg is not None and msg.get("STATUS", "").startswith("serving on"),
                "READY=1 ends the reload, with the serving STATUS=", msg)
        s.check("log level debug (was info)" in v.stderr(), "SIGHUP took the new log level",
                v.stderr()[-1000:])
        s.eq(c.ok("server.info", {})[0]["name"], "volfxd", "serving after SIGHUP")

        # A file that no longer parses keeps the level; the server keeps running.
        with open(cfg, "w") as f:
            f.write("{ not json")
        v.proc.send_signal(signal.SIGHUP)
        n.wait_for("READY", 10)
        s.check("log level stays debug" in v.stderr(), "a broken config file keeps the level",
                v.stderr()[-1000:])
        write_config(cfg, {"log-level": "warn"})
        for _ in range(20):
            v.proc.send_signal(signal.SIGHUP)
        for _ in range(20):
            if "log level warn" in v.stderr():
                break
            time.sleep(0.1)
        s.check("log level warn (was debug)" in v.stderr(), "a repaired file is read again",
                v.stderr()[-1000:])
        s.eq(c.ok("server.info", {})[0]["name"], "volfxd", "serving after 22 SIGHUPs")
        s.check(v.proc.poll() is None, "volfxd runs on after SIGHUP", v.proc.returncode)
        c.close()
        v.proc.send_signal(signal.SIGTERM)
        s.eq(v.wait(), 0, "exit status after SIGTERM")
    finally:
        v.close()
        n.close()

    v = Daemon(s, ["--listen", "127.0.0.1:0", "--config", cfg, "--log-level", "error",
                   "--data", os.path.dirname(cfg)])
    try:
        line = v.proc.stdout.readline().decode()
        s.check(mock.LISTEN_RE.search(line), "started with --log-level error", v.stderr())
        write_config(cfg, {"log-level": "debug"})
        v.proc.send_signal(signal.SIGHUP)
        for _ in range(50):
            if "SIGHUP" in v.stderr():
                break
            time.sleep(0.1)
        s.check("log level error (was error)" in v.stderr(),
                "--log-level on the command line wins over the file on SIGHUP", v.stderr())
        v.proc.send_signal(signal.SIGTERM)
        s.eq(v.wait(), 0, "exit status after SIGTERM")
    finally:
        v.close()
        shutil.rmtree(os.path.dirname(cfg), ignore_errors=True)


@T
def journal_priorities(s):
    # stderr is the journal's stream: every line starts with its priority, no timestamp.
    v = Daemon(s, ["--listen", "127.0.0.1:0", "--scene", "no-such-preset"], journal=True)
    try:
        s.eq(v.wait(), 1, "exit status with a missing main scene")
        lines = v.stderr().splitlines()
        s.check(lines and all(re.match(r"<[0-7]>", ln) for ln in lines),
                "every line carries a priority", lines[:5])
        s.check(any(ln.startswith("<3>error [scene]") for ln in lines),
                "the error is priority 3 (SD_ERR)", lines)
        s.check(any(ln.startswith("<6>info ") for ln in lines), "info lines are priority 6",
                lines)
        s.check(not any(re.search(r"\d{4}-\d\d-\d\dT", ln) for ln in lines),
                "no timestamps: the journal adds its own", lines[:3])
    finally:
        v.close()

    # A bad configuration leaves an error-priority line for `journalctl -p err`.
    v = Daemon(s, ["--listen", "nohostport"], journal=True)
    try:
        s.eq(v.wait(), 2, "exit status for a bad option")
        s.check("<3>error [config]" in v.stderr(), "a bad configuration logs at priority 3",
                v.stderr())
    finally:
        v.close()

    # JOURNAL_STREAM naming another stream (inherited, stderr redirected): the plain format.
    for journal in (None, False):
        v = Daemon(s, ["--listen", "127.0.0.1:0", "--scene", "no-such-preset"],
                   journal=journal)
        try:
            s.eq(v.wait(), 1, "exit status with a missing main scene")
            lines = v.stderr().splitlines()
            s.check(lines and all(re.match(r"\d{4}-\d\d-\d\dT[\d:.]+Z (info |error) \[", ln)
                                  for ln in lines),
                    "plain timestamped lines when stderr is not the journal (%s)" %
                    ("another stream" if journal is None else "no JOURNAL_STREAM"), lines[:3])
        finally:
            v.close()


def unit_for(s, d):
    """A copy of the unit in 'd' whose ExecStart= names the volfxd under test (verify wants an
    executable)."""
    with open(UNIT) as f:
        text = f.read()
    path = os.path.join(d, "volfxd.service")
    with open(path, "w") as f:
        f.write(text.replace("/usr/local/bin/volfxd", os.path.join(s.bin, "volfxd")))
    return path


@T
def unit_file(s):
    with open(UNIT) as f:
        text = f.read()
    for want in ("Type=notify", "ExecReload=/bin/kill -HUP $MAINPID", "RuntimeDirectory=volfx",
                 "StateDirectory=volfx", "CacheDirectory=volfx", "User=volfx",
                 "POCL_CACHE_DIR=%C/volfx/pocl"):
        s.check(want in text, "the unit sets %s" % want)
    with open(EXAMPLE_CONFIG) as f:
        cfg = json.load(f)
    s.check(cfg["unix"].startswith("/run/volfx/") and cfg["data"] == "/var/lib/volfx",
            "the example config's directories are the unit's", cfg)

    analyze = shutil.which("systemd-analyze")
    if not analyze:
        s.note("skipped: no systemd-analyze (Debian package systemd)")
        return
    d = tempfile.mkdtemp(prefix="volfx-unit-")
    try:
        path = unit_for(s, d)
        p = subprocess.run([analyze, "verify", path], capture_output=True, text=True,
                           timeout=60, cwd=d)
        s.check(p.returncode == 0 and not (p.stdout + p.stderr).strip(),
                "systemd-analyze verify passes without a warning", p.stdout + p.stderr)
        p = subprocess.run([analyze, "security", "--offline=true", path], capture_output=True,
                           text=True, timeout=60, cwd=d)
        m = re.search(r"Overall exposure level for volfxd\.service: ([\d.]+)", p.stdout)
        if p.returncode != 0 and not m:
            s.note("skipped the exposure score: this systemd-analyze has no offline security "
                   "check: " + p.stderr.strip()[:200])
        elif s.check(m, "systemd-analyze security prints a score", p.stdout[-500:]):
            s.check(float(m.group(1)) <= MAX_EXPOSURE,
                    "exposure %s is at most %.1f" % (m.group(1), MAX_EXPOSURE),
                    "\n".join(ln for ln in p.stdout.splitlines() if "\u2717" in ln))
    finally:
        shutil.rmtree(d, ignore_errors=True)

    sysusers = shutil.which("systemd-sysusers")
    if not sysusers:
        s.note("skipped the sysusers.d check: no systemd-sysusers")
        return
    root = tempfile.mkdtemp(prefix="volfx-sysroot-")
    try:
        os.makedirs(os.path.join(root, "etc"))
        p = subprocess.run([sysusers, "--root", root, SYSUSERS], capture_output=True, text=True,
                           timeout=60)
        s.eq(p.returncode, 0, "systemd-sysusers takes deploy/volfx.sysusers.conf")
        with open(os.path.join(root, "etc", "passwd")) as f:
            users = [ln.split(":") for ln in f.read().splitlines()]
        with open(os.path.join(root, "etc", "group")) as f:
            groups = [ln.split(":")[0] for ln in f.read().splitlines()]
        volfx = [u for u in users if u[0] == "volfx"]
        s.check(volfx and volfx[0][5] == "/var/lib/volfx" and "volfx" in groups,
                "the volfx user (home /var/lib/volfx) and group are created", users)
    finally:
        shutil.rmtree(root, ignore_errors=True)


def sandbox_usable():
    """Why the sandbox cannot run here, or None."""
    if os.geteuid() != 0:
        return "not root"
    for tool in ("unshare", "setpriv"):
        if not shutil.which(tool):
            return "no %s" % tool
    p = subprocess.run(["unshare", "--mount", "--pid", "--fork", "--propagation", "private",
                        "sh", "-c", "mount -t tmpfs tmpfs /mnt"], capture_output=True,
                       timeout=30)
    if p.returncode != 0:
        return "unshare cannot make a mount namespace: %s" % p.stderr.decode().strip()
    return None


def child_pid(pid, comm, timeout=30):
    """The pid of the child of 'pid' that runs the program named 'comm' (the process unshare
    --fork started, once it has exec'd), or None."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open("/proc/%d/task/%d/children" % (pid, pid)) as f:
                kids = [int(k) for k in f.read().split()]
        except OSError:
            return None
        for k in kids:
            try:
                with open("/proc/%d/comm" % k) as f:
                    if f.read().strip() == comm:
                        return k
            except OSError:
                pass
        time.sleep(0.05)
    return None


@T
def hardened(s):
    why = sandbox_usable()
    if why:
        s.note("skipped the sandboxed run: %s" % why)
        return
    env = dict(os.environ)
    mock._lsan_suppressions(env)
    # The example config as shipped; only the TCP port differs, so that tests never collide.
    t0 = time.monotonic()
    p = subprocess.Popen(["sh", SANDBOX, os.path.join(s.bin, "volfxd"), EXAMPLE_CONFIG,
                          os.path.join(ROOT, "scenes"), "--listen", "127.0.0.1:0"],
                         stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=env)
    try:
        line = p.stdout.readline().decode()
        m = mock.LISTEN_RE.search(line)
        if not m:
            p.kill()
            p.wait()
            s.fail("volfxd serves under the unit's restrictions",
                   "status %s: %s" % (p.returncode, p.stderr.read().decode("utf-8", "replace")))
            return
        s.note("started in %.1f s, compiling every kernel" % (time.monotonic() - t0))
        pid = child_pid(p.pid, "volfxd")
        if not s.check(pid is not None, "volfxd's pid under unshare"):
            return
        root = "/proc/%d/root" % pid
        cache = os.path.join(root, "var/cache/volfx/pocl")
        s.check(os.path.isdir(cache) and os.listdir(cache),
                "PoCL compiled into the empty cache (CacheDirectory=)",
                os.listdir(cache) if os.path.isdir(cache) else "no " + cache)
        info = unix_info(os.path.join(root, "run/volfx/volfxd.sock"))
        s.eq(info.get("result", {}).get("name"), "volfxd",
             "the Unix socket in /run/volfx (RuntimeDirectory=) answers")
        c = mock.Conn("127.0.0.1", int(m.group(2)), timeout=120)
        res, png = c.ok("render", {"width": 96, "height": 64})
        s.check(png and png.startswith(mock.PNG_SIGNATURE) and
                mock.png_info(png)[:2] == (96, 64), "a frame renders", res)
        c.ok("scene.save", {"file": "sandboxed.snap"})
        snap = os.path.join(root, "var/lib/volfx/sandboxed.snap")
        s.check(os.path.isfile(snap) and os.stat(snap).st_uid == 65534,
                "scene.save writes the state directory as the service user")
        os.kill(pid, signal.SIGHUP)
        s.eq(c.ok("server.info", {})[0]["name"], "volfxd", "serving after SIGHUP")
        c.close()
        os.kill(pid, signal.SIGTERM)
        rc = p.wait(60)
        err = p.stderr.read().decode("utf-8", "replace")
        s.eq(rc, 0, "exit status after SIGTERM")
        marks = [mk for mk in mock.SANITIZER_MARKS if mk in err]
        s.check(not marks, "no sanitizer report", err[-3000:])
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        p.stdout.close()
        p.stderr.close()


def systemd_usable():
    """Why systemd cannot be booted in namespaces here, or None."""
    if os.geteuid() != 0:
        return "not root"
    if not os.access("/lib/systemd/systemd", os.X_OK):
        return "no /lib/systemd/systemd (Debian package systemd)"
    for tool in ("unshare", "nsenter", "systemd-sysusers"):
        if not shutil.which(tool):
            return "no %s" % tool
    return sandbox_usable()


def sanitized(path):
    """True when the executable at 'path' was built with AddressSanitizer."""
    with open(path, "rb") as f:
        return b"__asan_init" in f.read()


def free_port():
    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        return so.getsockname()[1]


def remove_cgroup(path):
    """Removes the cgroup tree at 'path' once its processes are gone (a few seconds at most)."""
    for _ in range(50):
        for d, _, _ in sorted(os.walk(path), key=lambda w: -w[0].count("/")):
            try:
                os.rmdir(d)
            except OSError:
                pass
        if not os.path.exists(path):
            return
        time.sleep(0.1)


@T
def under_systemd(s):
    """The unit itself, under systemd booted in private namespaces, where that is possible."""
    why = systemd_usable()
    if why:
        s.note("skipped the run under systemd: %s" % why)
        return
    work = tempfile.mkdtemp(prefix="volfx-systemd-")
    volfxd = os.path.join(s.bin, "volfxd")
    port = free_port()
    with open(EXAMPLE_CONFIG) as f:
        cfg = json.load(f)
    cfg["listen"] = "127.0.0.1:%d" % port
    cfg_path = os.path.join(work, "volfxd.json")
    with open(cfg_path, "w") as f:
        json.dump(cfg, f)
    args = ["sh", SYSTEMD_BOOT, os.path.join(work, "root"), volfxd, cfg_path,
            os.path.join(ROOT, "scenes")]
    os.makedirs(os.path.join(work, "root"))
    if sanitized(volfxd):
        # The system call filter refuses ptrace, which LeakSanitizer's exit check needs.
        dropin = os.path.join(work, "test.conf")
        with open(dropin, "w") as f:
            f.write("[Service]\nEnvironment=ASAN_OPTIONS=detect_leaks=0:detect_odr_violation=0\n"
                    "Environment=UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1\n")
        args.append(dropin)
    log = open(os.path.join(work, "boot.log"), "w+b")
    p = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log, stderr=log)
    pid = None

    def sctl(*cmd, timeout=60):
        r = subprocess.run(["nsenter", "-t", str(pid), "-m", "-p", "--"] + list(cmd),
                           capture_output=True, text=True, timeout=timeout)
        return r.returncode, r.stdout.strip(), r.stderr.strip()

    def boot_log():
        log.seek(0)
        return log.read().decode("utf-8", "replace")[-2000:]

    try:
        pid = child_pid(p.pid, "systemd")
        state = ""
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and p.poll() is None:
            rc, state, _ = sctl("systemctl", "is-active", "volfxd")
            if state in ("active", "failed"):
                break
            time.sleep(0.25)
        if p.poll() is not None or pid is None or state == "":
            s.note("skipped the run under systemd: it did not boot here: " + boot_log())
            return
        if not s.eq(state, "active", "volfxd.service becomes active (READY=1) under systemd"):
            print(sctl("journalctl", "-u", "volfxd", "--no-pager")[1][-3000:])
            return
        _, show, _ = sctl("systemctl", "show", "-p", "StatusText", "-p", "Type", "volfxd")
        s.check("Type=notify" in show and "StatusText=serving on 127.0.0.1:%d" % port in show,
                "the unit's status line names the address", show)
        c = mock.Conn("127.0.0.1", port, timeout=120)
        res, png = c.ok("render", {"width": 96, "height": 64})
        s.check(png and mock.png_info(png)[:2] == (96, 64), "a frame renders under the unit",
                res)
        c.ok("scene.save", {"file": "under-systemd.snap"})
        root = os.path.join(work, "root")
        snap = os.path.join(root, "var", "lib", "volfx", "under-systemd.snap")
        with open(os.path.join(root, "etc", "passwd")) as f:
            uid = [int(u.split(":")[2]) for u in f.read().splitlines()
                   if u.startswith("volfx:")]
        s.check(os.path.isfile(snap) and uid and os.stat(snap).st_uid == uid[0],
                "the snapshot is in StateDirectory, owned by the volfx user")
        cache = os.path.join(root, "var", "cache", "volfx", "pocl")
        s.check(os.path.isdir(cache) and os.listdir(cache),
                "PoCL compiled into CacheDirectory under the unit's sandbox")
        info = unix_info("/proc/%d/root/run/volfx/volfxd.sock" % pid)
        s.eq(info.get("result", {}).get("name"), "volfxd", "the Unix socket in /run/volfx")

        # A reload with a broken config file: volfxd runs on, and the error has priority 3.
        sctl("sh", "-c", "echo '{ broken' >/etc/volfx/volfxd.json")
        rc, _, err = sctl("systemctl", "reload", "volfxd")
        s.eq(rc, 0, "systemctl reload volfxd")
        s.eq(c.ok("server.info", {})[0]["name"], "volfxd", "serving after the reload")
        found = ""
        for _ in range(40):
            _, found, _ = sctl("journalctl", "-u", "volfxd", "-p", "err", "--no-pager", "-q",
                               "-o", "cat")
            if "cannot read the configuration" in found:
                break
            time.sleep(0.25)
        s.check("cannot read the configuration" in found,
                "journalctl -p err shows the error logged on reload", found)
        _, infos, _ = sctl("journalctl", "-u", "volfxd", "-p", "err", "--no-pager", "-q",
                           "-o", "cat", "--grep", "ready in")
        s.check("ready in" not in infos, "info lines are not errors", infos)
        c.close()

        rc, _, err = sctl("systemctl", "stop", "volfxd", timeout=90)
        _, show, _ = sctl("systemctl", "show", "-p", "Result", "-p", "ExecMainStatus", "volfxd")
        s.check(rc == 0 and "Result=success" in show and "ExecMainStatus=0" in show,
                "systemctl stop ends volfxd cleanly", show + err)
    finally:
        if pid:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        log.close()
        cg = os.path.join(work, "root", "cgroup")
        if os.path.exists(cg):
            with open(cg) as f:
                remove_cgroup(f.read().strip())
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(suite.main())
