"""Serial link: pyserial URLs in one process, and the virtual unit across processes over a pty pair."""

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import SerialLink, open_link
from gyrocal.errors import ConfigError, LinkError
from gyrocal.protocol import termsets
from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffRead,
    CoeffReport,
    CoeffWrite,
    Hello,
    Sample,
    coeff_set_crc,
)
from gyrocal.sim.truth import TruthModel
from tests.sim_helpers import SimProcess, read_status, wait_for


class Recorder:
    """on_control / on_event sink that also notes ring.pushed at each HELLO (the session boundary)."""

    def __init__(self, ring: RingBuffer) -> None:
        self.ring, self.control, self.events = ring, [], []
        self.boundaries: dict[int, int] = {}
        self.lock = threading.Lock()

    def on_control(self, msg: object) -> None:
        with self.lock:
            self.control.append(msg)
            if isinstance(msg, Hello):
                self.boundaries[msg.boot_count] = self.ring.pushed

    def on_event(self, name: str, detail: str) -> None:
        self.events.append(name)

    def of(self, cls: type) -> list:
        with self.lock:
            return [m for m in self.control if isinstance(m, cls)]


def _write(version: int = 1) -> CoeffWrite:
    return CoeffWrite(version, termsets.SEED000_ID, TruthModel().coeffs_dps.tolist())


def _sample(i: int) -> Sample:
    return Sample(i, i / 100, (0.001 * i, 0.0, -0.5), (0.0, 0.0, 1.0), 25.0)


def test_serial_link_loop_url_sends_and_decodes_in_one_process() -> None:
    ring = RingBuffer(100)
    rec = Recorder(ring)
    with SerialLink("loop://", ring, rec.on_control, rec.on_event) as link:
        for i in range(20):
            link.send(_sample(i))
        link.send(_write())
        assert wait_for(lambda: ring.pushed == 20 and rec.of(CoeffWrite))
        st = link.stats()
    out = ring.pop()
    assert out["seq"].tolist() == list(range(20))
    np.testing.assert_allclose(out["wx"], 0.001 * np.arange(20), atol=1e-6)
    assert rec.of(CoeffWrite)[0] == _write()
    assert st["frames"] == 21 and st["samples"] == 20 and st["errors"]["crc_errors"] == 0
    assert rec.events == ["link_up"]


def test_serial_link_callback_errors_are_counted_apart_and_do_not_stop_the_reader() -> None:
    ring = RingBuffer(100)

    def boom(msg: object) -> None:
        raise RuntimeError("daemon bug")

    with SerialLink("loop://", ring, boom) as link:
        link.send(CoeffRead())
        link.send(_sample(0))
        link.send(CoeffRead())
        link.send(_sample(1))
        assert wait_for(lambda: ring.pushed == 2 and link.stats()["errors"]["callback_errors"] == 2)
        st = link.stats()
    assert st["errors"]["io_errors"] == 0 and st["reconnects"] == 0


def test_serial_link_stop_is_idempotent_and_send_after_stop_fails_cleanly() -> None:
    link = SerialLink("loop://", RingBuffer(10), lambda m: None)
    link.start()
    link.stop()
    link.stop()
    assert not link.connected
    with pytest.raises(LinkError, match="down"):
        link.send(CoeffRead())


def test_serial_link_unknown_port_gives_one_line_error_naming_port_and_fix() -> None:
    with pytest.raises(LinkError) as info:
        open_link({"kind": "serial", "url": "/dev/ttyGYRO_NOPE"}, RingBuffer(10), lambda m: None)
    text = str(info.value)
    assert "\n" not in text and "/dev/ttyGYRO_NOPE" in text and "check" in text


