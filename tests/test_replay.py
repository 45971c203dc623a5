"""``gyrocal replay``: the daemon's own engine on recordings, deterministic, pushes recorded not sent."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gyrocal.cli import main
from gyrocal.daemon.config import load_config
from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import open_link
from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import read_log, write_log
from gyrocal.protocol.messages import CoeffRead, CoeffReport, Hello, HelloRequest
from gyrocal.replay.run import replay
from gyrocal.replay.source import open_recording
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import SessionStream, TruthModel

DATA = Path(__file__).resolve().parent.parent / "data"
COLS = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session")


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two switch-ons of a tumbling unit at 200 Hz, 70 s each (enough for the daemon to push)."""
    parts = []
    for boot in (0, 1):
        c = SessionStream(TruthModel(), tumble(1.2, 0.4), 200.0, seed=5, boot=boot).chunk(14000)
        part = {k: np.asarray(c[k], dtype=np.float64) for k in COLS[:-1]}
        parts.append(part | {"session": np.full(14000, boot)})
    cols = {k: np.concatenate([p[k] for p in parts]) for k in COLS}
    path = tmp_path_factory.mktemp("replay") / "two_sessions.csv"
    write_log(path, cols, {"unit_serial": "31", "firmware": "2.1.0"})
    return path


def _cfg(tmp_path: Path):  # noqa: ANN202
    state = tmp_path / f"state-{time.monotonic_ns()}"
    state.mkdir()
    return load_config(None, {"state_dir": str(state), "control_socket": str(tmp_path / "c.sock"),
                              "watchdog": False})


@pytest.mark.slow
def test_replay_is_deterministic_and_records_the_push(sim_log: Path, tmp_path: Path) -> None:
    runs = [replay(open_recording(str(sim_log)), _cfg(tmp_path)) for _ in range(2)]
    a, b = runs
    for key in ("decisions", "validations", "pushes", "sessions", "samples"):
        assert a[key] == b[key], key
    assert a["samples"] == 28000 and len(a["sessions"]) == 2 and a["sessions_started"] == 2
    unit = {"serial": 31, "fw": "2.1.0", "rate_hz": 200}  # rate_hz: the HELLO's
    assert [s["unit"] for s in a["sessions"]] == [{**unit, "boot_count": 0}, {**unit, "boot_count": 1}]
    push = a["pushes"][0]
    assert push["status"] == "recorded" and push["engine_result"] == "acked" and push["readback_ok"]
    assert len(push["coefficients_dps"]) == 3 and len(push["coefficients_dps"][0]) == len(push["terms"])
    assert a["validations"][0]["passed"] is True
    states = [d["state"] for d in a["decisions"]]
    assert "PUSHING" in states and states.index("PUSHING") < states.index("MONITORING")
    # the clock never goes back, though the unit's time restarts at the second switch-on
    times = [d["t_s"] for d in a["decisions"]]
    assert times == sorted(times) and a["replayed_s"] > 139.0
    # the unit keeps the last set pushed (its flash), across the second switch-on
    assert a["sessions"][1]["applied"]["version"] == a["pushes"][-1]["version"]


