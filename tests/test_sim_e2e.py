"""End to end: virtual unit (own process) -> pty -> SerialLink -> ring buffer at 2 kHz for 10 s."""

from pathlib import Path

import numpy as np
import pytest
from sim_helpers import SimProcess, read_status, wait_for

from gyrocal.daemon.ring import RingBuffer
from gyrocal.drivers import SerialLink
from gyrocal.protocol.messages import Hello

RATE_HZ = 2000
SECONDS = 10
N = RATE_HZ * SECONDS


@pytest.mark.slow
def test_sim_2khz_for_10s_over_pty_delivers_every_sample_in_order(tmp_path: Path) -> None:
    status = tmp_path / "sim.json"
    ring = RingBuffer(4096)  # 2 s of slack: the consumer below drains it as a daemon would
    boundary: dict[int, int] = {}

    def on_control(msg: object) -> None:
        if isinstance(msg, Hello):
            boundary[msg.boot_count] = ring.pushed  # exact: called on the reader thread in stream order

    chunks: list[np.ndarray] = []
    with SimProcess("--rate", str(RATE_HZ), "--seed", "11", "--status-json", str(status),
                    tmp_path=tmp_path) as sim:
        with SerialLink(sim.address, ring, on_control) as link:
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
    assert stats["errors"]["crc_errors"] == 0 and stats["errors"]["lost_samples"] == 0
    assert stats["errors"]["seq_gaps"] == 0 and sent["transport"]["tx_dropped_frames"] == 0
