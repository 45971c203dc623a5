"""CAN link: the virtual unit over python-can ``virtual`` in one process, ``udp_multicast`` across two."""

import socket
import threading
from pathlib import Path

import can
import numpy as np
import pytest

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import CanLink, open_link
from gyrocal.errors import ConfigError, LinkError
from gyrocal.protocol import termsets
from gyrocal.protocol.messages import CoeffAck, CoeffRead, CoeffReport, CoeffWrite, Hello, coeff_set_crc
from gyrocal.sim.runner import Runner
from gyrocal.sim.schedule import tumble
from gyrocal.sim.transports import CanTransport
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import VirtualUnit
from tests.sim_helpers import SimProcess, free_udp_port, multicast_works, read_status, wait_for

GROUP = "239.74.163.2"
_REAL_BUS = can.Bus


def _write(version: int = 1) -> CoeffWrite:
    return CoeffWrite(version, termsets.SEED000_ID, TruthModel().coeffs_dps.tolist())


class Sink:
    def __init__(self, ring: RingBuffer) -> None:
        self.ring, self.msgs, self.events, self.boundaries = ring, [], [], {}

    def on_control(self, msg: object) -> None:
        self.msgs.append(msg)
        if isinstance(msg, Hello):
            self.boundaries[msg.boot_count] = self.ring.pushed

    def on_event(self, name: str, detail: str) -> None:
        self.events.append(name)

    def of(self, cls: type) -> list:
        return [m for m in list(self.msgs) if isinstance(m, cls)]


def test_can_virtual_bus_in_one_process_delivers_every_sample_and_acks() -> None:
    channel = f"gyrocal-test-{threading.get_ident()}"
    ring = RingBuffer(10_000)
    sink = Sink(ring)
    link = open_link({"kind": "can", "bus": {"interface": "virtual", "channel": channel}}, ring,
                     sink.on_control, sink.on_event)
    unit = VirtualUnit(TruthModel(), tumble(), 1000.0, 2, serial=77)
    transport = CanTransport({"interface": "virtual", "channel": channel})
    runner = Runner(unit, transport, duration_s=1.5, linger_s=1.0)
    th = threading.Thread(target=runner.run)
    try:
        th.start()
        assert wait_for(lambda: ring.pushed >= 200)
        link.send(_write(3))
        link.send(CoeffRead())
        th.join(30)
        assert wait_for(lambda: ring.pushed == 1500 and sink.of(CoeffReport))
        st = link.stats()
    finally:
        runner.request_stop()
        th.join(10)
        link.stop()
        transport.close()
    out = ring.pop()
    assert out["seq"].tolist() == list(range(1500)) and ring.lost == 0
    np.testing.assert_allclose(out["t"], np.arange(1500) / 1000.0)
    assert sink.of(Hello)[0].serial == 77
    w = _write(3)
    assert sink.of(CoeffAck) == [CoeffAck(3, coeff_set_crc(3, w.terms_id, w.coeffs_dps))]
    assert sink.of(CoeffReport)[0].version == 3
    assert st["errors"]["incomplete"] == 0 and st["errors"]["lost_samples"] == 0


def test_can_udp_multicast_across_processes_streams_and_acks(tmp_path: Path) -> None:
    port = free_udp_port()  # a distinct port per test run: parallel runs do not hear each other
    if not multicast_works(port):
        pytest.skip("no IPv4 multicast route on this host (udp_multicast cannot loop back)")
    status = tmp_path / "sim.json"
    args = ("--link", "can", "--can-interface", "udp_multicast", "--can-channel", GROUP,
            "--can-port", str(port), "--rate", "500", "--status-json", str(status))
    ring = RingBuffer(20_000)
    sink = Sink(ring)
    with SimProcess(*args, tmp_path=tmp_path) as sim:
        assert f"port={port}" in sim.address
        bus = {"interface": "udp_multicast", "channel": GROUP, "port": port}
        with CanLink(bus, ring, sink.on_control, sink.on_event) as link:
            sim.power_cycle()
            assert wait_for(lambda: 2 in sink.boundaries)
            assert wait_for(lambda: ring.pushed - sink.boundaries[2] >= 300)
            link.send(_write(4))
            assert wait_for(lambda: sink.of(CoeffAck))
            assert wait_for(lambda: read_status(status).get("applied_version") == 4)
            st = link.stats()
    out = ring.pop()
    boot2 = out[sink.boundaries[2] :]
    assert boot2["seq"][:300].tolist() == list(range(300))
    assert not sink.of(CoeffWrite)  # our own looped-back frames are not decoded
    assert st["echo_frames"] > 0 and st["errors"]["incomplete"] == 0


