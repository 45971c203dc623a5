"""The host's copy of the unit's dtemp rule is used only where it is the unit's (TempRate.exact).

Why: a unit holding a set with a dtemp term subtracts C @ terms(dtemp) with its own dtemp, the slope
of its last 20 whole-second temperature means since switch-on (docs/protocol.md, section 6). A host
that starts on a running unit, or sees its first samples only after reading the unit's set, averages
a part of its first second only, and for the next 20 seconds its dtemp is not the unit's. During a
warm-up that difference times the held coefficient is a drift the host learnt: on the independent
fibre unit with a factory dT/dt set, a daemon that started 2.3 s after the unit pushed nothing in
150 s on 5 of 8 seeds and cut 2.8-8x on the rest (in process, the same physics as tests/indep).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from gyrocal.protocol.termsets import TempRate
from tests.indep.inprocess import held_dtemp_run, replaced_factory_set
from tests.indep.truth import temperature


def _fed_in_chunks(t: np.ndarray, temp: np.ndarray, seq: np.ndarray | None, keep: np.ndarray,
                   chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """dtemp [degC/s] and exactness of a fresh copy fed the samples ``keep`` in uneven chunks, as a
    link delivers them; NaN and False where a sample never arrived."""
    copy = TempRate()
    d = np.full(t.size, np.nan)
    ok = np.zeros(t.size, dtype=bool)
    for part in np.array_split(keep, chunks):
        d[part], ok[part] = copy.update_exact(t[part], temp[part], None if seq is None else seq[part])
    return d, ok


def test_a_copy_started_late_is_marked_inexact_until_its_window_is_the_units() -> None:
    rate = 100.0
    t = np.arange(0, 40 * rate) / rate
    temp = np.round(temperature(t, 20.0) / 0.01) * 0.01  # a warm-up, as sent
    truth = TempRate().update(t, temp)
    start = int(2.3 * rate)
    d_early, ok_early = TempRate().update_exact(t, temp)
    d_late, ok_late = _fed_in_chunks(t, temp, None, np.arange(start, t.size), 37)
    assert ok_early.all() and np.array_equal(d_early, truth)  # seen from the unit's first second
    assert not ok_late[start:int(23 * rate)].any() and ok_late[int(24 * rate):].all()
    assert np.max(np.abs(d_late[start:int(23 * rate)] - truth[start:int(23 * rate)])) > 0.01  # degC/s
    # where it says exact, it is the unit's (to the rounding of sums taken in other chunks)
    np.testing.assert_allclose(d_late[ok_late], truth[ok_late], rtol=0, atol=1e-9)


def test_a_copy_that_misses_the_start_of_second_0_is_not_the_units() -> None:
    """Half of the unit's first second is not its first second: the mean of it is another mean."""
    rate = 400.0
    t = np.arange(0, 30 * rate) / rate
    seq = np.arange(t.size)
    temp = np.round(temperature(t, 22.0) / 0.01) * 0.01
    truth = TempRate().update(t, temp)
    start = int(0.5 * rate)
    half = TempRate()
    d_half, ok_half = half.update_exact(t[start:], temp[start:], seq[start:])
    assert not ok_half[: int(20.5 * rate)].any() and ok_half[int(21 * rate):].all()
    assert np.max(np.abs(d_half - truth[start:])[: int(20 * rate)]) > 0.01  # degC/s
    whole = TempRate()
    assert whole.update_exact(t, temp, seq)[1].all()  # from seq 0: the unit's own at once


@pytest.mark.parametrize("late_s", [0.75, 2.3])
def test_a_daemon_that_starts_late_on_a_unit_with_a_dtemp_set_still_cuts_10x(tmp_path: Path,
                                                                             late_s: float) -> None:
    """The unit streams late_s before the daemon sees it; its factory set holds a dT/dt term.

    Under a second is the pty case (tests/test_indep_unit.py): the daemon opens the port while the
    unit's first second runs. When any part of second 0 counted as exact, this unit's first push cut
    16.6 / 7.3 / 40x at 0.75 s (seeds 1-3 at 0.25-0.75 s: 5.7-149x; now 35-180x).
    """
    run, unit = held_dtemp_run(tmp_path, 1)
    run.switch_on()
    unit.render(int(late_s * 400))  # sent before the daemon listened
    run.run(150.0, replaced_factory_set)
    assert replaced_factory_set(run), run.session.reason
    before, after = unit.drift_rms_dps()
    assert np.all(after * 10 <= before), before / after
    assert run.session.status()["dtemp_inexact_samples"] > 0


def test_a_3_s_gap_leaves_the_window_in_part_for_20_s_but_a_lost_frame_does_not() -> None:
    rate = 400.0
    t = np.arange(0, 45 * rate) / rate
    seq = np.arange(t.size)
    temp = np.round(temperature(t, 22.0) / 0.01) * 0.01
    truth = TempRate().update(t, temp)
    drop = (seq >= int(8.2 * rate)) & (seq < int(11.2 * rate))  # a link down for 3 s
    drop[int(30.5 * rate)] = True  # and one frame lost later (filled in)
    keep = np.flatnonzero(~drop)
    d, ok = _fed_in_chunks(t, temp, seq, keep, 53)
    assert ok[: int(8.2 * rate)].all()  # from seq 0, before the gap: the unit's own
    after = keep[(t[keep] >= 11.2) & (t[keep] < 32)]
    assert not ok[after].any()  # seconds 8 and 11 seen in part, 9 and 10 not at all
    assert ok[keep[t[keep] >= 32]].all()  # the lost frame at 30.5 s is filled in
    assert np.max(np.abs(d - truth)[after]) > 0.01  # degC/s
    np.testing.assert_allclose(d[ok], truth[ok], rtol=0, atol=1e-4)


