"""A unit on CAN node 3: the daemon's link set to node 3 hears it; one left on node 0 counts it foreign."""

from __future__ import annotations

import threading

import pytest

from gyrocal.daemon.config import load_config
from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import open_link
from gyrocal.errors import ConfigError
from gyrocal.protocol.messages import CoeffRead, CoeffReport, Hello
from gyrocal.sim.runner import Runner
from gyrocal.sim.schedule import tumble
from gyrocal.sim.transports import CanTransport
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import VirtualUnit
from tests.sim_helpers import wait_for


def _run(node_unit: int, node_link: int) -> tuple[RingBuffer, list[object], dict]:
    channel = f"gyrocal-node-{node_unit}-{node_link}-{threading.get_ident()}"
    ring = RingBuffer(10_000)
    msgs: list[object] = []
    listen = open_link({"kind": "can", "node_id": node_link,
                        "bus": {"interface": "virtual", "channel": channel}}, ring, msgs.append, None)
    unit = VirtualUnit(TruthModel(), tumble(), 500.0, 2, serial=33)
    transport = CanTransport({"interface": "virtual", "channel": channel}, node_id=node_unit)
    runner = Runner(unit, transport, duration_s=1.0, linger_s=1.0)
    th = threading.Thread(target=runner.run)
    try:
        th.start()
        wait_for(lambda: ring.pushed >= 100, 10)
        listen.send(CoeffRead())
        th.join(30)
        if node_unit == node_link:
            wait_for(lambda: ring.pushed == 500 and any(isinstance(m, CoeffReport) for m in msgs), 10)
        st = listen.stats()
    finally:
        runner.request_stop()
        th.join(10)
        listen.stop()
        transport.close()
    return ring, msgs, st


def test_a_unit_on_node_3_is_heard_by_a_link_on_node_3() -> None:
    ring, msgs, st = _run(3, 3)
    assert ring.pushed == 500 and ring.lost == 0
    assert [m.serial for m in msgs if isinstance(m, Hello)] == [33]
    assert any(isinstance(m, CoeffReport) for m in msgs)  # it answered our COEFF_READ on node 3
    assert st["errors"]["foreign_frames"] == 0


def test_a_link_on_node_0_counts_a_node_3_unit_as_foreign_frames() -> None:
    ring, msgs, st = _run(3, 0)
    assert ring.pushed == 0 and not msgs
    assert st["errors"]["foreign_frames"] >= 3 * 500  # three frames per sample, all another node's


def test_the_node_id_is_a_checked_config_field(tmp_path) -> None:
    cfg = load_config(None, {"state_dir": str(tmp_path), "control_socket": str(tmp_path / "c"),
                             "link.can_node_id": 3})
    assert cfg.link["can_node_id"] == 3
    with pytest.raises(ConfigError, match="link.can_node_id"):
        load_config(None, {"state_dir": str(tmp_path), "link.can_node_id": 16})
