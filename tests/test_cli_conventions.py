"""CLI conventions every command shares: logs on stderr, journald priorities on every line (the fatal
one included), no traceback on a closed pipe, one -v/-q, `status --watch`, a tidy status view, and a
daemon side that works without the [analysis] extra."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from gyrocal.cli import main as cli_main
from gyrocal.daemon.cli_control import format_status, watch_status
from gyrocal.daemon.control import ControlServer
from gyrocal.daemon.logsetup import effective_level, set_verbosity

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def short_dir() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="gc", dir="/tmp"))
    yield d
    shutil.rmtree(d, ignore_errors=True)


def _gyrocal(*args: str, env: dict | None = None, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gyrocal.cli", *args], capture_output=True, text=True,
                          timeout=60, env={**os.environ, **(env or {})}, **kw)


# --- journald priorities and the fatal line -----------------------------------------------------------

def test_the_fatal_error_line_carries_priority_3_when_stderr_is_the_journal(short_dir: Path) -> None:
    """systemd sets JOURNAL_STREAM to the dev:ino of the journal stream; we stand in a pipe for it."""
    r, w = os.pipe()
    st = os.fstat(w)
    env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
    proc = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", "status", "--socket",
                             str(short_dir / "none.sock")], stderr=w, stdout=subprocess.DEVNULL, env=env)
    os.close(w)
    with os.fdopen(r) as f:
        err = f.read()
    assert proc.wait(30) == 2
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("<3>gyrocal: error: no gyrocal daemon listening")


def _under_journal(*args: str) -> tuple[int, str]:
    r, w = os.pipe()
    st = os.fstat(w)
    env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
    proc = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", *args], stderr=w, stdout=subprocess.DEVNULL,
                            env=env)
    os.close(w)
    with os.fdopen(r) as f:
        err = f.read()
    return proc.wait(30), err


def test_a_usage_error_under_journald_has_its_priority() -> None:
    code, err = _under_journal("run", "--no-such-flag")
    assert code == 2
    assert err.splitlines()[-1].startswith("<3>gyrocal: error: unrecognized arguments: --no-such-flag")
    code, err = _under_journal("run", "--log-level", "LOUD")
    assert code == 2
    assert err.splitlines()[-1].startswith("<3>gyrocal run: error: argument --log-level: invalid choice")


def test_a_traceback_under_journald_keeps_its_priority_on_every_line(capsys, monkeypatch) -> None:
    from gyrocal.daemon.logsetup import setup_logging

    monkeypatch.setenv("JOURNAL_STREAM", "8:1234")
    setup_logging("INFO")
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        logging.getLogger("gyrocal").critical("gyrocal run crashed", exc_info=True)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) > 3 and all(ln.startswith("<2>") for ln in lines)
    assert lines[0] == "<2>gyrocal: gyrocal run crashed" and lines[-1] == "<2>RuntimeError: boom"


def test_no_priority_prefix_when_stderr_is_not_the_journal_stream(short_dir: Path) -> None:
    """JOURNAL_STREAM inherited by a child whose stderr goes elsewhere: plain text (systemd.exec(5))."""
    out = _gyrocal("status", "--socket", str(short_dir / "none.sock"), env={"JOURNAL_STREAM": "1:1"})
    assert out.returncode == 2 and out.stderr.startswith("gyrocal: error: no gyrocal daemon")


def test_log_lines_go_to_stderr_with_priorities_under_journald(capsys, monkeypatch) -> None:
    from gyrocal.daemon.logsetup import setup_logging

    monkeypatch.setenv("JOURNAL_STREAM", "8:1234")  # capsys's stderr has no descriptor to check: trusted
    setup_logging("INFO")
    logging.getLogger("gyrocal.t").warning("disk nearly full")
    logging.getLogger("gyrocal.t").info("hello")
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.splitlines() == ["<4>gyrocal.t: disk nearly full", "<6>gyrocal.t: hello"]


# --- closed pipes ------------------------------------------------------------------------------------

def test_status_json_into_a_closed_pipe_exits_quietly(short_dir: Path) -> None:
    """`gyrocal status --json | head -c 10`: the answer is larger than a pipe buffer, the reader
    leaves after 10 bytes; no BrokenPipeError traceback, status 141 (128 + SIGPIPE)."""
    big = {"ok": True, "state": "MONITORING", "pad": ["x" * 100] * 3000}
    with ControlServer(short_dir / "c.sock", lambda req: dict(big)) as srv:
        proc = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", "status", "--json", "--socket",
                                 str(srv.path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None and proc.stderr is not None
        head = proc.stdout.read(10)
        proc.stdout.close()
        err = proc.stderr.read().decode()
        code = proc.wait(30)
    assert head == b'{\n  "ok": '
    assert "Traceback" not in err and "BrokenPipe" not in err and err == ""
    assert code == 141


# --- one verbosity flag set ----------------------------------------------------------------------------

def test_v_and_q_move_the_commands_default_level(short_dir: Path) -> None:
    set_verbosity(0, 0)
    assert effective_level("INFO") == "INFO"
    set_verbosity(1, 0)
    assert effective_level("INFO") == "DEBUG" and effective_level("WARNING") == "INFO"
    set_verbosity(3, 0)
    assert effective_level("WARNING") == "DEBUG"
    set_verbosity(0, 2)
    assert effective_level("INFO") == "ERROR"
    set_verbosity(0, 9)
    assert effective_level("INFO") == "CRITICAL"
    set_verbosity(0, 0)


@pytest.mark.parametrize(("argv", "level"), [
    (["status"], logging.WARNING),
    (["-v", "status"], logging.INFO),
    (["status", "-v", "-v"], logging.DEBUG),
    (["-q", "status", "--verbose"], logging.WARNING),
    (["status", "--quiet"], logging.ERROR),
])
def test_v_and_q_work_before_and_after_the_command(short_dir: Path, argv: list[str], level: int) -> None:
    with ControlServer(short_dir / "c.sock", lambda req: {"ok": True, "state": "X"}) as srv:
        assert cli_main([*argv, "--socket", str(srv.path)]) == 0
    assert logging.getLogger().level == level
    set_verbosity(0, 0)


def _help(cmd: str) -> str:
    import argparse

    from gyrocal.cli import build_parser

    parser = build_parser([cmd])
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[cmd].format_help()


def test_every_command_takes_v_and_q_and_run_keeps_log_level() -> None:
    for cmd in ("run", "demo", "sim", "status", "fit", "push", "rollback", "completion", "install-files"):
        text = _help(cmd)
        assert "-v" in text and "--verbose" in text and "-q, --quiet" in text, cmd
    assert "--log-level" in _help("run")


# --- status: tidy text, --watch ------------------------------------------------------------------------

def test_status_text_aligns_long_keys_and_wraps_instead_of_cutting() -> None:
    reply = {"ok": True, "state": "COLLECTING", "reason": "learning", "warm_started_from": None,
             "validation": {f"field_{i}": 0.123456 * i for i in range(20)},
             "dropped_nonfinite": 0}
    text = format_status(reply, width=80)
    lines = text.splitlines()
    assert "warm_started_fromNone" not in text and "..." not in text
    key_line = next(ln for ln in lines if ln.startswith("warm_started_from"))
    assert key_line.split() == ["warm_started_from", "None"]
    col = len(key_line) - len("None")
    assert all(len(ln) <= 80 for ln in lines)
    val_lines = [i for i, ln in enumerate(lines) if ln.startswith("validation")]
    assert val_lines and lines[val_lines[0] + 1].startswith(" " * col)  # wrapped under the value column
    assert "field_19=2.34566" in text  # the last item is shown, not cut
    assert lines[0].startswith("state" + " " * (col - len("state")) + "COLLECTING")


def test_watch_prints_one_json_line_per_change(short_dir: Path, capsys) -> None:
    # uptime and sample counts move at every poll: they are not a change (an operator's audit)
    answers = iter([{"state": "A", "n": 1, "uptime_s": 1.0}, {"state": "A", "n": 1, "uptime_s": 2.0,
                                                              "samples": 900},
                    {"state": "B", "n": 2}, {"state": "B", "n": 2}, {"state": "C", "n": 3}])
    asked = []

    def handler(req: dict) -> dict:
        asked.append(req)
        return dict(next(answers))

    with ControlServer(short_dir / "c.sock", handler) as srv:
        assert watch_status(srv.path, 0.01, count=3) == 0
    lines = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert [ln["state"] for ln in lines] == ["A", "B", "C"] and len(asked) == 5


def test_watch_does_not_count_the_figures_in_the_reason_as_a_change(short_dir: Path, capsys) -> None:
    """A cold unit collecting gave a line a second, the reason's seconds counter its only change (an
    integrator's check, F6); a new version in it (v8 -> v9) is a change."""
    why = "COLLECTING: a constant alone ... (no new direction learnt for {} s so far)"
    answers = iter([{"state": "C", "reason": why.format(46)}, {"state": "C", "reason": why.format(47)},
                    {"state": "C", "reason": why.format(48.5)}, {"state": "M", "reason": "monitoring v8"},
                    {"state": "M", "reason": "monitoring v9"}])

    with ControlServer(short_dir / "c.sock", lambda req: dict(next(answers))) as srv:
        assert watch_status(srv.path, 0.01, count=3) == 0
    lines = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert [ln["reason"] for ln in lines] == [why.format(46), "monitoring v8", "monitoring v9"]