def test_after_a_push_the_replayed_unit_compensates_with_the_pushed_set() -> None:
    from gyrocal.daemon.ring import SAMPLE_DTYPE
    from gyrocal.protocol.messages import CoeffAck, CoeffNak, CoeffWrite
    from gyrocal.protocol.termsets import terms_id
    from gyrocal.replay.unit import ReplayUnit

    names = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]
    recorded = CoeffReport(3, terms_id(names), [[0.01] + [0.0] * 9, [0.0] * 10, [0.0] * 10])
    unit = ReplayUnit(Hello(1, "1.0.0", 1), recorded)
    block = np.zeros(50, dtype=SAMPLE_DTYPE)
    block["t"] = np.arange(50) / 100
    block["az"] = 1.0
    block["wx"] = 0.5
    assert np.array_equal(unit.output(block)["wx"], block["wx"])  # nothing pushed: as recorded
    assert unit.answer(CoeffRead()) == [recorded]
    pushed = [[0.03, 0.0, 0.0, 0.002] + [0.0] * 6, [0.0] * 10, [-0.02] + [0.0] * 9]
    ack = unit.answer(CoeffWrite(4, terms_id(names), pushed))[0]
    assert isinstance(ack, CoeffAck) and ack.version == 4 and unit.pushes[-1]["status"] == "recorded"
    out = unit.output(block)
    # out = recorded output + C_rec.phi - C_new.phi, with gz = +1 at this pose
    np.testing.assert_allclose(out["wx"], 0.5 + 0.01 - 0.03 - 0.002)
    np.testing.assert_allclose(out["wz"], 0.02)
    assert unit.answer(CoeffRead())[0].version == 4
    nak = unit.answer(CoeffWrite(5, 0x1234, [[0.0], [0.0], [0.0]]))[0]
    assert isinstance(nak, CoeffNak) and unit.pushes[-1]["status"] == "refused"


def test_a_can_recording_answers_from_its_own_hello_and_coeff_report(tmp_path: Path) -> None:
    rec = open_recording(str(DATA / "sim_can" / "virtual_unit.blf"))
    assert isinstance(rec.first_hello, Hello) and isinstance(rec.first_report, CoeffReport)
    res = replay(rec, _cfg(tmp_path))
    s = res["sessions"][0]
    assert rec.first_report.version == 3 and s["unit"]["serial"] == 4242
    # the recorded unit's set, or a set pushed over it (its bias moved 10-23 deg/h at this boot: the
    # refinement at refine.HELD_CUT comes 30 s in), numbered above it
    assert s["applied"]["version"] == 3 or [p["version"] for p in res["pushes"]] == [s["applied"]["version"]]
    assert all(p["version"] > 3 for p in res["pushes"])
    assert res["samples"] == 4000 and s["samples"] + res["samples_before_hello"] <= 4000
    assert s["trained_samples"] > 0 and not res["dropped"]


def test_a_serial_capture_replays_through_the_same_decoder(tmp_path: Path) -> None:
    from gyrocal.protocol.messages import Sample
    from gyrocal.protocol.serial_framing import encode_frame
    from gyrocal.protocol.termsets import terms_id

    names = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]
    c = SessionStream(TruthModel(), tumble(1.2, 0.4), 200.0, seed=8, boot=0).chunk(2000)
    frames = [encode_frame(Hello(55, "3.0.1", 9, 200)),
              encode_frame(CoeffReport(7, terms_id(names), [[0.001] + [0.0] * 9] * 3))]
    frames += [encode_frame(Sample(i, float(c["t"][i]), (c["wx"][i], c["wy"][i], c["wz"][i]),
                                   (c["ax"][i], c["ay"][i], c["az"][i]), float(c["temp"][i])))
               for i in range(2000)]
    cap = tmp_path / "link.cap"
    cap.write_bytes(b"\x00garbage" + b"".join(frames))
    res = replay(open_recording(str(cap)), _cfg(tmp_path))
    s = res["sessions"][0]
    assert res["format"] == "serial" and res["samples"] == 2000 and res["dropped"]["garbage_bytes"] == 8
    assert s["unit"] == {"serial": 55, "boot_count": 9, "fw": "3.0.1", "rate_hz": 200}
    assert s["applied"]["version"] == 7


def test_a_converted_can_log_keeps_the_applied_set_for_replay(tmp_path: Path) -> None:
    out = tmp_path / "blf.csv"
    assert main(["convert", str(DATA / "sim_can" / "virtual_unit.blf"), str(out)]) == 0
    rec = open_recording(str(out))
    direct = open_recording(str(DATA / "sim_can" / "virtual_unit.blf"))
    assert rec.first_report == direct.first_report and rec.first_report.version == 3


