"""The control socket: JSON lines over a Unix stream socket in the runtime directory.

Why a Unix socket and JSON lines: the operator's ``gyrocal status`` must work without network
exposure, access is governed by file permissions (mode 0660, group gyrocal), and one JSON object per
line is easy to drive by hand (``socat - UNIX-CONNECT:/run/gyrocal/control.sock``) and to test.

Protocol: the client sends one JSON object per line, e.g. ``{"cmd": "status"}``; the server answers
each with one JSON object on one line holding at least ``"ok": true|false`` and, when false,
``"error": "one sentence"``. A connection may carry several requests.

Threads: one acceptor thread (it blocks in select() on the listening socket and a wake-up
socketpair, so stop() is immediate and nothing polls), plus one short-lived thread per connection (at
most MAX_CLIENTS). The daemon's handler is called under a lock, one request at a time, so it never
runs concurrently with itself; it must answer quickly (a snapshot of the daemon's state, no I/O wait).

Operators can always get in (the daemon runs for years next to whatever else is on the computer):
- a whole request must arrive within REQUEST_DEADLINE_S of its first byte, and a connection may sit
  idle between requests for at most CLIENT_IDLE_S: a client trickling one byte every 20 s is cut off
  at the deadline, however often it sends (the deadline is per request, not per recv);
- when MAX_CLIENTS connections are open, a new one evicts the connection that has gone longest
  without a complete request (never one whose request is being answered), so eight slow clients
  cannot lock everyone out;
- a request is at most MAX_REQUEST_BYTES long and nested at most MAX_JSON_DEPTH deep; anything else
  gets a one-line error answer (never a RecursionError in the log).

The socket's directory is checked before bind and before connect (check_socket_dir): a directory
another user could have made or can write (the classic /tmp/gyrocal-<uid> squat) is refused.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import select
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gyrocal.errors import ConfigError, GyrocalError

log = logging.getLogger(__name__)

DEFAULT_SOCKET = Path("/run/gyrocal/control.sock")
MAX_LINE_BYTES = 1 << 20  # the longest answer a client accepts (a status with many units)
MAX_REQUEST_BYTES = 64 << 10  # a push of 3 x 64 coefficients is ~5 kB; anything this long is not a request
MAX_JSON_DEPTH = 16  # a push request is 3 deep; json.loads recurses, so depth is bounded before parsing
MAX_CLIENTS = 8
CLIENT_IDLE_S = 30.0  # a connection with no request under way is dropped after this [s]
REQUEST_DEADLINE_S = 10.0  # a whole request line must arrive within this of its first byte [s]
_SUN_PATH_MAX = 107  # sockaddr_un.sun_path is 108 bytes including the terminating NUL

Handler = Callable[[dict], dict]


def default_socket_path() -> Path:
    """Where a client looks for the daemon: the same places, in the same order, as the daemon's
    `control_socket: auto` (config.py): $GYROCAL_SOCKET, $RUNTIME_DIRECTORY/control.sock (systemd),
    /run/gyrocal/control.sock, then the per-user fallback a daemon started by hand uses when
    /run/gyrocal is not writable. The first existing socket wins; /run/gyrocal/control.sock if none."""
    env = os.environ.get("GYROCAL_SOCKET")
    if env:
        return Path(env)
    candidates = []
    runtime = os.environ.get("RUNTIME_DIRECTORY", "")
    if runtime:
        candidates.append(Path(runtime.split(":")[0]) / "control.sock")
    candidates.append(DEFAULT_SOCKET)
    candidates.append(user_runtime_dir() / "control.sock")
    for path in candidates:
        with contextlib.suppress(OSError):
            if stat.S_ISSOCK(os.stat(path).st_mode):
                return path
    return candidates[0]


def user_runtime_dir() -> Path:
    """The per-user fallback directory of a daemon started by hand: $XDG_RUNTIME_DIR/gyrocal, else
    /tmp/gyrocal-<uid>/gyrocal. Both are created 0700 and must be owned by the user (check_socket_dir)."""
    base = os.environ.get("XDG_RUNTIME_DIR") or f"/tmp/gyrocal-{os.getuid()}"
    return Path(base) / "gyrocal"


def _describe(st: os.stat_result) -> str:
    return f"owner uid {st.st_uid}, mode {stat.S_IMODE(st.st_mode):04o}"


def _writable_by_others(st: os.stat_result) -> bool:
    return bool(st.st_mode & (stat.S_IWGRP | stat.S_IWOTH))


def check_socket_dir(directory: Path | str, server: bool) -> None:
    """Refuse a socket directory that another user made or can write. Raises ConfigError.

    Why: whoever controls the directory can put their own socket where the daemon's should be and
    answer the operator's ``status`` and ``push`` (or receive them). The rules, on the real path:
    - every ancestor is owned by root or by us, and if group/other can write it, it has the sticky bit
      (as /tmp does: others cannot rename or delete what is ours in it);
    - the directory itself is not group/other-writable, and
      - server side: it is owned by the daemon's uid (systemd's RuntimeDirectory= with User= does this);
      - client side: it is owned by us or root, or by another user (the daemon's, e.g. /run/gyrocal
        owned by user gyrocal) only when its parent is root's and writable by no one else, so that only
        root (systemd) can have put it there. A directory made by another user in /tmp is refused.
    """
    directory = Path(directory)
    uid = os.geteuid()
    fix = ("fix: remove it and let the daemon create it (mode 0700), or set control_socket / --socket "
           "to a directory you own")
    real = Path(os.path.realpath(directory))
    try:
        st = os.stat(real)
    except OSError as err:
        raise ConfigError(f"control socket directory {directory}: {err.strerror or err}") from err
    if not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"control socket directory {directory} is not a directory; {fix}")
    for anc in list(real.parents)[::-1]:
        ast = os.stat(anc)
        if ast.st_uid not in (0, uid):
            raise ConfigError(f"control socket directory {directory}: its parent {anc} belongs to another "
                              f"user ({_describe(ast)}); {fix}")
        if _writable_by_others(ast) and not ast.st_mode & stat.S_ISVTX:
            raise ConfigError(f"control socket directory {directory}: its parent {anc} is writable by other "
                              f"users ({_describe(ast)}); {fix}")
    if _writable_by_others(st):
        raise ConfigError(f"control socket directory {directory} is writable by other users "
                          f"({_describe(st)}); {fix}")
    if st.st_uid == uid:
        return
    if server:
        # most often the service's own directory, seen by an operator running a second daemon by hand:
        # "remove it" alone would have deleted the live service's socket (an operator's audit)
        raise ConfigError(f"control socket directory {directory} belongs to another user ({_describe(st)}, "
                          f"the daemon runs as uid {uid}): if a gyrocal service uses it (systemctl status "
                          "gyrocal), stop it first or give this daemon its own control_socket / --socket; "
                          f"otherwise {fix}")
    if st.st_uid == 0:
        return
    pst = os.stat(real.parent)
    if not (pst.st_uid == 0 and not _writable_by_others(pst)):
        raise ConfigError(f"control socket directory {directory} belongs to another user ({_describe(st)}) "
                          f"and sits in {real.parent}, where others can create directories; refusing to "
                          f"talk to it; {fix}")


def prepare_socket_dir(directory: Path) -> None:
    """Create the socket's directory (0700, parents too, as the per-user fallback needs), then check it."""
    missing = [d for d in [directory, *directory.parents] if not d.exists()][::-1]
    for d in missing:
        try:
            d.mkdir(mode=0o700)
        except FileExistsError:
            pass  # a race with another creator: check_socket_dir judges what is there
        except OSError as err:
            raise ConfigError(f"control socket: cannot create {d}: {err.strerror or err}; fix: make "
                              f"{d.parent} writable by the daemon (systemd: RuntimeDirectory=gyrocal) or "
                              "choose another control_socket path") from err
    if missing:  # said, so a mistyped control_socket path does not grow directories unnoticed
        log.info("control socket: created %s (mode 0700)", ", ".join(str(d) for d in missing))
    check_socket_dir(directory, server=True)


