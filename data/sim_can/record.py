"""Record the virtual unit's CAN traffic with python-can's own ``can.Logger`` (data/PROVENANCE.md).

Runs ``gyrocal sim --link can`` on a udp_multicast bus for DURATION s of samples, asks the unit
who it is (HELLO_REQUEST) and which set it holds (COEFF_READ) as a daemon would, and writes every
frame on the bus, the host's included, to OUT (.blf, .asc, .log: by extension).

    python data/sim_can/record.py data/sim_can/virtual_unit.blf --duration 40 --rate 100
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import can

from gyrocal.protocol.can_codec import CanCodec
from gyrocal.protocol.messages import CoeffRead, HelloRequest
from gyrocal.protocol.termsets import terms_id


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--duration", type=float, default=40.0)
    p.add_argument("--rate", type=float, default=100.0)
    p.add_argument("--seed", type=int, default=7)
    a = p.parse_args()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        port = s.getsockname()[1]
    flash = Path(a.out).with_suffix(".flash.json")
    # the unit holds a small bias set, so the recording's output is compensated (as in the field)
    names = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]
    rows = [[b] + [0.0] * (len(names) - 1) for b in (0.002, -0.001, 0.0005)]
    flash.write_text(json.dumps({"boot_count": 2, "applied": {
        "version": 3, "terms_id": terms_id(names), "coeffs_dps": rows}}))
    # udp_multicast loops our own frames back, so the host's requests are recorded too
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.2", port=port)
    logger = can.Logger(a.out)
    codec = CanCodec()
    sim = subprocess.Popen([sys.executable, "-m", "gyrocal.cli", "sim", "--link", "can", "--can-port",
                            str(port), "--rate", str(a.rate), "--seed", str(a.seed), "--serial", "4242",
                            "--duration", str(a.duration), "--flash", str(flash)],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    sim.stdout.readline()
    for msg in (HelloRequest(), CoeffRead()):
        for frame in codec.encode(msg):
            bus.send(frame)
    end = time.monotonic() + a.duration / 1.0 + 5.0
    n = 0
    while time.monotonic() < end and sim.poll() is None:
        frame = bus.recv(0.2)
        if frame is not None:
            logger(frame)
            n += 1
    sim.terminate()
    sim.wait(10)
    logger.stop()
    bus.shutdown()
    flash.unlink(missing_ok=True)
    print(f"{a.out}: {n} frames", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