class _FlakyBus(can.BusABC):
    """Wraps a virtual bus; the first ``fail`` recv calls raise as a vanished interface would."""

    fail = 1

    def __init__(self, channel: str, **kw: object) -> None:
        self._inner = _REAL_BUS(interface="virtual", channel=channel)
        super().__init__(channel=channel)

    def _recv_internal(self, timeout: float | None):  # type: ignore[override]
        if _FlakyBus.fail > 0:
            _FlakyBus.fail -= 1
            raise can.CanOperationError("interface went down")
        return self._inner.recv(timeout), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


def test_can_link_reconnects_after_a_bus_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def fake_bus(**kw: object) -> can.BusABC:
        return _FlakyBus(**kw) if kw.get("interface") == "virtual" else _REAL_BUS(**kw)

    monkeypatch.setattr(can, "Bus", fake_bus)
    _FlakyBus.fail = 1
    channel = "gyrocal-flaky"
    ring = RingBuffer(1000)
    sink = Sink(ring)
    sender = _REAL_BUS(interface="virtual", channel=channel)
    link = CanLink({"interface": "virtual", "channel": channel}, ring, sink.on_control, sink.on_event,
                   backoff_initial_s=0.01)
    try:
        link.start()
        assert wait_for(lambda: sink.events.count("link_up") == 2)
        unit = VirtualUnit(TruthModel(), tumble(), 100.0, 0, serial=1)
        unit.power_on()
        from gyrocal.protocol.can_codec import CanCodec

        codec = CanCodec()
        for s in unit.samples(20):
            for f in codec.encode(s):
                sender.send(f)
        assert wait_for(lambda: ring.pushed == 20)
        st = link.stats()
    finally:
        link.stop()
        sender.shutdown()
    assert sink.events[:3] == ["link_up", "link_lost", "link_up"]
    assert st["reconnects"] == 1 and st["errors"]["io_errors"] == 1


def test_can_bus_that_cannot_open_gives_one_line_link_error() -> None:
    with pytest.raises(LinkError) as info:
        open_link({"kind": "can", "interface": "udp_multicast", "channel": "not-an-address"}, RingBuffer(10),
                  lambda m: None)
    assert "\n" not in str(info.value) and "cannot be opened" in str(info.value)


def test_can_config_unknown_interface_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="no_such"):
        CanLink({"interface": "no_such"}, RingBuffer(10), lambda m: None)


def test_free_udp_port_is_bindable() -> None:
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", port))


def _looped_back_link(name: str) -> tuple[CanLink, str]:
    """A CAN link on a virtual bus of its own that loops its sends back to it (receive_own_messages),
    as udp_multicast does; returns it with the bus's channel name."""
    channel = f"gyrocal-test-{name}-{threading.get_ident()}"
    ring = RingBuffer(1000)
    sink = Sink(ring)
    link = open_link({"kind": "can", "bus": {"interface": "virtual", "channel": channel,
                                             "receive_own_messages": True}}, ring,
                     sink.on_control, sink.on_event)
    return link, channel


def test_another_hosts_frames_to_the_unit_are_counted_and_said(caplog: pytest.LogCaptureFixture) -> None:
    """Two daemons on one bus minted the same version for different sets and overwrote each other's
    pushes, and neither noticed (an integrator's fault campaign). Host-to-unit frames this link did
    not send are another host's: counted, and one WARNING says so. Its own looped-back frames are not."""
    from gyrocal.protocol.can_codec import CanCodec

    link, channel = _looped_back_link("hosts")
    other = can.Bus(interface="virtual", channel=channel)
    try:
        assert wait_for(lambda: link.connected, 5)
        link.send(CoeffRead())  # looped back to its own bus (receive_own_messages): an echo
        assert wait_for(lambda: link.stats().get("echo_frames", 0) >= 1, 5), link.stats()
        caplog.clear()
        for frame in CanCodec().encode(CoeffRead()):
            other.send(frame)
        assert wait_for(lambda: link.stats().get("other_host_frames", 0) >= 1, 5), link.stats()
        assert link.stats()["echo_frames"] >= 1
        assert sum("another host is talking to the unit" in r.getMessage() for r in caplog.records) == 1
    finally:
        other.shutdown()
        link.stop()


def test_a_write_resent_many_times_is_never_taken_for_another_host() -> None:
    """A unit NAKed the same set BUSY ten times: from the 6th write on, the daemon's own frames came back
    as "another host is talking to the unit" (an integrator's campaign, 3 runs of 3). The echoes of
    identical frames resent past the link's window of frames sent are still its own."""
    from gyrocal.drivers import can_link

    link, _ = _looped_back_link("resend")
    write = CoeffWrite(2, termsets.SEED000_ID, np.full((3, 10), 1e-3).tolist())
    try:
        assert wait_for(lambda: link.connected, 5)
        sent = 0
        while sent <= 3 * can_link.SENT_KEPT:
            link.send(write)
            sent += len(link._codec.encode(write))
            assert wait_for(lambda n=sent: link.stats()["echo_frames"] == n, 5), link.stats()
        assert link.stats()["other_host_frames"] == 0
    finally:
        link.stop()