def test_a_capture_without_hello_gets_an_anonymous_unit(tmp_path: Path) -> None:
    from gyrocal.protocol.messages import Sample
    from gyrocal.protocol.serial_framing import encode_frame

    c = SessionStream(TruthModel(), tumble(1.2, 0.4), 200.0, seed=9, boot=0).chunk(1500)
    cap = tmp_path / "late.cap"  # the logger started after the unit's switch-on: no HELLO recorded
    cap.write_bytes(b"".join(encode_frame(Sample(5000 + i, 25.0 + float(c["t"][i]),
                                                 (c["wx"][i], c["wy"][i], c["wz"][i]),
                                                 (c["ax"][i], c["ay"][i], c["az"][i]), float(c["temp"][i])))
                             for i in range(1500)))
    res = replay(open_recording(str(cap)), _cfg(tmp_path))
    assert res["hello_synthesized"] and len(res["sessions"]) == 1
    assert res["sessions"][0]["unit"]["serial"] == 0 and res["sessions"][0]["samples"] > 0


def test_replay_cli_writes_json_and_text(sim_log: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "r.json"
    assert main(["replay", str(sim_log), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads(out.read_text())
    assert "push v1" in text and "recorded" in text and res["pushes"][0]["status"] == "recorded"
    # every sample accounted for: the sessions' counts plus what the detector had not decided at the
    # end of each (a foreign-log audit saw 17971 of 18000 with "dropped: none")
    assert res["warnings"] == [] and res["not_decided"] >= 0
    assert sum(x["samples"] for x in res["sessions"]) + res["not_decided"] + res["samples_before_hello"] \
        == res["samples"]
    # a recording's warning is in the JSON, not on stderr only (m/s^2 read as g)
    cols = read_log(sim_log)
    ms2 = tmp_path / "ms2.csv"
    write_log(ms2, {**cols.columns, **{k: cols[k] * 9.80665 for k in ("ax", "ay", "az")}},
              {k: v for k, v in cols.metadata.items() if k != "units"})
    assert main(["replay", str(ms2), "--json", str(out)]) == 0
    assert any("m/s^2" in w for w in json.loads(out.read_text())["warnings"])
    assert main(["replay", str(tmp_path / "missing.csv")]) == 2
    assert "missing.csv" in capsys.readouterr().err


def test_replay_link_kind_is_registered_and_checked(sim_log: Path) -> None:
    ring = RingBuffer(1 << 14)
    got: list[object] = []
    with pytest.raises(ConfigError, match="field 'path' missing"):
        open_link({"kind": "replay"}, ring, got.append, where="cfg: link")
    with pytest.raises(ConfigError, match="unknown field 'rate'"):
        open_link({"kind": "replay", "path": str(sim_log), "rate": 3}, ring, got.append, where="cfg: link")
    link = open_link({"kind": "replay", "path": str(sim_log), "speed": 50.0}, ring, got.append)
    try:
        deadline = time.monotonic() + 10
        while ring.pushed < 400 and time.monotonic() < deadline:
            time.sleep(0.01)
        link.send(CoeffRead())
    finally:
        link.stop()
    assert ring.pushed >= 400 and isinstance(got[0], Hello) and got[0].serial == 31
    assert isinstance(got[-1], CoeffReport) and got[-1].version == 0  # a sample log: no set applied


@pytest.mark.slow
def test_pty_player_feeds_a_serial_link_and_answers_it(sim_log: Path, tmp_path: Path) -> None:
    from gyrocal.replay.pty_player import play_pty

    rec = open_recording(str(sim_log))
    path: list[str] = []
    stop = threading.Event()
    result: dict = {}
    player = threading.Thread(target=lambda: result.update(play_pty(
        rec, None, speed=20.0, linger_s=0.5, announce=path.append, should_stop=stop.is_set)), daemon=True)
    player.start()
    deadline = time.monotonic() + 10
    while not path and time.monotonic() < deadline:
        time.sleep(0.01)
    ring = RingBuffer(1 << 16)
    got: list[object] = []
    link = open_link({"kind": "serial", "url": path[0]}, ring, got.append)
    try:
        link.send(HelloRequest())
        link.send(CoeffRead())
        while (ring.pushed < 1000 or not any(isinstance(m, CoeffReport) for m in got)) \
                and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stop.set()
        link.stop()
        player.join(10)
    assert ring.pushed >= 1000 and any(isinstance(m, Hello) and m.serial == 31 for m in got)
    assert any(isinstance(m, CoeffReport) for m in got) and result["answers"] >= 1


@pytest.mark.slow
def test_bus_player_feeds_a_can_link_and_answers_it(sim_log: Path) -> None:
    from gyrocal.replay.pty_player import play_bus

    rec = open_recording(str(sim_log))
    channel = f"h11-replay-{time.monotonic_ns()}"
    bus = {"interface": "virtual", "channel": channel}
    ring = RingBuffer(1 << 16)
    got: list[object] = []
    link = open_link({"kind": "can", "bus": bus}, ring, got.append)  # listening before the unit talks
    stop = threading.Event()
    result: dict = {}
    player = threading.Thread(target=lambda: result.update(play_bus(
        rec, bus, speed=20.0, linger_s=0.5, announce=lambda _: None, should_stop=stop.is_set)), daemon=True)
    player.start()
    deadline = time.monotonic() + 10
    try:
        while ring.pushed < 200 and time.monotonic() < deadline:
            time.sleep(0.01)
        link.send(CoeffRead())
        while not any(isinstance(m, CoeffReport) for m in got) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stop.set()
        link.stop()
        player.join(10)
    assert ring.pushed >= 200 and isinstance(got[0], Hello) and got[0].serial == 31
    assert any(isinstance(m, CoeffReport) for m in got) and result["answers"] >= 1


@pytest.mark.slow
def test_a_csv_is_streamed_block_by_block_with_the_same_result(sim_log: Path, tmp_path: Path) -> None:
    from gyrocal.logformat import read_log
    from gyrocal.readers.csvstream import CsvStream
    from gyrocal.replay.source import Recording

    text = sim_log.read_text().splitlines()
    text[500] = ",".join(["nan"] * len(text[500].split(",")))  # a NaN row in the first block
    path = tmp_path / "nan.csv"
    path.write_text("\n".join(text) + "\n")
    whole = read_log(path)
    stream = CsvStream(str(path), block_rows=1000)
    blocks = list(stream.blocks())
    for c in ("t", "wx", "az", "temp", "session"):
        np.testing.assert_array_equal(np.concatenate([b[c] for b in blocks]), whole[c])
    assert stream.dropped == {"nonfinite": 1} == whole.dropped
    streamed = replay(open_recording(str(path)), _cfg(tmp_path))
    held = replay(Recording(str(path), "csv", log=whole), _cfg(tmp_path))
    for key in ("decisions", "validations", "pushes", "samples", "dropped"):
        assert streamed[key] == held[key], key
    bad = tmp_path / "back.csv"
    rows = ["t,wx,wy,wz,ax,ay,az"] + [f"{i / 100},0,0,0,0,0,1" for i in range(30)] + ["0.05,0,0,0,0,0,1"]
    bad.write_text("\n".join(rows) + "\n")
    with pytest.raises(LogFormatError, match="goes backwards"):
        list(CsvStream(str(bad), block_rows=30).blocks())


def test_a_sample_logs_sessions_are_sent_with_unit_time_since_their_switch_on(tmp_path: Path) -> None:
    """The wire's unit time is since switch-on (docs/protocol.md); a log's t need not be.

    A replayed session starts at 0 s, as `gyrocal analyze` takes t_on from each session's first
    sample: a held or learnt exp(-t_on/TAU) then means the same to the unit, the daemon and analyze.
    """
    from gyrocal.readers import read_any
    from gyrocal.replay.source import Recording

    n = 5000  # two blocks and a bit per session
    t = np.concatenate([500.0 + np.arange(n) / 100, 1200.0 + np.arange(n) / 100])
    cols = {c: np.zeros(2 * n) for c in COLS} | {"t": t, "az": np.ones(2 * n),
                                                  "session": np.repeat([0.0, 1.0], n)}
    path = tmp_path / "late.csv"
    write_log(path, cols, {})
    streamed = open_recording(str(path))
    whole = Recording(str(path), "csv", log=read_any(str(path), "csv"))
    for rec in (streamed, whole):
        sessions: list[list[np.ndarray]] = []
        for kind, ev in rec.events():
            if kind == "msg":
                assert isinstance(ev, Hello) and ev.rate_hz == 100
                sessions.append([])
            else:
                sessions[-1].append(ev)
        assert len(sessions) == 2
        for blocks in sessions:
            got = np.concatenate([b["t"] for b in blocks])
            np.testing.assert_allclose(got, np.arange(n) / 100, atol=1e-9)
            assert np.array_equal(np.concatenate([b["seq"] for b in blocks]), np.arange(n))


def test_the_replayed_unit_applies_a_pushed_dtemp_term_with_the_protocols_rule() -> None:
    """dtemp is the unit's rule (protocol.md, section 6) that the daemon rebuilds, not another fit."""
    from gyrocal.daemon.ring import SAMPLE_DTYPE
    from gyrocal.protocol.messages import CoeffAck, CoeffWrite
    from gyrocal.protocol.termsets import TempRate, names_for
    from gyrocal.replay.unit import ReplayUnit

    names = list(names_for(0x549E))
    unit = ReplayUnit(Hello(1, "1.0.0", 1), CoeffReport(3, 0x549E, [[0.0] * 14] * 3))
    n = 400 * 30
    block = np.zeros(n, dtype=SAMPLE_DTYPE)
    block["t"] = np.arange(n) / 400
    block["az"] = 1.0
    block["temp"] = np.round((25 + 8 * (1 - np.exp(-block["t"] / 40))) / 0.01) * 0.01  # a warm-up
    unit.output(block[:4000])  # the unit runs before the push: its rule runs from switch-on
    pushed = [[0.0] * 12 + [0.02, 0.0], [0.0] * 14, [0.0] * 14]  # deg/s per degC/s on x
    assert isinstance(unit.answer(CoeffWrite(4, 0x549E, pushed))[0], CoeffAck)
    out = np.concatenate([unit.output(block[i:i + 1000]) for i in range(4000, n, 1000)])
    dtemp = TempRate().update(block["t"], block["temp"])[4000:]
    assert names[12] == "dtemp" and np.max(np.abs(dtemp)) > 0.05  # degC/s
    np.testing.assert_allclose(out["wx"], -0.02 * dtemp, rtol=0, atol=1e-12)


def test_a_link_capture_started_late_keeps_the_units_time_since_switch_on(tmp_path: Path) -> None:
    """A capture that starts 100 s after the switch-on: t_on is 100 s at its first sample, in the
    analysis (derived_columns) and on the replayed wire, also once converted to CSV."""
    from gyrocal.model.terms import derived_columns, from_switch_on
    from gyrocal.protocol.messages import Sample
    from gyrocal.readers.stream import messages_to_log

    msgs = [Hello(9, "1.0.0", 3, 100)]
    msgs += [Sample(10_000 + i, 100.0 + i / 100, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 25.0) for i in range(300)]
    log = messages_to_log(msgs, "capture")
    assert from_switch_on(log.metadata)
    t_on = derived_columns(log.columns, t_from_switch_on=True)["t_on"]
    np.testing.assert_allclose(t_on[[0, -1]], [100.0, 102.99])
    path = tmp_path / "capture.csv"
    write_log(path, log.columns, log.metadata)
    sent = np.concatenate([b["t"] for kind, b in open_recording(str(path)).events() if kind == "samples"])
    np.testing.assert_allclose(sent[[0, -1]], [100.0, 102.99])
