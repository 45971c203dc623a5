"""The calibration store: versioned history, atomic writes, and survival of kill -9 mid-write."""

from __future__ import annotations

import json
import logging
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from gyrocal.daemon.store import CalibrationRecord, CalibrationStore
from gyrocal.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
TERMS = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]


def make_record(serial: int = 1234, version: int = 0, seed: int = 0, **kw) -> CalibrationRecord:
    rng = random.Random(seed)
    p = len(TERMS)
    return CalibrationRecord(
        serial=serial, version=version, terms=list(TERMS),
        coefficients_dps=[[rng.uniform(-0.1, 0.1) for _ in range(p)] for _ in range(3)],
        uncertainty_dps=[[rng.uniform(1e-5, 1e-4) for _ in range(p)] for _ in range(3)],
        identifiable={"rank": 9, "undetermined": ["1 + gx^2 + gy^2 + gz^2"]},
        stats={"samples": 1000 + seed, "rms_dps": {"x": 0.01, "y": 0.02, "z": 0.03}, "poses": 6},
        session={"boot_count": 7, "fw": "1.2.3"}, **kw)


def test_add_assigns_contiguous_versions_and_reads_back_after_reopen(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    recs = [store.add(make_record(seed=i)) for i in range(3)]
    assert [r.version for r in recs] == [1, 2, 3]
    assert store.next_version(1234) == 4
    assert store.units() == [1234]
    again = CalibrationStore(tmp_path)
    assert [r.version for r in again.history(1234)] == [1, 2, 3]
    assert again.get(1234, 2).coefficients_dps == recs[1].coefficients_dps
    assert again.get(1234, 9) is None
    files = sorted(p.name for p in (tmp_path / "units" / "1234").iterdir())
    assert files == ["v000001.json", "v000002.json", "v000003.json"]


def test_latest_acked_only_skips_failed_and_pending_pushes(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    for i in range(4):
        store.add(make_record(seed=i))
    store.update_push(1234, 2, {"status": "acked", "attempts": 1, "acked_crc": 0xBEEF, "readback_ok": True})
    store.update_push(1234, 3, {"status": "nak", "attempts": 3})
    assert store.latest(1234).version == 2
    assert store.latest(1234, acked_only=False).version == 4
    assert store.latest(999) is None
    reopened = CalibrationStore(tmp_path)
    assert reopened.latest(1234).push["acked_crc"] == 0xBEEF
    assert reopened.get(1234, 3).push == {"status": "nak", "attempts": 3, "acked_crc": None,
                                          "readback_ok": None, "time": None}


def test_update_push_merges_keys_and_keeps_unknown_status(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.add(make_record(push={"status": "pending"}))
    store.update_push(1234, 1, {"attempts": 2})
    rec = store.update_push(1234, 1, {"status": "readback_timeout", "reasons": ["no report"]})
    assert rec.push["attempts"] == 2 and rec.push["reasons"] == ["no report"]
    assert CalibrationStore(tmp_path).get(1234, 1).push["status"] == "readback_timeout"
    with pytest.raises(KeyError):
        store.update_push(1234, 5, {"status": "acked"})
    with pytest.raises(ValueError):
        store.update_push(1234, 1, {"status": ""})


def test_add_refuses_to_overwrite_an_existing_version(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.add(make_record())
    with pytest.raises(ValueError, match="already has version 1"):
        store.add(make_record(version=1))
    assert store.add(make_record(version=5)).version == 5
    assert store.next_version(1234) == 6


def test_invalid_records_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    bad = make_record()
    bad.coefficients_dps[1] = bad.coefficients_dps[1][:-1]
    with pytest.raises(ValueError, match=r"coefficients_dps\[y\]"):
        store.add(bad)
    bad = make_record()
    bad.coefficients_dps[0][0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        store.add(bad)
    assert store.history(1234) == []
    assert not any((tmp_path / "units").rglob("*.json"))


def test_infinite_uncertainty_is_stored_as_none_meaning_undetermined(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    rec = make_record()
    rec.uncertainty_dps[0][4] = float("inf")
    rec.uncertainty_dps[2][6] = float("nan")
    store.add(rec)
    back = CalibrationStore(tmp_path).get(1234, 1)
    assert back.uncertainty_dps[0][4] is None and back.uncertainty_dps[2][6] is None
    json.loads((tmp_path / "units/1234/v000001.json").read_text())  # strict JSON, no Infinity


def test_numpy_arrays_are_accepted_and_stored_as_lists(tmp_path: Path) -> None:
    np = pytest.importorskip("numpy")
    rec = make_record()
    rec.coefficients_dps = np.arange(30, dtype=float).reshape(3, 10) * 1e-3
    rec.uncertainty_dps = np.full((3, 10), np.nan)
    CalibrationStore(tmp_path).add(rec)
    back = CalibrationStore(tmp_path).get(1234, 1)
    assert back.coefficients_dps[2][9] == pytest.approx(0.029)
    assert back.uncertainty_dps[1] == [None] * 10


def test_corrupt_file_and_leftover_tmp_are_ignored_with_a_warning(tmp_path: Path, caplog) -> None:
    store = CalibrationStore(tmp_path)
    for i in range(3):
        store.add(make_record(seed=i))
    udir = tmp_path / "units" / "1234"
    (udir / "v000002.json").write_text('{"serial": 1234, "version": 2, "terms": ["1"')  # truncated
    (udir / ".v000004.json.999.1.tmp").write_text('{"serial": 12')
    (udir / "notes.txt").write_text("not a record")
    caplog.set_level(logging.WARNING, logger="gyrocal.daemon.store")
    again = CalibrationStore(tmp_path)
    assert [r.version for r in again.history(1234)] == [1, 3]
    assert again.next_version(1234) == 4  # the unreadable v2 is never reused
    text = caplog.text
    assert "v000002.json" in text and "unreadable" in text
    assert ".v000004.json.999.1.tmp" in text and "leftover" in text


def test_record_that_claims_another_version_is_ignored(tmp_path: Path, caplog) -> None:
    store = CalibrationStore(tmp_path)
    store.add(make_record())
    udir = tmp_path / "units" / "1234"
    (udir / "v000002.json").write_text((udir / "v000001.json").read_text())  # a copy, still says v1
    caplog.set_level(logging.WARNING)
    assert [r.version for r in CalibrationStore(tmp_path).history(1234)] == [1]
    assert "claims serial 1234 version 1" in caplog.text


def test_loader_keeps_unknown_fields_through_a_rewrite(tmp_path: Path) -> None:
    store = CalibrationStore(tmp_path)
    store.add(make_record())
    path = tmp_path / "units/1234/v000001.json"
    doc = json.loads(path.read_text())
    doc["from_the_future"] = {"temperature_model": "T^3"}
    doc["push"]["future_flag"] = True
    path.write_text(json.dumps(doc))
    again = CalibrationStore(tmp_path)
    assert again.get(1234, 1).extra == {"from_the_future": {"temperature_model": "T^3"}}
    again.update_push(1234, 1, {"status": "acked"})
    doc = json.loads(path.read_text())
    assert doc["from_the_future"] == {"temperature_model": "T^3"} and doc["push"]["future_flag"] is True
    assert doc["push"]["status"] == "acked"


def test_state_dir_that_cannot_be_used_raises_config_error_naming_path_and_fix(tmp_path: Path) -> None:
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("")
    with pytest.raises(ConfigError) as err:
        CalibrationStore(blocker / "state")
    msg = str(err.value)
    assert str(blocker / "state") in msg and "fix:" in msg and "StateDirectory" in msg


# --- kill -9 during writes -------------------------------------------------------------------------

WRITER = textwrap.dedent("""
    import random, sys
    from pathlib import Path
    from gyrocal.daemon.store import CalibrationRecord, CalibrationStore
    store = CalibrationStore(Path(sys.argv[1]))
    rng = random.Random(int(sys.argv[2]))
    terms = ["1", "gx", "gy", "gz", "gx^2", "gy^2", "gz^2", "gx*gy", "gy*gz", "gx*gz"]
    while True:
        rec = CalibrationRecord(
            serial=77, version=0, terms=terms,
            coefficients_dps=[[rng.uniform(-1, 1) for _ in terms] for _ in range(3)],
            uncertainty_dps=[[rng.uniform(0, 1e-3) for _ in terms] for _ in range(3)],
            # padding makes each write take long enough that kills often land inside one
            stats={"samples": 5000, "residual_trace": [rng.random() for _ in range(4000)]})
        rec = store.add(rec)
        print("added", rec.version, flush=True)
        store.update_push(77, rec.version, {"status": "acked", "attempts": 1, "readback_ok": True})
        print("acked", rec.version, flush=True)
""")


def test_kill_9_at_random_moments_leaves_a_complete_contiguous_history(tmp_path: Path) -> None:
    """~20 writer processes are SIGKILLed at seeded random points; each time the store must load,
    every version file must be complete JSON, versions must be 1..N without a gap, and every
    version the writer reported as written (add returned) must be there, with its ack if reported."""
    rng = random.Random(20261122)
    state = tmp_path / "state"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    durable_added, acked = 0, set()
    for iteration in range(20):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(state), str(iteration)],
                                stdout=subprocess.PIPE, text=True, env=env, cwd=REPO)
        try:
            wanted = rng.randint(1, 6)  # reported lines to wait for, then a random extra delay
            for _ in range(wanted):
                line = proc.stdout.readline()
                assert line, f"writer died on its own in iteration {iteration}"
                kind, version = line.split()
                if kind == "added":
                    durable_added = max(durable_added, int(version))
                else:
                    acked.add(int(version))
            time.sleep(rng.uniform(0.0, 0.004))
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            proc.stdout.close()
        assert proc.returncode == -signal.SIGKILL

        store = CalibrationStore(state)
        history = store.history(77)
        versions = [r.version for r in history]
        assert versions == list(range(1, len(versions) + 1)), f"gap after kill {iteration}: {versions}"
        assert len(versions) >= durable_added, "a version that add() returned is missing"
        for path in (state / "units" / "77").glob("v*.json"):
            json.loads(path.read_text())  # every visible version file is complete
        for rec in history:
            assert len(rec.coefficients_dps) == 3 and len(rec.stats["residual_trace"]) == 4000
            if rec.version in acked:
                assert rec.push["status"] == "acked", f"v{rec.version} lost its reported ack"
        durable_added = len(versions)  # the next writer continues from here
    assert durable_added >= 20


def test_add_never_overwrites_a_version_file_written_behind_its_back(tmp_path: Path) -> None:
    first = CalibrationStore(tmp_path)
    second = CalibrationStore(tmp_path)
    first.add(make_record(seed=1))
    assert second.history(1234)[0].version == 1  # loads now, sees v1
    first.add(make_record(seed=2))  # v2 written by another store object
    rec = second.add(make_record(seed=3))
    assert rec.version == 3
    assert CalibrationStore(tmp_path).get(1234, 2).stats["samples"] == 1002


def test_numpy_and_nan_in_free_form_stats_do_not_block_the_write(tmp_path: Path) -> None:
    np = pytest.importorskip("numpy")
    rec = make_record(serial=np.int64(55))
    rec.stats = {"rms_dps": np.array([0.1, np.nan, 0.3], dtype=np.float32), "n": np.int64(7),
                 "validation": {"ratio": float("inf")}, "path": tmp_path}
    CalibrationStore(tmp_path).add(rec)
    back = CalibrationStore(tmp_path).get(55, 1)
    assert back.stats["rms_dps"][1] is None and back.stats["n"] == 7
    assert back.stats["validation"]["ratio"] is None and back.stats["path"] == str(tmp_path)


def test_assigned_version_never_goes_below_the_floor_the_unit_holds(tmp_path: Path) -> None:
    """A unit holding factory v7 that this store never wrote gets v8 next, then v9, not v1."""
    store = CalibrationStore(tmp_path)
    assert store.add(make_record(), min_version=8).version == 8
    assert store.add(make_record(seed=1), min_version=8).version == 9
    assert store.add(make_record(seed=2)).version == 10
    assert [r.version for r in CalibrationStore(tmp_path).history(1234)] == [8, 9, 10]


def test_prune_keeps_the_newest_versions_and_every_set_the_unit_may_hold(tmp_path: Path, caplog) -> None:
    """keep 5 of 30: v26-v30, plus the two newest acked (v3, v8: older failed pushes after them), v2 that
    was acked last (a rollback re-sent it), and the pending v12 (a push in flight)."""
    store = CalibrationStore(tmp_path)
    for i in range(30):
        store.add(make_record(seed=i))
    for v in range(13, 31):
        store.update_push(1234, v, {"status": "nak"})
    for v, utc in ((5, "2026-10-01T10:00:00.000000Z"), (3, "2026-11-01T10:00:00.000000Z"),
                   (8, "2026-11-02T10:00:00.000000Z"), (2, "2026-11-20T10:00:00.000000Z")):  # ack order
        store.update_push(1234, v, {"status": "acked", "utc": utc})
    for v in (1, 4, 6, 7, 9, 10, 11):
        store.update_push(1234, v, {"status": "timeout"})
    caplog.set_level(logging.INFO, logger="gyrocal.daemon.store")
    gone = store.prune(1234, keep=5)
    kept = [2, 5, 8, 12, 26, 27, 28, 29, 30]  # v5: one of the two newest acked by version (5, 8)
    assert [r.version for r in store.history(1234)] == kept
    assert gone == sorted(set(range(1, 31)) - set(kept))
    files = sorted(p.name for p in (tmp_path / "units" / "1234").iterdir())
    assert files == [f"v{v:06d}.json" for v in kept]
    reopened = CalibrationStore(tmp_path)
    assert [r.version for r in reopened.history(1234)] == kept
    assert reopened.next_version(1234) == 31 and reopened.latest(1234).version == 8
    assert store.prune(1234, keep=5) == [] and store.prune(1234, keep=0) == []
    said = [r.getMessage() for r in caplog.records if "removed" in r.getMessage()]
    assert len(said) == 1 and "21 versions: v1, v3-v4, v6-v7, v9-v11, v13-v25" in said[0], said



def test_prune_on_a_store_that_cannot_be_written_keeps_everything_and_says_so_once(
        tmp_path: Path, caplog) -> None:
    """The unit's directory replaced by a file after the load (ENOTDIR, as the fault campaign's
    store_unwritable does): no version is lost, and one line, not one per version."""
    store = CalibrationStore(tmp_path)
    for i in range(8):
        store.add(make_record(seed=i, push={"status": "nak"}))
    udir = tmp_path / "units" / "1234"
    aside = tmp_path / "aside"
    udir.rename(aside)
    udir.write_text("not a directory")
    caplog.set_level(logging.WARNING, logger="gyrocal.daemon.store")
    try:
        assert store.prune(1234, keep=2) == []
    finally:
        udir.unlink()
        aside.rename(udir)
    assert len(store.history(1234)) == 8 and len(list(udir.iterdir())) == 8
    said = [r.getMessage() for r in caplog.records if "cannot remove" in r.getMessage()]
    assert len(said) == 1, said


def test_the_warm_start_is_the_set_the_unit_held_last_not_the_newest(tmp_path: Path) -> None:
    """A rollback to v2 after v3: the unit holds v2. The warm start was the newest acked (v3), whose
    bias stage then pushed v3's set back (an operator's audit)."""
    store = CalibrationStore(tmp_path)
    for i in range(3):
        store.add(make_record(serial=5, seed=i))
    store.update_push(5, 1, {"status": "acked", "utc": "2026-11-20T10:00:00.000000Z"})
    store.update_push(5, 3, {"status": "acked", "utc": "2026-11-21T10:00:00.000000Z"})
    store.update_push(5, 2, {"status": "acked", "utc": "2026-11-22T10:00:00.000000Z"})  # the rollback
    assert store.held_last(5).version == 2 and store.latest(5).version == 3
    assert CalibrationStore(tmp_path).held_last(5).version == 2
    assert CalibrationStore(tmp_path / "none").held_last(5) is None


def test_the_set_held_last_is_the_last_acked_whatever_the_wall_clock_said(tmp_path: Path) -> None:
    """v1 was acked while the clock ran 400 days ahead; NTP corrected it and v2 was acked. By push
    utc, v1 stayed the set held last: every switch-on warm-started from its gravity terms and left
    100x the drift (an operator's audit). Acks are counted (push.held_seq)."""
    store = CalibrationStore(tmp_path)
    for i in range(2):
        store.add(make_record(serial=5, seed=i))
    store.update_push(5, 1, {"status": "acked", "utc": "2027-12-30T10:00:00.000000Z"})  # clock ahead
    store.update_push(5, 2, {"status": "acked", "utc": "2026-11-24T10:00:00.000000Z"})  # corrected
    for s in (store, CalibrationStore(tmp_path)):
        assert s.held_last(5).version == 2
        assert [s.get(5, v).push["held_seq"] for v in (1, 2)] == [1, 2]


def test_a_failed_rollback_never_erases_that_the_unit_held_the_version(tmp_path: Path) -> None:
    """A rollback to v1 with the unit unplugged ended 'abandoned' and rewrote v1's 'acked' with no
    history: a later rollback to v1 was refused and the prune deleted it (an operator's audit)."""
    store = CalibrationStore(tmp_path)
    for i in range(2):
        store.add(make_record(serial=5, seed=i))
    store.update_push(5, 1, {"status": "acked", "utc": "2026-11-20T10:00:00.000000Z"})
    store.update_push(5, 2, {"status": "acked", "utc": "2026-11-21T10:00:00.000000Z"})
    store.update_push(5, 1, {"status": "abandoned", "reasons": ["push cut short: a new session started"],
                             "utc": "2026-11-22T10:00:00.000000Z", "attempts": 1})
    for s in (store, CalibrationStore(tmp_path)):
        rec = s.get(5, 1)
        assert rec.push["status"] == "acked" and rec.push["utc"] == "2026-11-20T10:00:00.000000Z"
        assert rec.push["history"][-1]["status"] == "abandoned" and rec.push["attempts"] == 0
        assert s.held_last(5).version == 2  # the unit still holds v2: the failed push changed nothing
    store.update_push(5, 1, {"status": "acked", "utc": "2026-11-23T10:00:00.000000Z"})  # it succeeds
    assert store.held_last(5).version == 1 and store.get(5, 1).push["history"][-1]["status"] == "abandoned"


def test_a_full_disk_names_the_file_it_could_not_write(tmp_path: Path) -> None:
    """ENOSPC from write() carries no path ("store unavailable: [Errno 28] No space left on device"
    said nothing of where: an operator's audit); the temporary file is removed."""
    import builtins
    import errno
    from unittest import mock

    from gyrocal.daemon.store import atomic_write_json

    real_open = builtins.open

    class Full:
        def __init__(self, *a, **k) -> None:
            self.f = real_open(*a, **k)

        def __enter__(self) -> Full:
            return self

        def __exit__(self, *a) -> None:
            self.f.close()

        def write(self, b: bytes) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

    with mock.patch("builtins.open", Full), pytest.raises(OSError) as err:
        atomic_write_json(tmp_path / "v000001.json", {"a": 1})
    assert err.value.errno == errno.ENOSPC and str(tmp_path / "v000001.json") in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_a_read_only_state_directory_at_start_is_a_fault_not_an_exit(tmp_path: Path, monkeypatch,
                                                                       caplog) -> None:
    """docs/operations.md: a read-only state directory never stops the daemon; at start it exited
    (an operator's audit, with chattr +i). One that cannot be made at all stays a config error, and
    names the config field as it is spelled (it said daemon.state_dir)."""
    import logging
    import os

    from gyrocal.daemon import store as store_mod
    from gyrocal.errors import ConfigError

    CalibrationStore(tmp_path)  # the directory exists, with its units/
    real = os.access
    monkeypatch.setattr(store_mod.os, "access", lambda p, mode: False if mode & os.W_OK else real(p, mode))
    caplog.set_level(logging.ERROR, logger="gyrocal.daemon.store")
    s = CalibrationStore(tmp_path)
    assert s.read_only and "not writable" in s.read_only
    assert [r.levelno for r in caplog.records] == [logging.ERROR] and "pushes no set" in caplog.text
    monkeypatch.setattr(store_mod.os, "access", real)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ConfigError, match=r"point state_dir in the config"):
        CalibrationStore(blocker / "state")
    # a readable state directory with no store in it yet, on a read-only mount (a vehicle's first boot
    # on a read-only /var): it stopped `gyrocal run` with exit 2 (an operator's audit)
    import errno

    empty = tmp_path / "empty"
    empty.mkdir()
    real_mkdir = Path.mkdir

    def ro_mkdir(self: Path, *a: object, **k: object) -> None:
        if str(self).startswith(str(empty)):
            raise OSError(errno.EROFS, "Read-only file system")
        real_mkdir(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", ro_mkdir)
    s = CalibrationStore(empty)
    assert s.read_only and "Read-only file system" in s.read_only and s.units() == []


def test_a_store_read_only_at_start_says_so_until_a_write_goes_through(tmp_path: Path, monkeypatch,
                                                                       caplog) -> None:
    """status's store_view.read_only_at_start kept "... cannot be written (Permission denied)" to the
    end of a run whose store was written from 21 s on (an integrator's campaign, rc33 G8)."""
    from gyrocal.daemon import store as store_mod

    CalibrationStore(tmp_path)
    real = os.access
    monkeypatch.setattr(store_mod.os, "access", lambda p, mode: False if mode & os.W_OK else real(p, mode))
    s = CalibrationStore(tmp_path)
    assert s.read_only
    monkeypatch.setattr(store_mod.os, "access", real)  # chmod'ed writable meanwhile
    caplog.set_level(logging.INFO, logger="gyrocal.daemon.store")
    rec = s.add(make_record())
    assert s.read_only is None and "could not be at start" in caplog.text
    monkeypatch.setattr(store_mod.os, "access", lambda p, mode: False if mode & os.W_OK else real(p, mode))
    s2 = CalibrationStore(tmp_path)
    assert s2.read_only
    monkeypatch.setattr(store_mod.os, "access", real)
    s2.update_push(rec.serial, rec.version, {"status": "acked"})
    assert s2.read_only is None


def test_each_fsync_of_a_write_feeds_the_watchdog_first(tmp_path: Path) -> None:
    """On a disk taking 2-3 s per fsync, a record and its push result took 10.9 s and systemd's 10 s
    watchdog would have killed the daemon mid-push (an operator's audit). The store calls its io beat
    (the engine's rate-limited WATCHDOG=1) before every fsync."""
    from gyrocal.daemon.store import set_io_beat

    beats: list[int] = []
    set_io_beat(lambda: beats.append(1))
    try:
        store = CalibrationStore(tmp_path)
        rec = store.add(make_record())
        first = len(beats)
        store.update_push(rec.serial, rec.version, {"status": "acked"})
    finally:
        set_io_beat(None)
    assert first >= 2 and len(beats) >= first + 2  # the file's and its directory's, each write
