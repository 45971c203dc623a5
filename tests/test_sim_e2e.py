"""End to end: virtual unit (own process) -> link -> driver -> ring buffer at 2 kHz for 10 s.

Over a pty pair (SerialLink) and over python-can udp_multicast (CanLink, 6000 frames/s). The
daemon side starts listening, power-cycles the unit (SIGUSR1) so that it sees a session from its
HELLO and first sample, then drains the ring as the daemon would until 20000 samples arrived.
"""

from pathlib import Path

import numpy as np
import pytest

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import CanLink, SerialLink
from gyrocal.drivers.base import Link
from gyrocal.protocol.messages import Hello
from tests.sim_helpers import SimProcess, free_udp_port, multicast_works, read_status, wait_for

RATE_HZ = 2000
SECONDS = 10
N = RATE_HZ * SECONDS
GROUP = "239.74.163.2"


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pty", "can_udp_multicast"])
def test_sim_2khz_for_10s_delivers_every_sample_in_order(tmp_path: Path, kind: str) -> None:
    status = tmp_path / "sim.json"
    ring = RingBuffer(4096)  # 2 s of slack: the consumer below drains it as a daemon would
    boundary: dict[int, int] = {}

    def on_control(msg: object) -> None:
        if isinstance(msg, Hello):
            boundary[msg.boot_count] = ring.pushed  # exact: called on the reader thread in stream order

    args = ["--rate", str(RATE_HZ), "--seed", "11", "--status-json", str(status)]
    if kind != "pty":
        port = free_udp_port()
        if not multicast_works(port):
            pytest.skip("no IPv4 multicast route on this host (udp_multicast cannot loop back)")
        args += ["--link", "can", "--can-interface", "udp_multicast", "--can-channel", GROUP,
                 "--can-port", str(port)]
    chunks: list[np.ndarray] = []
    with SimProcess(*args, tmp_path=tmp_path) as sim:
        bus = {"interface": "udp_multicast", "channel": GROUP, "port": port} if kind != "pty" else {}
        link: Link = SerialLink(sim.address, ring, on_control) if not bus else CanLink(bus, ring, on_control)
        with link:
            sim.power_cycle()  # start a session we see from its first sample (HELLO, seq 0)
            assert wait_for(lambda: 2 in boundary, 30)

            def drained_enough() -> bool:
                chunks.append(ring.pop())
                return ring.popped - boundary[2] >= N

            assert wait_for(drained_enough, timeout_s=120, poll_s=0.02)
            stats = link.stats()
        sent = read_status(status)
    out = np.concatenate(chunks)[boundary[2] :][:N]
    assert ring.lost == 0 and stats["drops"] == 0
    seq = out["seq"].astype(np.int64)
    gaps = [(int(seq[i]), int(seq[i + 1])) for i in np.flatnonzero(np.diff(seq) != 1)[:5]]
    assert seq.tolist() == list(range(N)), f"gaps {gaps}; link {stats}; sim {sent.get('transport')}"
    np.testing.assert_array_equal(out["t"], np.arange(N) / RATE_HZ)  # unit clock from the index
    assert np.all(np.diff(out["rx"]) >= 0)
    errors = stats["errors"]
    assert errors["crc_errors"] == 0 and errors["lost_samples"] == 0 and errors["seq_gaps"] == 0
    assert errors["incomplete"] == 0