_STRINGS = re.compile(rb'"(?:[^"\\]|\\.)*"')
_BRACKETS = re.compile(rb"[\[\]{}]")


def json_depth(line: bytes) -> int:
    """The deepest nesting of [ and { in a JSON text (strings skipped), without recursion."""
    depth = deepest = 0
    for m in _BRACKETS.finditer(_STRINGS.sub(b'""', line)):
        if m.group() in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
        else:
            depth -= 1
    return deepest


def _json_default(obj: Any) -> Any:
    """Let handlers answer with numpy scalars/arrays or Paths without each one converting by hand."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path | bytes):
        return str(obj)
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def encode_line(obj: dict) -> bytes:
    return json.dumps(obj, default=_json_default, separators=(",", ":")).encode() + b"\n"


def _check_path_length(path: Path) -> None:
    n = len(os.fsencode(path))
    if n > _SUN_PATH_MAX:
        raise ConfigError(f"control socket path {path} is {n} bytes; a Unix socket path may have at most "
                          f"{_SUN_PATH_MAX}; fix: choose a shorter path (e.g. /run/gyrocal/control.sock)")


@dataclass(eq=False)
class _Client:
    """One connection: when it last completed a request (or connected), and whether one is being answered."""

    conn: socket.socket
    peer: str = "a client"  # who connected (peer_of), for the log line of a command that acts
    since: float = field(default_factory=time.monotonic)
    busy: bool = False
    sending: bool = False
    evicted: bool = False


class ControlServer:
    """Serve ``handler`` on a Unix stream socket at ``path``. start() and stop() are idempotent."""

    def __init__(self, path: Path | str, handler: Handler, mode: int = 0o660) -> None:
        self.path = Path(path)
        self.handler = handler
        self.mode = mode
        self._sock: socket.socket | None = None
        self._inode: tuple[int, int] | None = None
        self._acceptor: threading.Thread | None = None
        self._wake_r: socket.socket
        self._wake_w: socket.socket
        self._clients: dict[socket.socket, _Client] = {}
        self._client_threads: set[threading.Thread] = set()
        self._state_lock = threading.Lock()
        self._handler_lock = threading.Lock()
        self._stopping = threading.Event()
        self.requests = 0
        self.errors = 0
        self.dropped = 0  # connections cut for a missed deadline, an idle spell or eviction
        self._noted_at = -1e9
        self._noted_count = 0

    def __enter__(self) -> ControlServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._sock is not None

    def start(self) -> None:
        """Bind, chmod, listen and start the acceptor thread. Raises GyrocalError if the path is taken."""
        with self._state_lock:
            if self._sock is not None:
                return
            _check_path_length(self.path)
            prepare_socket_dir(self.path.parent)
            self._remove_stale()
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                sock.bind(os.fspath(self.path))
            except OSError as err:
                sock.close()
                raise ConfigError(f"control socket: cannot bind {self.path}: {err.strerror or err}; "
                                  f"fix: make {self.path.parent} writable by the daemon "
                                  "(systemd: RuntimeDirectory=gyrocal) or choose another control_socket "
                                  "(config) or --socket path") from err
            # chmod after bind: bind() creates the file with the umask applied, and the group must be able
            # to connect. The directory mode (RuntimeDirectoryMode=0750) limits who can reach it.
            os.chmod(self.path, self.mode)
            st = os.stat(self.path)
            self._inode = (st.st_dev, st.st_ino)
            sock.listen(MAX_CLIENTS)
            sock.setblocking(False)
            self._wake_r, self._wake_w = socket.socketpair()  # stop() writes here to wake the acceptor
            self._sock = sock
            self._stopping.clear()
            self._acceptor = threading.Thread(target=self._accept_loop, name="gyrocal-control", daemon=True)
            self._acceptor.start()
            log.info("control socket listening on %s (mode %o)", self.path, self.mode)

    def _remove_stale(self) -> None:
        """A socket file left by a killed daemon blocks bind(); remove it, unless someone still listens."""
        try:
            st = os.lstat(self.path)
        except FileNotFoundError:
            return
        if not stat.S_ISSOCK(st.st_mode):
            raise ConfigError(f"control socket: {self.path} exists and is not a socket; fix: remove it or "
                              "choose another control_socket (config) or --socket path")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)
        try:
            probe.connect(os.fspath(self.path))
        except (ConnectionRefusedError, FileNotFoundError):
            log.warning("control socket: removing stale socket file %s (no one listens)", self.path)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
            return
        except OSError as err:
            raise ConfigError(f"control socket: cannot probe {self.path}: {err}") from err
        finally:
            probe.close()
        raise GyrocalError(f"another gyrocal daemon is listening on {self.path}; stop it first "
                           "(systemctl stop gyrocal) or choose another control_socket (config) or --socket "
                           "path")

    def stop(self) -> None:
        """Stop accepting, close client connections, join threads and remove the socket file."""
        with self._state_lock:
            sock, self._sock = self._sock, None
            if sock is None:
                return
            self._stopping.set()
            acceptor = self._acceptor
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        if acceptor is not None:
            acceptor.join(timeout=5.0)
        sock.close()
        self._wake_r.close()
        self._wake_w.close()
        with self._state_lock:
            clients, threads = list(self._clients), list(self._client_threads)
        for c in clients:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
        for t in threads:
            t.join(timeout=2.0)
        self._unlink_own_socket()
        log.info("control socket %s closed", self.path)

    def _unlink_own_socket(self) -> None:
        """Remove the socket file only if it is still the one we bound (a successor may own the path)."""
        try:
            st = os.lstat(self.path)
            if (st.st_dev, st.st_ino) == self._inode:
                os.unlink(self.path)
        except FileNotFoundError:
            pass

    def _accept_loop(self) -> None:
        sock, wake = self._sock, self._wake_r
        while not self._stopping.is_set() and sock is not None:
            try:
                readable, _, _ = select.select([sock, wake], [], [])
                if wake in readable:
                    break
                conn, _ = sock.accept()
                conn.setblocking(True)
            except BlockingIOError:  # the client went away between select and accept
                continue
            except OSError as err:
                if self._stopping.is_set():
                    break
                # e.g. EMFILE: the daemon runs for months, so back off and keep serving, never give up
                log.error("control socket: accept failed: %s; retrying in 1 s", err)
                self._stopping.wait(1.0)
                continue
            if self._stopping.is_set():
                conn.close()
                break
            client = _Client(conn, peer_of(conn))
            with self._state_lock:
                victim = self._evict_for_new() if len(self._clients) >= MAX_CLIENTS else None
                full = len(self._clients) >= MAX_CLIENTS
                if not full:
                    self._clients[conn] = client
            if victim is not None:
                self._note(f"{MAX_CLIENTS} connections open; evicted the one idle for "
                           f"{time.monotonic() - victim.since:.0f} s")
                self._goodbye(victim)
                with contextlib.suppress(OSError):
                    victim.conn.shutdown(socket.SHUT_RDWR)  # its thread wakes from recv and exits
            if full:  # every connection is being answered right now (the handler is slow): say so
                with contextlib.suppress(OSError):
                    conn.send(encode_line({"ok": False, "error": "too many control connections; retry"}),
                              socket.MSG_DONTWAIT)
                conn.close()
                continue
            t = threading.Thread(target=self._serve_client, args=(client,), name="gyrocal-control-client",
                                 daemon=True)
            with self._state_lock:
                self._client_threads.add(t)
            t.start()

    @staticmethod
    def _goodbye(victim: _Client) -> None:
        """Tell an evicted client why, unless its thread is sending (the line would split its answer)
        or its buffer is full: the acceptor must never wait on a client (socket.send waits out the
        socket's timeout, whatever the flags, so the descriptor is written directly, once)."""
        if victim.sending:
            return
        line = encode_line({"ok": False, "error": "connection evicted: too many control connections, and "
                                                  "this one was the most idle"})
        with contextlib.suppress(OSError, ValueError):
            fd = victim.conn.fileno()
            if select.select([], [fd], [], 0)[1]:
                os.write(fd, line)

    def _note(self, what: str, level: int = logging.WARNING) -> None:
        """One line per minute at most about dropped clients, with the count since the last one, so
        that a client hammering the socket cannot flood the journal. An idle client (a monitor that
        holds its connection open) is INFO: it is not a fault (an operator's soak)."""
        with self._state_lock:
            self.dropped += 1
            self._noted_count += 1
            now = time.monotonic()
            if now - self._noted_at < 60.0:
                return
            count, self._noted_count, self._noted_at = self._noted_count, 0, now
        log.log(level, "control socket: %s (%d connection(s) dropped in the last minute)", what, count)

    def _evict_for_new(self) -> _Client | None:
        """Under _state_lock: take the connection longest without a complete request out of the table
        (one being answered is never chosen); None if every connection is being answered."""
        idle = [c for c in self._clients.values() if not c.busy]
        if not idle:
            return None
        victim = min(idle, key=lambda c: c.since)
        victim.evicted = True
        del self._clients[victim.conn]
        return victim

    def _answer(self, client: _Client, line: bytes) -> None:
        with self._state_lock:
            if client.evicted:
                return
            client.busy = True
        try:
            reply = encode_line(self.dispatch(line, client.peer))
        finally:
            with self._state_lock:
                client.busy = False
                client.since = time.monotonic()
                client.sending = not client.evicted
        if not client.sending:
            return  # evicted while its request ran: the acceptor's goodbye is the only writer
        # evictable again while the answer is sent: a client that does not read its answers cannot hold
        # a slot by filling its socket buffer (eviction's shutdown() ends this sendall at once)
        try:
            client.conn.settimeout(REQUEST_DEADLINE_S)
            client.conn.sendall(reply)
        finally:
            with self._state_lock:
                client.sending = False

    def _serve_client(self, client: _Client) -> None:
        conn = client.conn
        buf = b""
        started: float | None = None  # when the first byte of the request under way arrived
        try:
            while not self._stopping.is_set():
                nl = buf.find(b"\n")
                if nl < 0:
                    if len(buf) > MAX_REQUEST_BYTES:
                        conn.sendall(encode_line({"ok": False, "error": f"request longer than "
                                                  f"{MAX_REQUEST_BYTES} bytes; closing"}))
                        return
                    now = time.monotonic()
                    if buf.strip():
                        started = started if started is not None else now
                        left, why = started + REQUEST_DEADLINE_S - now, "request not complete within"
                        limit = REQUEST_DEADLINE_S
                    else:
                        left, why = client.since + CLIENT_IDLE_S - now, "no request within"
                        limit = CLIENT_IDLE_S
                    if left <= 0:
                        self._note(f"client dropped: {why} {limit:g} s",
                                   logging.INFO if not buf.strip() else logging.WARNING)
                        with contextlib.suppress(OSError):
                            conn.sendall(encode_line({"ok": False, "error": f"{why} {limit:g} s; closing"}))
                        return
                    conn.settimeout(left)
                    try:
                        chunk = conn.recv(65536)
                    except TimeoutError:
                        continue  # the loop sends the reason and closes
                    if not chunk:
                        if buf.strip() and not client.evicted:  # a last request without its newline
                            self._answer(client, buf)
                        return
                    buf += chunk
                    continue
                line, buf = buf[:nl], buf[nl + 1:]
                if line.strip():
                    self._answer(client, line)
                    if client.evicted:
                        return
                started = None if not buf.strip() else time.monotonic()
        except (TimeoutError, ConnectionError, OSError) as err:
            log.debug("control socket: client dropped: %s", err)
        finally:
            conn.close()
            with self._state_lock:
                if self._clients.get(conn) is client:
                    del self._clients[conn]
                self._client_threads.discard(threading.current_thread())

    def dispatch(self, line: bytes, peer: str = "a client") -> dict:
        """Parse one request line and answer it; never raises (a bad request gets an error answer).
        ``peer`` (who sent it) reaches the handler as the request's ``from``, whatever the client wrote
        there: an operator's command is logged with the user who gave it."""
        self.requests += 1
        if len(line) > MAX_REQUEST_BYTES:
            self.errors += 1
            return {"ok": False, "error": f"request longer than {MAX_REQUEST_BYTES} bytes"}
        opens = line.count(b"[") + line.count(b"{")  # an upper bound on the depth, cheap to take
        if opens > MAX_JSON_DEPTH and json_depth(line) > MAX_JSON_DEPTH:
            self.errors += 1
            return {"ok": False, "error": f"request nested deeper than {MAX_JSON_DEPTH} levels; a request is "
                                          'a flat object, e.g. {"cmd": "status"}'}
        try:
            req = json.loads(line)
        except RecursionError:  # json_depth bounds this; kept so no parse can ever take the thread down
            self.errors += 1
            return {"ok": False, "error": "request nested too deeply"}
        except (ValueError, UnicodeDecodeError) as err:
            self.errors += 1
            return {"ok": False, "error": f"bad JSON: {err}; send one JSON object per line, "
                                          'e.g. {"cmd": "status"}'}
        if not isinstance(req, dict):
            self.errors += 1
            return {"ok": False, "error": 'a request must be a JSON object, e.g. {"cmd": "status"}'}
        req["from"] = peer
        try:
            with self._handler_lock:
                reply = self.handler(req)
        except Exception as err:  # the daemon must keep serving whatever one request does
            self.errors += 1
            log.exception("control socket: handler failed on %r", req.get("cmd"))
            return {"ok": False, "error": f"{type(err).__name__}: {err}"}
        if not isinstance(reply, dict):
            self.errors += 1
            log.error("control socket: handler answered %r, not a dict", type(reply).__name__)
            return {"ok": False, "error": "internal error: the daemon's answer was not a JSON object"}
        reply.setdefault("ok", True)
        try:
            encode_line(reply)
        except (TypeError, ValueError) as err:
            self.errors += 1
            return {"ok": False, "error": f"internal error: answer not JSON serialisable: {err}"}
        return reply


def peer_of(conn: socket.socket) -> str:
    """'uid U pid P' of the process at the other end of a unix socket (SO_PEERCRED, Linux), as the
    kernel vouches for it; 'a client' where the platform does not say."""
    try:
        pid, uid, _gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                             struct.calcsize("3i")))
    except (AttributeError, OSError):
        return "a client"
    return f"uid {uid} pid {pid}"