@pytest.mark.parametrize(
    "cfg, needle",
    [
        ({"url": "/dev/ttyUSB0"}, "field 'kind'"),
        ({"kind": "serial"}, "field 'url' missing"),
        ({"kind": "serial", "url": "/dev/ttyUSB0", "baudrate": "fast"}, "'baudrate'"),
        ({"kind": "serial", "url": "/dev/ttyUSB0", "speed": 9600}, "unknown field 'speed'"),
        ({"kind": "serial", "url": "loop://", "backoff_max_s": -1}, "'backoff_max_s'"),
        ({"kind": "can", "bus": {"channel": "can0"}}, '"interface" missing'),
        ({"kind": "can", "interface": "no_such_iface"}, "not a python-can interface"),
        ("serial", "must be a mapping"),
    ],
)
def test_open_link_broken_config_gives_one_line_config_error(cfg: object, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle) as info:
        open_link(cfg, RingBuffer(10), lambda m: None, where="gyrocal.yaml: link")  # type: ignore[arg-type]
    assert "\n" not in str(info.value) and str(info.value).startswith("gyrocal.yaml: link")


def test_serial_pty_across_processes_streams_acks_and_reports(tmp_path: Path) -> None:
    status = tmp_path / "sim.json"
    with SimProcess("--rate", "500", "--seed", "3", "--status-json", str(status), tmp_path=tmp_path) as sim:
        ring = RingBuffer(20_000)
        rec = Recorder(ring)
        with SerialLink(sim.address, ring, rec.on_control, rec.on_event) as link:
            sim.power_cycle()  # HELLO of boot 2 reaches us: a clean session start
            assert wait_for(lambda: 2 in rec.boundaries)
            assert wait_for(lambda: ring.pushed - rec.boundaries[2] >= 300)
            write = _write(7)
            link.send(write)
            assert wait_for(lambda: rec.of(CoeffAck))
            link.send(CoeffRead())
            assert wait_for(lambda: rec.of(CoeffReport))
            assert wait_for(lambda: read_status(status).get("applied_version") == 7)
            st = link.stats()
        out = ring.pop()
    assert rec.of(CoeffAck)[0] == CoeffAck(7, coeff_set_crc(7, write.terms_id, write.coeffs_dps))
    rep = rec.of(CoeffReport)[0]
    assert rep.version == 7 and rep.terms_id == termsets.SEED000_ID
    np.testing.assert_allclose(rep.coeffs_dps, write.coeffs_dps)
    assert ring.lost == 0 and len(out) == ring.pushed
    boot2 = out[rec.boundaries[2] :]
    assert boot2["seq"][:300].tolist() == list(range(300))
    np.testing.assert_allclose(boot2["t"][:300], np.arange(300) / 500.0)
    assert st["errors"]["crc_errors"] == 0 and st["drops"] == 0
    doc = read_status(status)
    assert doc["boot_count"] == 2 and set(doc["drift_rms_compensated_dps"]) == {"x", "y", "z"}


def test_serial_link_reconnects_when_the_unit_goes_away_and_comes_back(tmp_path: Path) -> None:
    link_path = tmp_path / "gyro0"
    ring = RingBuffer(50_000)
    rec = Recorder(ring)
    link = SerialLink(str(link_path), ring, rec.on_control, rec.on_event, backoff_initial_s=0.05,
                      backoff_max_s=0.2)
    link.start(wait=False)  # the daemon starts before the unit: it retries
    try:
        assert wait_for(lambda: "reconnecting" in rec.events)
        with SimProcess("--rate", "300", "--pty-link", str(link_path), tmp_path=tmp_path):
            assert wait_for(lambda: link.connected and ring.pushed > 50)
        assert wait_for(lambda: "link_lost" in rec.events)
        before = ring.pushed
        with SimProcess("--rate", "300", "--pty-link", str(link_path), tmp_path=tmp_path):
            assert wait_for(lambda: ring.pushed > before + 50)
            st = link.stats()
    finally:
        link.stop()
    assert st["reconnects"] == 1 and st["errors"]["io_errors"] >= 1
    assert rec.events.count("link_up") == 2