def test_bursts_lost_on_the_link_are_filled_in_and_the_copy_stays_the_units() -> None:
    """300 ms lost every 4 s and one gap of 1.5 s, in the fibre unit's warm-up (up to 0.72 degC/s).

    The seconds seen in part are filled in on the unit's sample clock, so the copy stays exact and
    within 4e-4 degC/s of the unit's dT/dt, with 0.02 degC of noise on the temperature. Their means
    taken from the samples received alone are up to 0.018 degC/s off. Before the fill, every burst
    longer than 10 ms set 20 s aside, and a link that lost one every few seconds kept a unit with a
    dT/dt set out of learning for good (benchmarks/bench_late_start.py --cases lossy).
    """
    rate = 400.0
    t = np.arange(0, 60 * rate) / rate
    seq = np.arange(t.size)
    rng = np.random.default_rng(1)
    temp = np.round((temperature(t, 22.0) + rng.normal(0.0, 0.02, t.size)) / 0.01) * 0.01
    truth = TempRate().update(t, temp)
    drop = np.zeros(t.size, dtype=bool)
    for start in np.arange(3.1, 60.0, 4.0):
        drop[int(start * rate):int((start + 0.3) * rate)] = True
    drop[int(40.7 * rate):int(42.2 * rate)] = True
    keep = np.flatnonzero(~drop)
    err = {}
    for name, given in (("filled", seq), ("received only", None)):
        d, ok = _fed_in_chunks(t, temp, given, keep, 77)
        assert ok[keep].all()
        err[name] = float(np.max(np.abs(d - truth)[keep]))
    assert err["filled"] < 4e-4 and err["received only"] > 0.01, err  # degC/s


def test_a_gap_longer_than_fill_s_is_not_filled() -> None:
    rate = 100.0
    t = np.arange(0, 30 * rate) / rate
    seq = np.arange(t.size)
    temp = np.round(temperature(t, 22.0) / 0.01) * 0.01
    back = 5.0 + TempRate.FILL_S + 0.1  # [s] the link back in the middle of a second
    keep = (t < 5.0) | (t >= back)
    copy = TempRate()
    _, ok = copy.update_exact(t[keep], temp[keep], seq[keep])
    tk = t[keep]
    assert ok[tk < 5.0].all() and not ok[(tk >= back) & (tk < back + TempRate.WINDOW)].any()


def test_a_daemon_on_a_link_that_loses_a_burst_every_few_seconds_still_pushes(tmp_path: Path) -> None:
    """50 ms lost every 5 s from switch-on (a USB-serial adapter that overruns now and then).

    Each burst set 20 s aside before the fill: no push in 150 s on seeds 1-3 (bench_late_start.py
    --cases lossy at 856f8f4); now the first push comes at about the same sample as on a clean link.
    """
    run, unit = held_dtemp_run(tmp_path, 1)
    run.switch_on()
    for _ in range(30):
        run.run(4.95, replaced_factory_set)
        if replaced_factory_set(run):
            break
        unit.render(20)  # 50 ms lost on the link
        run.now += 0.05
    assert replaced_factory_set(run), run.session.reason
    before, after = unit.drift_rms_dps()
    assert np.all(after * 10 <= before), before / after
    assert run.session.status()["dtemp_inexact_samples"] == 0


def test_a_link_that_drops_3_s_during_the_warm_up_does_not_spoil_the_push(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The daemon hears the unit from switch-on, then the link is down from 8 to 11 s.

    With the gap counted exact, the first push cut this unit 6.7 / 16.8 / 7.6x (seeds 1-3: 6.7-65x;
    benchmarks/bench_late_start.py at 24d9300); the seconds around the gap now stay out of learning
    for 20 s.
    """
    run, unit = held_dtemp_run(tmp_path, 2)
    caplog.set_level(logging.INFO, logger="gyrocal.session")
    run.switch_on()
    run.run(8.0)
    unit.render(int(3.0 * 400))  # lost on the link
    run.now += 3.0
    run.run(150.0, replaced_factory_set)
    assert replaced_factory_set(run), run.session.reason
    before, after = unit.drift_rms_dps()
    assert np.all(after * 10 <= before), before / after
    assert run.session.status()["dtemp_inexact_samples"] > 0
    said = [r.getMessage() for r in caplog.records if "set aside" in r.getMessage()]
    assert len(said) == 1 and "from unit time 11" in said[0], said  # one line for the one gap


def test_a_jump_in_seq_that_the_time_does_not_bear_out_is_not_filled() -> None:
    """A seq 2^31 ahead 2.5 ms later is not two billion lost samples: set aside, nothing allocated."""
    rate = 400.0
    t = np.arange(0, 30 * rate) / rate
    seq = np.arange(t.size, dtype=np.int64)
    seq[int(5.3 * rate):] += 2**31
    temp = np.round(temperature(t, 22.0) / 0.01) * 0.01
    copy = TempRate()
    _, ok = copy.update_exact(t, temp, seq)
    assert ok[t < 5.0].all() and not ok[(t >= 5.0) & (t < 26.0)].any() and ok[t >= 26.0].all()