def test_watch_reports_a_lost_daemon_once_and_picks_it_up_again(short_dir: Path, capsys) -> None:
    path = short_dir / "c.sock"
    srv = ControlServer(path, lambda req: {"state": "UP"})
    srv.start()
    import threading

    calls = {"n": 0}
    real_request = __import__("gyrocal.daemon.cli_control", fromlist=["request"]).request

    def flaky(p, obj, timeout=5.0):
        calls["n"] += 1
        if calls["n"] == 2:
            srv.stop()
        if calls["n"] == 5:
            srv.start()
        return real_request(p, obj, timeout)

    import gyrocal.daemon.cli_control as cc

    orig = cc.request
    cc.request = flaky
    try:
        t = threading.Timer(20, srv.stop)
        t.start()
        assert watch_status(path, 0.01, count=3) == 0
        t.cancel()
    finally:
        cc.request = orig
        srv.stop()
    lines = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert lines[0]["state"] == "UP" and lines[1]["ok"] is False and "no gyrocal daemon" in lines[1]["error"]
    assert lines[2]["state"] == "UP" and len(lines) == 3


def test_watch_cli_streams_json_lines(short_dir: Path) -> None:
    with ControlServer(short_dir / "c.sock", lambda req: {"ok": True, "state": "UP"}) as srv:
        out = _gyrocal("status", "--watch", "--count", "1", "--socket", str(srv.path))
    assert out.returncode == 0 and json.loads(out.stdout) == {"ok": True, "state": "UP"}