def test_serial_garbage_from_the_unit_is_counted_and_no_sample_is_lost(tmp_path: Path) -> None:
    with SimProcess("--rate", "500", "--garbage-rate", "0.3", "--seed", "1", tmp_path=tmp_path) as sim:
        ring = RingBuffer(20_000)
        with SerialLink(sim.address, ring, lambda m: None) as link:
            assert wait_for(lambda: ring.pushed >= 400)
            st = link.stats()
    seq = ring.pop()["seq"].astype(int)
    assert np.all(np.diff(seq) == 1)
    assert st["errors"]["garbage_bytes"] > 0 and st["errors"]["lost_samples"] == 0


def test_a_port_this_user_may_not_open_gets_the_permission_advice(monkeypatch) -> None:
    """EACCES said "check that the unit is plugged in" first (an operator's audit): the port is there."""
    import serial as pyserial

    def denied(url: str, **kw: object) -> None:
        why = f"could not open port {url}: [Errno 13] Permission denied: '{url}'"
        raise pyserial.SerialException(13, why)

    monkeypatch.setattr(pyserial, "serial_for_url", denied)
    link = SerialLink("/dev/ttyUSB7", RingBuffer(10), lambda m: None)
    with pytest.raises(LinkError) as err:
        link._open()
    assert "Permission denied" in str(err.value) and "may not open it" in str(err.value)
    assert "plugged in" not in str(err.value)


def test_a_second_daemon_does_not_take_the_port_at_a_replug(tmp_path: Path, monkeypatch) -> None:
    """The exclusive open held the port only while it was open: at a replug, a second daemon with its
    own store could open the new tty first and calibrate the unit against that store (an outside
    audit). The first claims the configured path for its life; the second waits, saying who holds it,
    and takes the port once the first stops."""
    monkeypatch.setenv("GYROCAL_LOCK_DIR", str(tmp_path))
    link_path = tmp_path / "gyro0"
    ring_a, ring_b = RingBuffer(50_000), RingBuffer(50_000)
    rec_a, rec_b = Recorder(ring_a), Recorder(ring_b)
    kw = {"backoff_initial_s": 0.05, "backoff_max_s": 0.2}
    a = SerialLink(str(link_path), ring_a, rec_a.on_control, rec_a.on_event, **kw)
    b = SerialLink(str(link_path), ring_b, rec_b.on_control, lambda n, d: rec_b.events.append(d), **kw)
    a.start(wait=False)
    try:
        with SimProcess("--rate", "300", "--pty-link", str(link_path), tmp_path=tmp_path):
            assert wait_for(lambda: a.connected and ring_a.pushed > 50)
            b.start(wait=False)
            assert wait_for(lambda: any("claimed by another gyrocal daemon" in e for e in rec_b.events))
            # a daemon that names the device itself, not the udev symlink (took it once in 6 replugs:
            # an operator's re-check)
            said: list[str] = []
            c = SerialLink(os.path.realpath(link_path), RingBuffer(100), lambda m: None,
                           lambda n, d: said.append(d), **kw)
            c.start(wait=False)
            try:
                assert wait_for(lambda: any("claimed by another gyrocal daemon" in e for e in said))
                assert not c.connected
            finally:
                c.stop()
        assert wait_for(lambda: "link_lost" in rec_a.events)
        before = ring_a.pushed
        with SimProcess("--rate", "300", "--pty-link", str(link_path), tmp_path=tmp_path):  # the replug
            assert wait_for(lambda: ring_a.pushed > before + 50)
            assert ring_b.pushed == 0 and not b.connected
            a.stop()
            assert wait_for(lambda: b.connected and ring_b.pushed > 50)
    finally:
        a.stop()
        b.stop()
    assert f"pid {os.getpid()}" in " ".join(rec_b.events)


def test_a_port_is_claimed_in_run_lock_under_its_configured_path(monkeypatch) -> None:
    """The claim's name is the configured path (a udev symlink stays the same across a replug); a URL
    that is not a device has none."""
    from gyrocal.drivers.serial_link import _claim_path

    monkeypatch.delenv("GYROCAL_LOCK_DIR", raising=False)
    assert str(_claim_path("/dev/gyrocal-imu")) == "/run/lock/gyrocal-dev_gyrocal-imu.lock"
    assert _claim_path("socket://127.0.0.1:5000") is None and _claim_path("loop://") is None
