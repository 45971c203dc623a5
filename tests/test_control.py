"""The control socket (JSON lines over a Unix socket) and the status/recalibrate/rollback/push CLI."""

from __future__ import annotations

import json
import os
import select
import shutil
import socket
import stat
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from gyrocal.cli import main as cli_main
from gyrocal.daemon.cli_control import load_coefficient_file
from gyrocal.daemon.control import ControlServer, request
from gyrocal.errors import ConfigError, GyrocalError

TERMS = ["1", "gx", "gy", "gz"]


@pytest.fixture
def short_dir() -> Iterator[Path]:
    """A short directory: AF_UNIX paths are limited to 107 bytes, and pytest's tmp_path can be long."""
    d = Path(tempfile.mkdtemp(prefix="gc", dir="/tmp"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


class FakeDaemon:
    """Records requests and answers like the daemon's handler would."""

    def __init__(self) -> None:
        self.requests: list[dict] = []
        self.peers: list[str | None] = []  # who sent each request, as the server says (its "from")

    def __call__(self, req: dict) -> dict:
        self.peers.append(req.pop("from", None))
        self.requests.append(req)
        cmd = req.get("cmd")
        if cmd == "status":
            return {"ok": True, "state": "MONITORING", "reason": "v2 applied",
                    "unit": {"serial": 1234, "boot_count": 3, "fw": "1.0"}, "applied": {"version": 2},
                    "samples": 4200, "monitor_rms_dps": {"x": 0.001, "y": 0.002, "z": 0.003},
                    "terms": TERMS, "coefficients_dps": [[0.1, 0.2, 0.3, 0.4]] * 3,
                    "link": {"frames": 4300, "crc_errors": 1}, "last_push": {"version": 2, "status": "acked"}}
        if cmd == "boom":
            raise RuntimeError("handler blew up")
        if cmd == "rollback" and req.get("to") == 99:
            return {"ok": False, "error": "unit 1234 has no calibration v99"}
        if cmd == "numpy":
            np = pytest.importorskip("numpy")
            return {"ok": True, "value": np.float64(1.5), "rows": np.eye(2)}
        return {"ok": True, "message": f"did {cmd}", "version": req.get("to") or 3}


@pytest.fixture
def server(short_dir: Path) -> Iterator[tuple[ControlServer, FakeDaemon]]:
    daemon = FakeDaemon()
    srv = ControlServer(short_dir / "control.sock", daemon)
    srv.start()
    yield srv, daemon
    srv.stop()


def raw_exchange(path: Path, payload: bytes, answers: int) -> list[dict]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(os.fspath(path))
        s.sendall(payload)
        buf = b""
        while buf.count(b"\n") < answers:
            chunk = s.recv(65536)
            assert chunk, "server closed early"
            buf += chunk
    return [json.loads(line) for line in buf.splitlines()]


# --- server ----------------------------------------------------------------------------------------

def test_request_round_trip_and_socket_mode_0660(server) -> None:
    srv, daemon = server
    reply = request(srv.path, {"cmd": "recalibrate"})
    assert reply == {"ok": True, "message": "did recalibrate", "version": 3}
    assert daemon.requests == [{"cmd": "recalibrate"}]
    assert stat.S_IMODE(os.stat(srv.path).st_mode) == 0o660


def test_several_requests_on_one_connection_get_one_answer_each(server) -> None:
    srv, _ = server
    answers = raw_exchange(srv.path, b'{"cmd": "a"}\n\n{"cmd": "b"}\n', 2)
    assert [a["message"] for a in answers] == ["did a", "did b"]


def test_bad_json_and_non_objects_get_errors_and_the_server_keeps_serving(server) -> None:
    srv, _ = server
    bad, not_obj, good = raw_exchange(srv.path, b'{"cmd": stat\n[1, 2]\n{"cmd": "ok"}\n', 3)
    assert bad["ok"] is False and "bad JSON" in bad["error"]
    assert not_obj["ok"] is False and "JSON object" in not_obj["error"]
    assert good == {"ok": True, "message": "did ok", "version": 3}
    assert srv.errors == 2


def test_handler_exception_is_answered_as_an_error_and_serving_continues(server) -> None:
    srv, _ = server
    reply = request(srv.path, {"cmd": "boom"})
    assert reply == {"ok": False, "error": "RuntimeError: handler blew up"}
    assert request(srv.path, {"cmd": "status"})["state"] == "MONITORING"


def test_numpy_values_in_an_answer_are_serialised(server) -> None:
    srv, _ = server
    assert request(srv.path, {"cmd": "numpy"}) == {"ok": True, "value": 1.5, "rows": [[1.0, 0.0], [0.0, 1.0]]}


def test_start_and_stop_are_idempotent_and_stop_removes_the_socket(short_dir: Path) -> None:
    srv = ControlServer(short_dir / "c.sock", FakeDaemon())
    srv.start()
    srv.start()
    assert srv.running and (short_dir / "c.sock").exists()
    srv.stop()
    srv.stop()
    assert not srv.running and not (short_dir / "c.sock").exists()
    srv.start()  # restartable
    assert request(short_dir / "c.sock", {"cmd": "x"})["ok"] is True
    srv.stop()


def test_stale_socket_file_from_a_killed_daemon_is_replaced(short_dir: Path) -> None:
    path = short_dir / "c.sock"
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(os.fspath(path))
    dead.close()  # the file stays, no one listens: what kill -9 leaves behind
    assert path.exists()
    with ControlServer(path, FakeDaemon()):
        assert request(path, {"cmd": "x"})["ok"] is True


def test_a_live_daemon_on_the_path_is_not_stolen(server) -> None:
    srv, _ = server
    with pytest.raises(GyrocalError, match="another gyrocal daemon is listening"):
        ControlServer(srv.path, FakeDaemon()).start()
    assert request(srv.path, {"cmd": "x"})["ok"] is True


def test_a_regular_file_on_the_path_is_refused(short_dir: Path) -> None:
    (short_dir / "c.sock").write_text("")
    with pytest.raises(ConfigError, match="not a socket"):
        ControlServer(short_dir / "c.sock", FakeDaemon()).start()


def test_missing_socket_gives_the_one_line_hint(short_dir: Path) -> None:
    path = short_dir / "none.sock"
    with pytest.raises(GyrocalError) as err:
        request(path, {"cmd": "status"})
    assert str(err.value) == (f"no gyrocal daemon listening on {path}; is the service running? "
                              "(systemctl status gyrocal; `gyrocal run --config FILE` by hand), or pass "
                              "--socket")


def test_a_handler_that_hangs_gives_a_timeout_error_not_a_hang(short_dir: Path) -> None:
    release = threading.Event()

    def slow(req: dict) -> dict:
        release.wait(10)
        return {"ok": True}

    with ControlServer(short_dir / "c.sock", slow) as srv:
        with pytest.raises(GyrocalError, match="did not answer within 0.2 s"):
            request(srv.path, {"cmd": "status"}, timeout=0.2)
        release.set()


def test_a_too_long_socket_path_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="at most 107"):
        ControlServer(Path("/tmp/" + "x" * 120), FakeDaemon()).start()


# --- CLI -------------------------------------------------------------------------------------------

def test_cli_status_prints_state_samples_rms_coefficients_link_and_push(server, capsys) -> None:
    srv, _ = server
    assert cli_main(["status", "--socket", str(srv.path)]) == 0
    out = capsys.readouterr().out
    for text in ("MONITORING", "serial 1234", "v2", "4200", "x=0.001", "gx", "+2.0000e-01", "crc_errors=1",
                 "status=acked"):
        assert text in out


def test_cli_status_json_is_the_daemons_answer(server, capsys) -> None:
    srv, _ = server
    assert cli_main(["status", "--json", "--socket", str(srv.path)]) == 0
    assert json.loads(capsys.readouterr().out)["unit"]["serial"] == 1234


def test_cli_socket_default_comes_from_gyrocal_socket_env(server, capsys, monkeypatch) -> None:
    srv, daemon = server
    monkeypatch.setenv("GYROCAL_SOCKET", str(srv.path))
    assert cli_main(["recalibrate"]) == 0
    assert daemon.requests == [{"cmd": "recalibrate"}]
    assert "did recalibrate" in capsys.readouterr().out


def test_cli_rollback_sends_the_version_and_exits_1_when_refused(server, capsys) -> None:
    srv, daemon = server
    assert cli_main(["rollback", "--socket", str(srv.path), "--no-wait"]) == 0
    assert cli_main(["rollback", "--to", "2", "--socket", str(srv.path), "--no-wait"]) == 0
    assert cli_main(["rollback", "--to", "99", "--socket", str(srv.path)]) == 1
    assert daemon.requests == [{"cmd": "rollback", "to": None}, {"cmd": "rollback", "to": 2},
                               {"cmd": "rollback", "to": 99}]
    assert "no calibration v99" in capsys.readouterr().err


def test_cli_rollback_rejects_a_bad_version_as_a_user_error(server) -> None:
    srv, _ = server
    with pytest.raises(SystemExit) as err:
        cli_main(["rollback", "--to", "zero", "--socket", str(srv.path)])
    assert err.value.code == 2


def test_cli_without_a_daemon_exits_2_with_the_hint(short_dir: Path, capsys) -> None:
    assert cli_main(["status", "--socket", str(short_dir / "none.sock")]) == 2
    assert "no gyrocal daemon listening on" in capsys.readouterr().err
    # --json answers in JSON even then (it printed the text line: an operator's audit)
    assert cli_main(["status", "--json", "--socket", str(short_dir / "none.sock")]) == 2
    reply = json.loads(capsys.readouterr().out)
    assert reply["ok"] is False and "no gyrocal daemon listening on" in reply["error"]


def test_cli_push_yaml_sends_three_rows_in_term_order(server, tmp_path: Path) -> None:
    srv, daemon = server
    f = tmp_path / "set.yaml"
    f.write_text("terms: ['1', gx, gy, gz]\ncoefficients:\n  x: [0.1, 0.2, 0.3, 0.4]\n"
                 "  y: [1, 2, 3, 4]\n  z: [-1, -2, -3, -4.5]\n")
    assert cli_main(["push", "--file", str(f), "--socket", str(srv.path), "--no-wait"]) == 0
    assert daemon.requests == [{"cmd": "push", "terms": TERMS, "source": str(f), "coefficients": [
        [0.1, 0.2, 0.3, 0.4], [1.0, 2.0, 3.0, 4.0], [-1.0, -2.0, -3.0, -4.5]]}]


def test_cli_push_waits_for_the_unit_s_answer_and_exits_1_on_a_nak(short_dir: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    """The daemon answers a push request when the push starts: `gyrocal push` said "pushing v14" and
    exit 0 for a set the unit then NAKed OUT_OF_RANGE, which only the journal said (an audit with a
    unit built from protocol.md). It now waits for the unit's answer: 1 and the reason on a NAK, 0 on
    an ack; with a daemon that never shows the outcome (a new session took over), 1 after about a
    second."""
    answers = {"push": {"version": 14, "status": "nak", "reasons": ["unit answered NAK (reason "
                                                                     "OUT_OF_RANGE (3))"]}}

    def daemon(req: dict) -> dict:
        if req.get("cmd") == "status":
            return {"ok": True, "state": "COLLECTING", "last_push": answers["push"]}
        return {"ok": True, "message": "pushing v14", "version": 14}

    srv = ControlServer(short_dir / "control.sock", daemon)
    srv.start()
    try:
        f = tmp_path / "set.yaml"
        f.write_text("terms: ['1']\ncoefficients: [[9.0], [0.0], [0.0]]\n")  # a unit NAKs it (the stub)
        assert cli_main(["push", "--file", str(f), "--socket", str(srv.path)]) == 1
        err = capsys.readouterr().err
        assert "v14 not taken: nak" in err and "OUT_OF_RANGE" in err
        answers["push"] = {"version": 14, "status": "acked"}
        assert cli_main(["rollback", "--to", "14", "--socket", str(srv.path)]) == 0
        assert "v14 acked" in capsys.readouterr().out
        answers["push"] = {"version": 9, "status": "acked"}  # never this version's outcome: not a success
        assert cli_main(["push", "--file", str(f), "--socket", str(srv.path)]) == 1
        assert "not in the daemon's status" in capsys.readouterr().err
    finally:
        srv.stop()


def test_push_accepts_fit_output_and_store_records(tmp_path: Path) -> None:
    fit = tmp_path / "fit.json"  # Contract 3
    fit.write_text(json.dumps({"method": "rls", "terms": TERMS, "samples": 10,
                               "coefficients": {"x": [0, 1, 2, 3], "y": [0, 1, 2, 3], "z": [0, 1, 2, 3]}}))
    assert load_coefficient_file(fit)[1][2] == [0.0, 1.0, 2.0, 3.0]
    rec = tmp_path / "v000001.json"  # a calibration store record
    rec.write_text(json.dumps({"terms": TERMS, "coefficients_dps": [[0, 0, 0, 1]] * 3}))
    assert load_coefficient_file(rec) == (TERMS, [[0.0, 0.0, 0.0, 1.0]] * 3)


def test_push_file_carries_the_temperature_range_its_set_was_learnt_over(tmp_path: Path) -> None:
    """An autopilot writes it as TMIN..TMAX: the range the link has seen since may reach past it."""
    from gyrocal.daemon.cli_control import file_temp_range
    from gyrocal.daemon.push import parse_temp_range

    fit = tmp_path / "fit.json"  # `gyrocal fit --json` of a log with temperature terms
    fit.write_text(json.dumps({"terms": ["1", "temp"], "coefficients": [[0, 1]] * 3,
                               "temp_range_c": [21.5, 38.0]}))
    rec = tmp_path / "v000003.yaml"  # a store record
    rec.write_text("terms: ['1', temp]\ncoefficients_dps: [[0, 1], [0, 1], [0, 1]]\n"
                   "stats: {temp_range_c: [22.4, 38.0]}\n")
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({"terms": ["1", "temp"], "coefficients": [[0, 1]] * 3}))
    assert file_temp_range(fit) == (21.5, 38.0) and file_temp_range(rec) == (22.4, 38.0)
    assert file_temp_range(bare) is None
    assert parse_temp_range("20,45.5", "--temp-range") == (20.0, 45.5)
    for bad in ("45,20", "20", "a,b", "nan,3"):
        with pytest.raises(ConfigError, match="--temp-range"):
            parse_temp_range(bad, "--temp-range")


@pytest.mark.parametrize(("content", "suffix", "expected"), [
    ("{not json", ".json", "not valid JSON"),
    ("terms: [1\n", ".yaml", ":2:1: not valid YAML (expected ',' or ']'"),  # one line, not PyYAML's drawing
    ("- 1\n- 2\n", ".yaml", "top level is list"),
    ("coefficients: {x: [1], y: [1], z: [1]}\n", ".yaml", "field 'terms'"),
    ("terms: ['1', 'gx^0']\ncoefficients: {x: [1, 2], y: [1, 2], z: [1, 2]}\n", ".yaml", "field 'terms'"),
    ("terms: ['1', gx]\n", ".yaml", "field 'coefficients' is missing"),
    ("terms: ['1', gx]\ncoefficients: {x: [1, 2], y: [1, 2]}\n", ".yaml", "lacks axes ['z']"),
    ("terms: ['1', gx]\ncoefficients: {x: [1, 2], y: [1], z: [1, 2]}\n", ".yaml", "'coefficients.y' has 1"),
    ("terms: ['1', gx]\ncoefficients: {x: [1, 2], y: [1, .nan], z: [1, 2]}\n", ".yaml",
     "'coefficients.y[1]'"),
    ("terms: ['1', gx]\ncoefficients: {x: [1, 2], y: [1, 'a'], z: [1, 2]}\n", ".yaml", "(term 'gx')"),
    # said by the daemon, without the file or the field (an integrator's check, F7)
    ("terms: ['1', gx]\ncoefficients: {x: [50, 2], y: [1, 2], z: [1, 2]}\n", ".yaml",
     "'coefficients.x[0]' (term '1') is 50 deg/s per term unit, beyond the 10"),
    ("terms: ['1', gq]\ncoefficients: {x: [1, 2], y: [1, 2], z: [1, 2]}\n", ".yaml",
     "field 'terms': 'gq' is not an atom a unit evaluates; fix:"),
])
def test_push_file_errors_name_the_file_the_field_and_the_fix(tmp_path: Path, content: str, suffix: str,
                                                              expected: str) -> None:
    f = tmp_path / f"bad{suffix}"
    f.write_text(content)
    with pytest.raises(ConfigError) as err:
        load_coefficient_file(f)
    assert str(f) in str(err.value) and expected in str(err.value) and "\n" not in str(err.value)


def test_cli_push_missing_file_exits_2_naming_it(server, tmp_path: Path, capsys) -> None:
    srv, daemon = server
    missing = tmp_path / "nope.yaml"
    assert cli_main(["push", "--file", str(missing), "--socket", str(srv.path)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "fix:" in err
    assert daemon.requests == []


def test_default_socket_follows_env_then_the_first_live_socket(short_dir: Path, monkeypatch) -> None:
    from gyrocal.daemon.control import DEFAULT_SOCKET, default_socket_path

    monkeypatch.setenv("GYROCAL_SOCKET", "/x/y.sock")
    assert default_socket_path() == Path("/x/y.sock")
    monkeypatch.delenv("GYROCAL_SOCKET")
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(short_dir))
    if not DEFAULT_SOCKET.exists():
        assert default_socket_path() == DEFAULT_SOCKET  # nothing listens anywhere: the system path
        (short_dir / "gyrocal").mkdir()
        with ControlServer(short_dir / "gyrocal" / "control.sock", FakeDaemon()):
            # a daemon started by hand, without /run/gyrocal, is found (config.py's fallback)
            assert default_socket_path() == short_dir / "gyrocal" / "control.sock"


def test_an_oversized_request_is_refused_without_unbounded_buffering(server, monkeypatch) -> None:
    import gyrocal.daemon.control as control

    srv, daemon = server
    monkeypatch.setattr(control, "MAX_REQUEST_BYTES", 1000)
    (reply,) = raw_exchange(srv.path, b"x" * 5000, 1)
    assert reply["ok"] is False and "longer than 1000 bytes" in reply["error"]
    assert daemon.requests == []
    assert request(srv.path, {"cmd": "x"})["ok"] is True


# --- slow clients, eviction, nesting, the runtime directory ------------------------------------------

def _connect(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(10)
    s.connect(os.fspath(path))
    return s


def _read_line(s: socket.socket) -> dict:
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = s.recv(65536)
        if not chunk:
            break
        buf += chunk
    return json.loads(buf) if buf else {}


def test_a_trickling_client_is_cut_off_at_the_whole_request_deadline(server, monkeypatch) -> None:
    """A byte every 0.1 s keeps every recv busy, but the request as a whole misses its 0.5 s deadline
    (the same as a byte every 20 s against the real 10 s deadline)."""
    import gyrocal.daemon.control as control

    srv, daemon = server
    monkeypatch.setattr(control, "REQUEST_DEADLINE_S", 0.5)
    s = _connect(srv.path)
    cut = False
    for ch in b'{"cmd": "status", "pad": "' + b"x" * 100:
        try:
            s.sendall(bytes([ch]))
        except OSError:
            cut = True
            break
        ready, _, _ = select.select([s], [], [], 0.1)
        if ready:
            reply = _read_line(s)
            assert reply["ok"] is False and "not complete within 0.5 s" in reply["error"]
            cut = True
            break
    s.close()
    assert cut and daemon.requests == []


def test_an_idle_connection_is_dropped_with_a_reason(server, monkeypatch) -> None:
    import gyrocal.daemon.control as control

    srv, _ = server
    monkeypatch.setattr(control, "CLIENT_IDLE_S", 0.3)
    s = _connect(srv.path)
    reply = _read_line(s)
    assert reply["ok"] is False and "no request within 0.3 s" in reply["error"]
    assert s.recv(10) == b""
    s.close()


def test_eight_slow_clients_do_not_lock_the_operator_out(server) -> None:
    """MAX_CLIENTS connections each holding half a request: a new connection evicts the most idle one
    and is answered at once (deadlines are the real ones: nothing here waits for a timeout)."""
    import gyrocal.daemon.control as control

    srv, daemon = server
    slow = []
    for _ in range(control.MAX_CLIENTS):
        s = _connect(srv.path)
        s.sendall(b'{"cmd": "sta')
        slow.append(s)
    deadline = 500
    while len(srv._clients) < control.MAX_CLIENTS and deadline:  # the acceptor registers them in turn
        threading.Event().wait(0.02)
        deadline -= 1
    assert len(srv._clients) == control.MAX_CLIENTS
    for _ in range(3):  # operators keep getting in, each evicting the most idle slow client
        assert request(srv.path, {"cmd": "status"})["state"] == "MONITORING"
    evicted = [s for s in slow if select.select([s], [], [], 0)[0]]
    assert evicted, "no slow client was evicted"
    assert "evicted" in _read_line(evicted[0])["error"]
    assert slow[0] in evicted  # the oldest goes first
    for s in slow:
        s.close()
    assert [r["cmd"] for r in daemon.requests] == ["status"] * 3 and srv.dropped >= 1


@pytest.mark.parametrize("depth", [17, 100, 30_000])
def test_deeply_nested_json_gets_a_clear_answer_not_a_recursion_error(server, caplog, depth: int) -> None:
    srv, daemon = server
    line = b'{"cmd": "push", "x": ' + b"[" * depth + b"]" * depth + b"}\n"
    (reply,) = raw_exchange(srv.path, line, 1)
    assert reply["ok"] is False and "nested deeper than 16 levels" in reply["error"]
    assert daemon.requests == [] and "RecursionError" not in caplog.text and "Traceback" not in caplog.text
    assert request(srv.path, {"cmd": "x"})["ok"] is True


def test_brackets_inside_strings_do_not_count_as_nesting(server) -> None:
    srv, daemon = server
    assert request(srv.path, {"cmd": "push", "source": "[[[[[[[[[[[[[[[[[[[[{{{{{{{{{{{{{{"})["ok"] is True
    from gyrocal.daemon.control import json_depth

    assert json_depth(b'{"a": [[1], {"b": "]]]]"}]}') == 3


def test_the_daemon_creates_its_runtime_directory_0700(short_dir: Path) -> None:
    path = short_dir / "run" / "gyrocal" / "c.sock"
    with ControlServer(path, FakeDaemon()):
        for d in (short_dir / "run", short_dir / "run" / "gyrocal"):
            assert stat.S_IMODE(os.stat(d).st_mode) == 0o700
        assert request(path, {"cmd": "x"})["ok"] is True


def test_a_world_writable_socket_directory_is_refused_by_daemon_and_client(short_dir: Path) -> None:
    d = short_dir / "open"
    d.mkdir()
    os.chmod(d, 0o777)
    with pytest.raises(ConfigError, match="writable by other users"):
        ControlServer(d / "c.sock", FakeDaemon()).start()
    with pytest.raises(ConfigError, match="writable by other users"):
        request(d / "c.sock", {"cmd": "status"})
    os.chmod(d, 0o770)
    with pytest.raises(ConfigError, match="mode 0770"):
        ControlServer(d / "c.sock", FakeDaemon()).start()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give a directory to another user")
def test_another_users_directory_in_a_shared_tmp_is_refused_by_daemon_and_client(short_dir: Path) -> None:
    """The squat: another user pre-creates /tmp/gyrocal-<uid> (0700, theirs) and listens in it."""
    os.chmod(short_dir, 0o1777)  # stands in for /tmp
    squat = short_dir / "gyrocal-1000"
    (squat / "gyrocal").mkdir(parents=True)
    with ControlServer(squat / "gyrocal" / "c.sock", FakeDaemon()) as fake:  # the squatter's daemon
        for d in (squat / "gyrocal", squat):
            os.chown(d, 12345, 12345)
        os.chown(fake.path, 12345, 12345)
        with pytest.raises(ConfigError, match="belongs to another user"):
            request(fake.path, {"cmd": "status"})
        with pytest.raises(ConfigError, match="belongs to another user"):
            ControlServer(squat / "gyrocal" / "d.sock", FakeDaemon()).start()
        os.chown(squat / "gyrocal", 0, 0)  # only the parent is foreign: still refused
        with pytest.raises(ConfigError, match=f"its parent {squat} belongs to another user"):
            request(fake.path, {"cmd": "status"})


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give a directory to another user")
def test_a_system_runtime_dir_owned_by_the_daemon_user_is_accepted_by_the_client(short_dir: Path) -> None:
    """/run/gyrocal belongs to user gyrocal (systemd RuntimeDirectory= with User=) and sits in a
    directory only root can write: the operator's client talks to it."""
    run = short_dir / "run"
    (run / "gyrocal").mkdir(parents=True)
    os.chmod(run, 0o755)
    with ControlServer(run / "gyrocal" / "c.sock", FakeDaemon()) as srv:
        os.chown(run / "gyrocal", 12345, 12345)
        os.chmod(run / "gyrocal", 0o750)
        assert request(srv.path, {"cmd": "x"})["ok"] is True


def test_the_per_user_fallback_is_private(short_dir: Path, monkeypatch) -> None:
    from gyrocal.daemon.config import load_config

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(short_dir))
    monkeypatch.delenv("RUNTIME_DIRECTORY", raising=False)
    monkeypatch.delenv("GYROCAL_SOCKET", raising=False)
    import gyrocal.daemon.config as config

    monkeypatch.setattr(config, "_writable_dir", lambda p: False)  # no /run/gyrocal
    sock = load_config(None).control_socket
    assert sock == short_dir / "gyrocal" / "control.sock"
    with ControlServer(sock, FakeDaemon()):
        assert stat.S_IMODE(os.stat(sock.parent).st_mode) == 0o700


def test_clients_that_never_read_their_answers_cannot_hold_the_slots(short_dir: Path) -> None:
    """Eight clients flood requests for a large answer and never read: their sends block, yet the
    operator still gets in (a client blocked in sending its answer can be evicted)."""
    import gyrocal.daemon.control as control

    big = {"ok": True, "pad": "x" * 200_000}
    with ControlServer(short_dir / "c.sock", lambda req: dict(big) if req.get("cmd") == "big"
                       else {"ok": True, "state": "UP"}) as srv:
        hogs = []
        for _ in range(control.MAX_CLIENTS):
            s = _connect(srv.path)
            s.sendall(b'{"cmd": "big"}\n' * 20)
            hogs.append(s)
        deadline = 500
        while len(srv._clients) < control.MAX_CLIENTS and deadline:
            threading.Event().wait(0.02)
            deadline -= 1
        threading.Event().wait(0.3)  # let their answers fill the socket buffers
        assert request(srv.path, {"cmd": "status"}, timeout=5)["state"] == "UP"
        for s in hogs:
            s.close()


def test_a_command_reaches_the_daemon_with_who_sent_it_as_the_kernel_says(server) -> None:
    """SO_PEERCRED, not the client's word: a 'from' in the request is overwritten."""
    srv, fake = server
    assert request(srv.path, {"cmd": "recalibrate", "from": "uid 0 pid 1"})["ok"]
    assert fake.peers[-1] == f"uid {os.getuid()} pid {os.getpid()}"


def test_an_operator_command_is_one_log_line_with_who_and_how_it_ended(tmp_path: Path, caplog) -> None:
    import logging

    from gyrocal.daemon.config import load_config
    from gyrocal.daemon.engine import Engine

    eng = Engine(load_config(None, {"state_dir": str(tmp_path), "control_socket": str(tmp_path / "c")}))
    caplog.set_level(logging.INFO, logger="gyrocal.engine")
    reply = eng._command({"cmd": "rollback", "to": 3, "from": "uid 1000 pid 42"}, 0.0)
    assert not reply["ok"]
    lines = [r for r in caplog.records if "operator command" in r.getMessage()]
    assert len(lines) == 1 and lines[0].levelno == logging.WARNING
    assert lines[0].getMessage() == ("operator command rollback --to 3 from uid 1000 pid 42: refused: "
                                     "no unit session yet; wait for the unit's HELLO")


def test_a_file_push_of_a_set_the_unit_cannot_hold_stores_nothing(tmp_path: Path) -> None:
    """operations.md: a push is checked before anything is stored. On an autopilot (it holds its
    cubic in temperature only), ["1", "gx"] was stored as a 'refused' version first (an integrator's
    audit)."""
    from gyrocal.daemon.capabilities import UnitCapabilities
    from gyrocal.daemon.config import load_config
    from gyrocal.daemon.engine import Engine
    from gyrocal.daemon.learner import make_learner
    from gyrocal.daemon.session import Session
    from gyrocal.protocol.messages import Hello

    eng = Engine(load_config(None, {"state_dir": str(tmp_path), "control_socket": str(tmp_path / "c")}))
    caps = UnitCapabilities("px4", (("1", "temp", "temp^2", "temp^3"),), 4, reboot_required=True)
    eng.session = Session(eng.cfg, Hello(77, "1.0", 1, 250), make_learner(eng.cfg, None, 250.0), eng.store,
                          lambda msg: None, 0.0, 250.0, caps=caps)

    class Up:
        connected = True

    eng.link = Up()
    reply = eng._command({"cmd": "push", "terms": ["1", "gx"], "coefficients": [[0.01, 0.0]] * 3}, 0.0)
    assert not reply["ok"] and "cannot hold" in reply["error"] and "nothing was stored" in reply["error"]
    assert eng.store.history(77) == []

    held: list[tuple[int, float, float]] = []
    Up.hold_range = staticmethod(lambda v, lo, hi: held.append((v, lo, hi)))  # type: ignore[attr-defined]
    poly = [[0.01, 1e-4, 0.0, 0.0]] * 3
    reply = eng._command({"cmd": "push", "terms": ["1", "temp", "temp^2", "temp^3"], "coefficients": poly,
                          "temp_range_c": [30.0, 22.0]}, 0.0)
    assert not reply["ok"] and "LO must be below HI" in reply["error"] and eng.store.history(77) == []
    reply = eng._command({"cmd": "push", "terms": ["1", "temp", "temp^2", "temp^3"], "coefficients": poly,
                          "temp_range_c": [22.0, 30.0]}, 0.0)
    assert reply["ok"], reply
    v = reply["version"]
    assert held == [(v, 22.0, 30.0)] and eng.store.get(77, v).stats["temp_range_c"] == [22.0, 30.0]