def request(path: Path | str, obj: dict, timeout: float = 5.0) -> dict:
    """Send one request to the daemon at ``path`` and return its answer. Raises GyrocalError."""
    path = Path(path)
    _check_path_length(path)
    if path.parent.is_dir():  # a missing directory is "no daemon listening", said below
        check_socket_dir(path.parent, server=False)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout)
    try:
        try:
            sock.connect(os.fspath(path))
        except (FileNotFoundError, ConnectionRefusedError) as err:
            # "start it with `gyrocal run`" led an operator to run it by hand as root, without --config:
            # the virtual unit against the real store, root-owned files in it (an operator's audit)
            raise GyrocalError(f"no gyrocal daemon listening on {path}; is the service running? "
                               "(systemctl status gyrocal; `gyrocal run --config FILE` by hand), or pass "
                               "--socket") from err
        except PermissionError as err:
            raise GyrocalError(f"permission denied on {path}; add your user to group gyrocal "
                               "(sudo usermod -aG gyrocal $USER, then log in again) or use sudo") from err
        try:
            sock.sendall(encode_line(obj))
            buf = b""
            while b"\n" not in buf:
                chunk = sock.recv(65536)
                if not chunk:
                    raise GyrocalError(f"the gyrocal daemon on {path} closed the connection "
                                       "without answering")
                buf += chunk
                if len(buf) > MAX_LINE_BYTES:
                    raise GyrocalError(f"the gyrocal daemon on {path} sent an answer over "
                                       f"{MAX_LINE_BYTES} bytes")
        except TimeoutError as err:
            raise GyrocalError(f"the gyrocal daemon on {path} did not answer within {timeout:g} s; "
                               "check `journalctl -u gyrocal`") from err
        except OSError as err:
            raise GyrocalError(f"control socket {path}: {err.strerror or err}") from err
    finally:
        sock.close()
    try:
        reply = json.loads(buf[:buf.index(b"\n")])
    except ValueError as err:
        raise GyrocalError(f"the gyrocal daemon on {path} answered with bad JSON: {err}") from err
    if not isinstance(reply, dict):
        raise GyrocalError(f"the gyrocal daemon on {path} answered {type(reply).__name__}, not an object")
    return reply