# --- lean install: the daemon's commands without the [analysis] extra ------------------------------------

_BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('scipy', 'matplotlib', 'allantools', 'pytest', 'hypothesis'):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Block())
from gyrocal.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _lean(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _BLOCK, *args], capture_output=True, text=True, timeout=120,
                          cwd=REPO)


@pytest.mark.parametrize("cmd", ["run", "demo", "status", "sim", "fit", "push", "install-files"])
def test_daemon_commands_load_without_the_analysis_extra(cmd: str) -> None:
    out = _lean(cmd, "--help")
    assert out.returncode == 0, out.stderr


def test_sim_runs_without_the_analysis_extra(tmp_path: Path) -> None:
    out = _lean("sim", "--duration", "0.5", "--rate", "100", "--record", str(tmp_path / "r.csv"))
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "r.csv").stat().st_size > 0


def test_analyze_without_the_extra_says_how_to_install_it(tmp_path: Path) -> None:
    out = _lean("analyze", str(tmp_path / "x.csv"), "--json", str(tmp_path / "o.json"))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "pip install 'gyrocal[analysis]'" in out.stderr and out.stderr.startswith("gyrocal: error:")


# --- python-can conventions on `gyrocal sim` -------------------------------------------------------------

def _sim_bus(argv: list[str]) -> dict:
    from gyrocal.cli import build_parser
    from gyrocal.sim.cli_sim import can_bus_kwargs

    return can_bus_kwargs(build_parser(["sim"]).parse_args(["sim", "--link", "can", *argv]))


def test_sim_takes_python_cans_i_c_b_and_bus_kwargs(tmp_path: Path, monkeypatch) -> None:
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert _sim_bus(["-i", "virtual", "-c", "gyro", "-b", "1000000", "--bus-kwargs",
                     "receive_own_messages=True", "rx_queue_size=64"]) == {
        "interface": "virtual", "channel": "gyro", "bitrate": 1000000, "receive_own_messages": True,
        "rx_queue_size": 64}
    assert _sim_bus([]) == {"interface": "udp_multicast", "channel": "239.74.163.2"}  # nothing configured
    assert _sim_bus(["--can-interface", "udp_multicast", "--can-port", "4000"])["port"] == 4000  # old names
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "bench")
    assert _sim_bus([]) == {"interface": "virtual", "channel": "bench"}  # python-can's environment
    with pytest.raises(SystemExit):
        _sim_bus(["-i", "no_such_bus"])
    from gyrocal.errors import ConfigError

    with pytest.raises(ConfigError, match="KEY=VALUE"):
        _sim_bus(["--bus-kwargs", "oops"])
