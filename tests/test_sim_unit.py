"""The virtual unit's firmware logic: HELLO at switch-on, compensated output, ACK/NAK, faults, status."""

import numpy as np
import pytest

from gyrocal.protocol import termsets
from gyrocal.protocol.messages import (
    CoeffAck,
    CoeffNak,
    CoeffRead,
    CoeffReport,
    CoeffTransferFailed,
    CoeffWrite,
    Hello,
    HelloRequest,
    NakReason,
    Sample,
    coeff_set_crc,
)
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import TruthModel
from gyrocal.sim.unit import Faults, VirtualUnit


def _unit(seed: int = 7, faults: Faults | None = None, rate_hz: float = 100.0) -> VirtualUnit:
    return VirtualUnit(TruthModel(), tumble(), rate_hz, seed, serial=1234, faults=faults)


def _true_write(version: int = 1) -> CoeffWrite:
    return CoeffWrite(version, termsets.SEED000_ID, TruthModel().coeffs_dps.tolist())


def test_unit_power_on_sends_hello_and_counts_boots_with_new_bias() -> None:
    u = _unit()
    assert u.power_on() == [Hello(serial=1234, fw_version="1.0.0", boot_count=1, rate_hz=100)]
    b1 = u.bias_dps().copy()
    s = u.samples(3)
    assert [x.seq for x in s] == [0, 1, 2] and s[1].t_s == pytest.approx(0.01)
    u.power_on()
    assert u.boot_count == 2 and not np.allclose(u.bias_dps(), b1)
    assert u.samples(1)[0].seq == 0  # seq restarts at switch-on


def test_unit_output_is_deterministic_for_a_seed_and_differs_across_seeds() -> None:
    a, b, c = _unit(3), _unit(3), _unit(4)
    for u in (a, b, c):
        u.power_on()
    sa, sb, sc = a.samples(50), b.samples(50), c.samples(50)
    assert sa == sb and sa != sc
    assert all(isinstance(x, Sample) for x in sa)


def test_unit_applies_true_coefficients_and_output_drift_drops_to_the_bias() -> None:
    u = _unit()
    u.power_on()
    write = _true_write()
    assert u.handle(write) == [CoeffAck(1, coeff_set_crc(1, write.terms_id, write.coeffs_dps))]
    st = u.status()
    assert st["applied_version"] == 1 and st["applied_terms_id"] == termsets.SEED000_ID
    # with the exact gravity model removed only the switch-on bias is left at every pose
    np.testing.assert_allclose([st["drift_rms_compensated_dps"][a] for a in "xyz"], np.abs(u.bias_dps()),
                               rtol=1e-9)
    chunk = u.render(400)  # the sent output equals raw minus compensation, sample by sample
    c = chunk.columns
    np.testing.assert_allclose(c["wx"] + c["comp_wx"] - c["ref_wx"] - c["drift_wx"], 0.0, atol=0.02)
    a = np.column_stack([c["ax"], c["ay"], c["az"]])  # the unit's gravity terms use a/|a| (protocol.md)
    gravity_part = TruthModel().gravity_drift_dps(a / np.linalg.norm(a, axis=1)[:, None])
    np.testing.assert_allclose(c["comp_wy"], gravity_part[:, 1], atol=1e-12)


def test_unit_keeps_applied_set_across_power_cycles() -> None:
    u = _unit()
    u.power_on()
    u.handle(_true_write(5))
    u.power_on()
    assert u.status()["applied_version"] == 5
    (report,) = u.handle(CoeffRead())
    assert isinstance(report, CoeffReport) and report.version == 5
    np.testing.assert_allclose(report.coeffs_dps, TruthModel().coeffs_dps)


@pytest.mark.parametrize(
    "write, reason",
    [
        (CoeffWrite(2, 0x0001, ((0.0,),) * 3), NakReason.UNKNOWN_TERMS),
        (CoeffWrite(2, termsets.SEED000_ID, ((0.0,) * 9,) * 3), NakReason.BAD_LENGTH),
        (CoeffWrite(2, termsets.SEED000_ID, ((float("nan"),) + (0.0,) * 9,) * 3), NakReason.OUT_OF_RANGE),
        (CoeffWrite(2, termsets.SEED000_ID, ((1e6,) + (0.0,) * 9,) * 3), NakReason.OUT_OF_RANGE),
    ],
)
def test_unit_naks_bad_sets_and_keeps_the_old_one(write: CoeffWrite, reason: NakReason) -> None:
    u = _unit()
    u.power_on()
    u.handle(_true_write(1))
    (nak,) = u.handle(write)
    assert isinstance(nak, CoeffNak) and nak.reason == reason and nak.version == 2
    assert u.status()["applied_version"] == 1


def test_unit_naks_a_failed_can_transfer() -> None:
    u = _unit()
    assert u.handle(CoeffTransferFailed(3, 99, NakReason.BAD_CRC)) == [CoeffNak(3, 99, NakReason.BAD_CRC)]


def test_unit_faults_nak_next_then_drop_acks_then_normal() -> None:
    u = _unit(faults=Faults(nak_next=2))
    u.power_on()
    assert [type(r) for w in range(2) for r in u.handle(_true_write(w + 1))] == [CoeffNak, CoeffNak]
    assert u.handle(_true_write(3))[0] == CoeffAck(3, u.applied.crc)
    u.faults.drop_acks = 1
    assert u.handle(_true_write(4)) == [] and u.status()["applied_version"] == 3
    assert isinstance(u.handle(_true_write(4))[0], CoeffAck)
    assert u.status()["writes"] == {"acked": 2, "naked": 2, "dropped": 1, "acks_lost": 0}


def test_unit_answers_hello_request_with_the_current_boot() -> None:
    u = _unit()
    assert u.handle(HelloRequest()) == []  # off: nothing to say
    u.power_on()
    u.power_on()
    assert u.handle(HelloRequest()) == [Hello(serial=1234, fw_version="1.0.0", boot_count=2, rate_hz=100)]
    assert u.boot_count == 2


def test_unit_never_hello_fault_stays_silent_at_switch_on_and_on_request() -> None:
    u = _unit(faults=Faults(never_hello=True))
    assert u.power_on() == [] and u.boot_count == 1 and u.handle(HelloRequest()) == []


def test_unit_flash_state_round_trips() -> None:
    u = _unit()
    u.power_on()
    u.handle(_true_write(9))
    v = _unit()
    v.load_flash(u.flash_state())
    assert v.boot_count == 1 and v.applied is not None and v.applied.crc == u.applied.crc
