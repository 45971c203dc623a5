"""The calibration store: a versioned history of coefficient sets per unit serial, on disk.

Why it looks like this: the daemon runs for months on a vehicle whose power may be cut at any moment,
so the store must never hold a half-written calibration and must never lose the last good one.

- Layout: ``state_dir/units/<serial>/v<NNNNNN>.json``, one file per version. There is no index file:
  the history is rebuilt from the version files at load, so no single file is a point of failure.
- Every write is atomic: a temporary file in the same directory, write, flush, ``os.fsync``,
  ``os.replace`` onto the final name, then ``fsync`` of the directory so the rename itself is durable.
  A kill -9 or a power cut leaves either the old file or the new one, plus at worst a stray temporary.
- Reading is forgiving: a corrupt or partial file, or a leftover temporary, is skipped with a warning
  and never crashes the daemon. Unknown fields are kept (``extra``) so an older daemon can read, and
  rewrite, a newer daemon's records without losing what it does not understand.
- One daemon writes a state directory; readers in the same process share it under a lock (the
  estimator thread adds records while the control thread answers ``status``).
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import threading
from dataclasses import asdict, dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from gyrocal.errors import ConfigError

log = logging.getLogger(__name__)

FORMAT = "gyrocal.calibration/1"
"""Written into every record so a future layout change can be recognised."""

PUSH_STATUSES = (
    "pending", "acked", "applied_ack_lost", "nak", "timeout", "link_down", "refused", "abandoned",
    "crc_mismatch", "readback_mismatch", "readback_timeout",
)
"""Known push results. 'applied_ack_lost': the push ended without its ack, but a later read-back
showed the unit holds exactly this set (see daemon/reconcile.py). 'refused': the daemon refused to
send it (e.g. the link was down when it started, or the set failed a check). 'abandoned': left
'pending' by a daemon that stopped mid-push. Another status string is stored anyway, with a warning:
losing the record of a failed push would be worse."""

APPLIED_STATUSES = ("acked", "applied_ack_lost")
"""Sets the unit verifiably held: the only candidates for warm start and rollback."""

_VERSION_FILE = re.compile(r"^v(\d{6,})\.json$")
_TMP_SUFFIX = ".tmp"


def utc_now() -> str:
    """ISO 8601 UTC timestamp with a Z suffix, the form every record uses."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def default_push() -> dict[str, Any]:
    """The push result of a set that has not been sent yet."""
    return {"status": "pending", "attempts": 0, "acked_crc": None, "readback_ok": None, "time": None}


@dataclass
class CalibrationRecord:
    """One calibration of one unit.

    coefficients_dps and uncertainty_dps are 3 rows (x, y, z) of P values, one per term, in deg/s per
    unit of the term (deg/s per g, per degC, ...). An uncertainty of None means "not determined by this
    session's data" (JSON has no Inf): its value was held, never learnt (the stored set's value on a
    warm start, else the prior zero; see daemon/learner.py). version 0 means "assign on add".
    """

    serial: int
    version: int
    terms: list[str]
    coefficients_dps: list[list[float]]
    uncertainty_dps: list[list[float | None]]
    identifiable: dict = field(default_factory=dict)  # e.g. {"rank": 9, "undetermined": [...]}
    stats: dict = field(default_factory=dict)  # samples, rms_dps per axis, poses, ...
    created_utc: str = field(default_factory=utc_now)
    session: dict = field(default_factory=dict)  # boot_count, fw
    push: dict = field(default_factory=default_push)  # status, attempts, acked_crc, readback_ok, time
    host_remainder: dict = field(default_factory=dict)
    """Empty, or the part of the learnt set the unit cannot hold (daemon/capabilities.py): ``terms``,
    ``coefficients_dps`` (3 rows) that a host consumer subtracts from the unit's output as the unit
    does with its own set, ``held_terms``, and ``drift_left_poses_dph`` (x, y, z) it would leave."""
    extra: dict = field(default_factory=dict)  # fields this version of gyrocal does not know

    def validate(self) -> None:
        """Raise ValueError naming the first field that is wrong; called before every write."""
        if not isinstance(self.serial, int) or isinstance(self.serial, bool) or self.serial < 0:
            raise ValueError(f"serial must be a non-negative int, got {self.serial!r}")
        if not isinstance(self.version, int) or isinstance(self.version, bool) or self.version < 0:
            raise ValueError(f"version must be a non-negative int, got {self.version!r}")
        if not isinstance(self.terms, list) or not all(isinstance(t, str) and t for t in self.terms):
            raise ValueError(f"terms must be a list of non-empty strings, got {self.terms!r}")
        p = len(self.terms)
        for name, rows, allow_none in (("coefficients_dps", self.coefficients_dps, False),
                                       ("uncertainty_dps", self.uncertainty_dps, True)):
            if not isinstance(rows, list) or len(rows) != 3:
                raise ValueError(f"{name} must be 3 rows (x, y, z), got {rows!r}")
            for axis, row in zip("xyz", rows, strict=True):
                if not isinstance(row, list) or len(row) != p:
                    raise ValueError(f"{name}[{axis}] must hold {p} values (one per term), got {row!r}")
                for v in row:
                    if v is None and allow_none:
                        continue
                    if not _is_number(v) or not math.isfinite(v):
                        raise ValueError(f"{name}[{axis}] holds {v!r}; every value must be a finite number")
        for name in ("identifiable", "stats", "session", "push", "host_remainder", "extra"):
            if not isinstance(getattr(self, name), dict):
                raise ValueError(f"{name} must be a dict")
        _check_push_status(self.push.get("status"))
        if not isinstance(self.created_utc, str):
            raise ValueError("created_utc must be an ISO 8601 string")

    def normalise(self) -> None:
        """Turn Inf/NaN uncertainties (undetermined) into None and numpy scalars into floats."""
        def num(v: Any, none_if_bad: bool) -> Any:
            if hasattr(v, "item") and not isinstance(v, bool):
                v = v.item()  # numpy scalar
            if none_if_bad and _is_number(v) and not math.isfinite(v):
                return None
            return v

        for name, none_if_bad in (("coefficients_dps", False), ("uncertainty_dps", True)):
            rows = getattr(self, name)
            if hasattr(rows, "tolist"):
                rows = rows.tolist()  # a (3, P) numpy array
            if isinstance(rows, list | tuple) and all(isinstance(r, list | tuple) or hasattr(r, "tolist")
                                                      for r in rows):
                rows = [[num(v, none_if_bad) for v in (r.tolist() if hasattr(r, "tolist") else r)]
                        for r in rows]
            setattr(self, name, rows)
        for name in ("serial", "version"):
            value = getattr(self, name)
            if hasattr(value, "item") and not isinstance(value, bool):
                setattr(self, name, value.item())  # a numpy integer
        if isinstance(self.terms, tuple):
            self.terms = list(self.terms)
        if isinstance(self.push, dict):
            self.push = {**default_push(), **self.push}  # a partial push dict gets the missing keys

    def to_dict(self) -> dict[str, Any]:
        """The JSON form: known fields at top level, unknown ones merged back in unchanged."""
        d = _jsonable(asdict(self))
        extra = d.pop("extra")
        if not d["host_remainder"]:  # optional: a record the unit holds whole looks as it always did
            del d["host_remainder"]
        return {"format": FORMAT, **extra, **d}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CalibrationRecord:
        """Build and validate a record; unknown keys go to ``extra``. Raises ValueError/TypeError."""
        if not isinstance(d, dict):
            raise ValueError("a record must be a JSON object")
        known = {f.name for f in fields(cls)} - {"extra"}
        missing = {"serial", "version", "terms", "coefficients_dps", "uncertainty_dps"} - d.keys()
        if missing:
            raise ValueError(f"missing fields {sorted(missing)}")
        kwargs = {k: v for k, v in d.items() if k in known}
        extra = {k: v for k, v in d.items() if k not in known and k != "format"}
        rec = cls(**kwargs, extra=extra)
        rec.normalise()
        rec.validate()
        return rec


def _jsonable(obj: Any) -> Any:
    """Make free-form fields (stats, identifiable, ...) strict JSON: numpy values become Python ones,
    NaN/Inf become None. A stray NaN in the statistics must not cost us the calibration itself."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, str | bytes):
        return _jsonable(obj.tolist())  # numpy arrays and scalars
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if obj is None or isinstance(obj, str | int | float | bool):
        return obj
    return str(obj)  # Paths, enums, ...: readable rather than a failed write


def _check_push_status(status: object) -> None:
    if not isinstance(status, str) or not status:
        raise ValueError(f"push.status must be a non-empty string such as {PUSH_STATUSES}, got {status!r}")


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _spans(versions: list[int]) -> str:
    """Ascending versions as runs: [11, 12, 13, 15] -> 'v11-v13, v15'."""
    runs: list[list[int]] = []
    for v in versions:
        if runs and v == runs[-1][-1] + 1:
            runs[-1].append(v)
        else:
            runs.append([v])
    return ", ".join(f"v{r[0]}" if len(r) == 1 else f"v{r[0]}-v{r[-1]}" for r in runs)


IO_BEAT: list[Any] = []
"""Called before each fsync (the daemon's watchdog keep-alive, ``set_io_beat``): a store on a slow disk
(2-3 s per fsync) took 10.9 s for a record and its push result, and systemd's 10 s watchdog would have
killed the daemon mid-push (an operator's audit). An fsync that hangs for good still stops the pings."""


def set_io_beat(beat: Any) -> None:
    """Install (or, with None, remove) the callable run before each fsync of the store."""
    IO_BEAT[:] = [] if beat is None else [beat]


def _beat() -> None:
    for beat in IO_BEAT:
        try:
            beat()
        except Exception:  # a keep-alive must never fail a write
            log.debug("calibration store: io beat failed", exc_info=True)


def _fsync_dir(path: Path) -> None:
    """Make a rename or a new entry in ``path`` durable (POSIX needs the directory synced too)."""
    _beat()
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as JSON to ``path`` so that a crash leaves the old content or the new, never half.

    The temporary file lives in the same directory (os.replace is only atomic within a filesystem)
    and carries the pid, so two writers never share one. Its name starts with '.' and ends with
    '.tmp', so loaders skip it.
    """
    data = json.dumps(obj, indent=1, allow_nan=False, sort_keys=False).encode() + b"\n"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}{_TMP_SUFFIX}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            _beat()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        try:
            tmp.unlink()
        except OSError:
            pass
        if isinstance(err, OSError) and err.filename is None:  # a full disk says no path: name it
            raise OSError(err.errno, err.strerror, str(path)) from err
        raise
    _fsync_dir(path.parent)


class CalibrationStore:
    """Versioned calibration history per unit serial under ``state_dir/units``.

    Thread-safe within one process. Each call that writes is durable when it returns, so there is
    nothing to flush at shutdown (``close`` exists for symmetry). The in-memory view is loaded per
    serial on first use and kept in step with this process's writes.
    """

    def __init__(self, state_dir: Path | str) -> None:
        self.state_dir = Path(state_dir)
        self.units_dir = self.state_dir / "units"
        self._lock = threading.RLock()
        self._cache: dict[int, dict[int, CalibrationRecord]] = {}
        self._max_seen: dict[int, int] = {}  # highest version file name seen, valid or not
        # why the store could not be written at start, until a write goes through; or None
        self.read_only: str | None = None
        self._check_dir()

    def _check_dir(self) -> None:
        """A state directory that cannot be made or read is a configuration error (exit 2, the fix
        named). One that exists and can be read but not written (a read-only mount, an immutable
        directory) is a fault like a full disk: the daemon runs and learns, pushes nothing it cannot
        record, and says so (``read_only``; one ERROR line). It exited at start (an operator's audit),
        where docs/operations.md promises a read-only state directory never stops it."""
        fix = ("fix: create it writable by the daemon's user (under systemd, StateDirectory=gyrocal does "
               "this), or point state_dir in the config at a writable directory")
        try:
            self.units_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            if (not self.units_dir.exists() and self.state_dir.is_dir()
                    and os.access(self.state_dir, os.R_OK | os.X_OK)):
                # a readable state directory that cannot be written, with no store in it yet (a vehicle's
                # first boot on a read-only /var): the same fault as a full one, not an exit (it stopped
                # `gyrocal run` with exit 2, a restart loop under systemd: an operator's audit)
                self.read_only = f"{self.state_dir} cannot be written ({err.strerror or err})"
                log.error("calibration store: %s: the daemon runs and learns, but records and pushes no "
                          "set until it can be written (status: faults.store); %s", self.read_only, fix)
                return
            if not (self.units_dir.is_dir() and os.access(self.units_dir, os.R_OK | os.X_OK)):
                raise ConfigError(f"calibration store: cannot use state directory {self.state_dir}: "
                                  f"{err.strerror or err}; {fix}") from err
        if not os.access(self.units_dir, os.R_OK | os.X_OK):
            raise ConfigError(f"calibration store: state directory {self.units_dir} is not readable by "
                              f"uid {os.getuid()}; {fix}")
        why = None if os.access(self.units_dir, os.W_OK) else f"{self.units_dir} is not writable"
        if why is None:  # root passes access() on an immutable or read-only-mounted directory: try it
            probe = self.units_dir / f".probe-{os.getpid()}.tmp"
            try:
                probe.write_bytes(b"")
                probe.unlink()
            except OSError as err:
                why = f"{self.units_dir} cannot be written ({err.strerror or err})"
        if why is not None:
            self.read_only = why
            log.error("calibration store: %s: the daemon runs and learns, but records and pushes no set "
                      "until it can be written (status: faults.store); %s", why, fix)

    # --- reading -----------------------------------------------------------------------------------

    def units(self) -> list[int]:
        """Serials that have a directory in the store, ascending."""
        with self._lock:
            out = set(self._cache)
            try:
                for entry in os.scandir(self.units_dir):
                    if entry.is_dir() and entry.name.isdigit():
                        out.add(int(entry.name))
            except FileNotFoundError:
                pass  # no store yet (a read-only state directory at a first start)
            except OSError as err:
                log.warning("calibration store: cannot list %s: %s", self.units_dir, err)
            return sorted(out)

    def history(self, serial: int) -> list[CalibrationRecord]:
        """Every readable record of ``serial``, oldest version first."""
        with self._lock:
            recs = self._load(serial)
            return [recs[v] for v in sorted(recs)]

    def get(self, serial: int, version: int) -> CalibrationRecord | None:
        """The record of one version, or None if it does not exist (or was unreadable)."""
        with self._lock:
            return self._load(serial).get(version)

    def latest(self, serial: int, acked_only: bool = True) -> CalibrationRecord | None:
        """The newest record; with acked_only, the newest one the unit verifiably held (acked, or
        applied with its ack lost: the warm start)."""
        with self._lock:
            recs = self._load(serial)
            for v in sorted(recs, reverse=True):
                if not acked_only or recs[v].push.get("status") in APPLIED_STATUSES:
                    return recs[v]
            return None

    def held_last(self, serial: int) -> CalibrationRecord | None:
        """The set the unit verifiably held last: the applied record whose ack (or read-back) came
        last, by ``push.held_seq`` (a count, +1 at each), then push ``utc`` for records written
        before it, the highest version among equals. The warm start: after an operator's rollback to
        v2 the unit holds v2, and a restart that warm-started from the newest version (v7) pushed
        v7's set back at its bias stage, undoing the rollback (an operator's audit). By ``utc``
        alone, a wall clock corrected backwards (NTP, GPS) made an older set the last held: every
        switch-on warm-started from it, its gravity terms 100x off (an operator's audit)."""
        with self._lock:
            recs = self._load(serial)
            applied = [v for v in recs if recs[v].push.get("status") in APPLIED_STATUSES]
            if not applied:
                return None

            def order(v: int) -> tuple[int, str, int]:
                seq = recs[v].push.get("held_seq")
                return (seq if isinstance(seq, int) else -1, str(recs[v].push.get("utc") or ""), v)

            return recs[max(applied, key=order)]

    def next_version(self, serial: int) -> int:
        """One more than the highest version on disk, counting unreadable files so none is reused."""
        with self._lock:
            self._load(serial)
            return self._max_seen.get(serial, 0) + 1

    def _unit_dir(self, serial: int) -> Path:
        return self.units_dir / str(int(serial))

    def _load(self, serial: int) -> dict[int, CalibrationRecord]:
        if serial in self._cache:
            return self._cache[serial]
        recs: dict[int, CalibrationRecord] = {}
        max_seen = 0
        udir = self._unit_dir(serial)
        try:
            names = sorted(os.listdir(udir))
        except FileNotFoundError:
            names = []
        except OSError as err:
            log.warning("calibration store: cannot list %s: %s; treating unit %d as new", udir, err, serial)
            names = []
        for name in names:
            path = udir / name
            if name.endswith(_TMP_SUFFIX):  # removed by clean_leftovers() at daemon start
                log.warning("calibration store: ignoring leftover temporary file %s (an interrupted write; "
                            "safe to delete)", path)
                continue
            m = _VERSION_FILE.match(name)
            if not m:
                continue
            version = int(m.group(1))
            max_seen = max(max_seen, version)
            rec = self._read_file(path, serial, version)
            if rec is not None:
                recs[version] = rec
        self._cache[serial] = recs
        self._max_seen[serial] = max_seen
        return recs

    def clean_leftovers(self) -> int:
        """Delete the temporary files of interrupted writes under every unit (call at daemon start,
        when this process is the only writer); returns how many were removed."""
        removed = 0
        with self._lock:
            for serial in self.units():
                try:
                    names = os.listdir(self._unit_dir(serial))
                except OSError:
                    continue
                for name in names:
                    if name.endswith(_TMP_SUFFIX) and self._remove_leftover(self._unit_dir(serial) / name):
                        removed += 1
        return removed

    @staticmethod
    def _remove_leftover(path: Path) -> bool:
        """A '.vNNNNNN.json.<pid>.<tid>.tmp' of a write cut short: the final file is the old or the new
        version, never this one, so it is safe to delete. Ours (this pid) may be in flight: keep it."""
        if f".{os.getpid()}." in path.name:
            return False
        try:
            path.unlink()
        except FileNotFoundError:
            return False
        except OSError as err:
            log.warning("calibration store: cannot remove leftover temporary file %s (%s); it is ignored",
                        path, err)
            return False
        log.info("calibration store: removed leftover temporary file %s (an interrupted write)", path)
        return True

    @staticmethod
    def _read_file(path: Path, serial: int, version: int) -> CalibrationRecord | None:
        try:
            with open(path, "rb") as fh:
                rec = CalibrationRecord.from_dict(json.loads(fh.read()))
        except (OSError, ValueError, TypeError) as err:  # JSONDecodeError is a ValueError
            log.warning("calibration store: ignoring unreadable record %s: %s", path, err)
            return None
        if rec.serial != serial or rec.version != version:
            log.warning("calibration store: ignoring %s: it claims serial %d version %d",
                        path, rec.serial, rec.version)
            return None
        return rec

    # --- writing -----------------------------------------------------------------------------------

    def add(self, record: CalibrationRecord, min_version: int = 0) -> CalibrationRecord:
        """Write a new version durably and return it (with its version assigned if it was 0).

        Refuses to overwrite an existing version: history is append-only; push results change
        through update_push. ``min_version`` is a floor for an assigned version: the unit may hold a
        set this store never wrote (a factory set, another host's), and a new set must not go back
        below it, or two different sets would share a version on the unit's side.
        """
        record.normalise()
        record.validate()
        with self._lock:
            serial = record.serial
            recs = self._load(serial)
            auto = record.version == 0
            if auto:
                record.version = max(self._max_seen.get(serial, 0) + 1, int(min_version))
            elif record.version in recs or record.version <= 0:
                raise ValueError(f"unit {serial} already has version {record.version}; add with version=0")
            udir = self._unit_dir(serial)
            if not udir.is_dir():
                udir.mkdir(parents=True, exist_ok=True)
                _fsync_dir(self.units_dir)
            # Never replace a file we did not load (a directory we could not list, another writer):
            # history is append-only, whatever the in-memory view says.
            while (udir / f"v{record.version:06d}.json").exists():
                log.warning("calibration store: unit %d version %d exists on disk but was not loaded; "
                            "not overwriting it", serial, record.version)
                if not auto:
                    raise ValueError(f"unit {serial} already has version {record.version} on disk")
                record.version += 1
            atomic_write_json(udir / f"v{record.version:06d}.json", record.to_dict())
            self._written()
            recs[record.version] = record
            self._max_seen[serial] = max(self._max_seen.get(serial, 0), record.version)
            log.info("calibration store: unit %d version %d written (%d terms, push %s)",
                     serial, record.version, len(record.terms), record.push.get("status"))
            return record

    def update_push(self, serial: int, version: int, push: dict) -> CalibrationRecord:
        """Merge ``push`` into the record's push result and rewrite its file atomically.

        Only the keys given change, so a caller may report {"attempts": 2} and later
        {"status": "acked", "acked_crc": 0x1234, "readback_ok": True, "time": ...}.

        A version the unit verifiably held keeps that status whatever a later push of it (a
        rollback) ends as: the failed attempt goes into ``push.history``. An operator's rollback to
        v8 with the unit unplugged rewrote v8 'acked' -> 'abandoned', with no history; the next
        rollback to v8 was then refused, and the prune deleted it (an operator's audit).
        """
        with self._lock:
            rec = self._load(serial).get(version)
            if rec is None:
                raise KeyError(f"unit {serial} has no readable version {version}")
            held, status = rec.push.get("status"), push.get("status")
            if held in APPLIED_STATUSES and status is not None and status not in APPLIED_STATUSES:
                attempt = {k: push[k] for k in ("status", "reasons", "nak_reason", "utc") if k in push}
                push = {"history": [*(rec.push.get("history") or []), {**attempt, "of": "a later push"}]}
                log.warning("calibration store: unit %d version %d: a later push of it ended %s; the record "
                            "stays %s (the unit held it), the attempt is in push.history", serial, version,
                            status, held)
            if status in APPLIED_STATUSES:
                # the order the unit was seen holding sets in, which no clock correction reorders
                # (held_last)
                seqs = [r.push.get("held_seq") for r in self._load(serial).values()]
                push = {**push, "held_seq": 1 + max([s for s in seqs if isinstance(s, int)], default=0)}
            merged = {**rec.push, **push}
            _check_push_status(merged.get("status"))
            if merged.get("status") not in PUSH_STATUSES:
                log.warning("calibration store: unit %d version %d: unknown push status %r stored as given",
                            serial, version, merged.get("status"))
            new = CalibrationRecord(**{**{f.name: getattr(rec, f.name) for f in fields(rec)}, "push": merged})
            atomic_write_json(self._unit_dir(serial) / f"v{version:06d}.json", new.to_dict())
            self._written()
            self._cache[serial][version] = new
            log.info("calibration store: unit %d version %d push %s", serial, version, merged.get("status"))
            return new

    def _written(self) -> None:
        """A write went through: a store read-only at start is not any more. Status kept "... cannot be
        written (Permission denied)" to the end of a run whose store was locked and written from 21 s on
        (an integrator's campaign, rc33 G8)."""
        if self.read_only is not None:
            log.info("calibration store: written now; it could not be at start (%s)", self.read_only)
            self.read_only = None

    def prune(self, serial: int, keep: int) -> list[int]:
        """Delete all but the ``keep`` newest versions of ``serial`` (0: keep every one); returns the
        versions deleted, oldest first.

        Why: one version per push, a push per switch-on, for years. Each version is a 4 KB file and
        about 13 KB of memory once loaded, and every daemon start reads them all: 40,000 versions took
        11.4 s and 510 MB (benchmarks/bench_store.py). Never deleted whatever their age: the two newest
        sets the unit verifiably held (warm start, and the default rollback target), the one it
        acked last (a rollback re-sends an older version, which the unit then holds), and a push still
        pending. The newest version is always kept, so no version number is ever reused. A crash
        between two deletions leaves a shorter history, never a damaged one.
        """
        if keep <= 0:
            return []
        with self._lock:
            recs = self._load(serial)
            versions = sorted(recs)
            if len(versions) <= keep:
                return []
            applied = [v for v in versions if recs[v].push.get("status") in APPLIED_STATUSES]
            protect = set(versions[-keep:]) | set(applied[-2:])
            protect |= {v for v in versions if recs[v].push.get("status") == "pending"}
            held = self.held_last(serial)  # the one it acked last (an RLock: re-entered)
            if held is not None:
                protect.add(held.version)
            gone: list[int] = []
            udir = self._unit_dir(serial)
            for v in versions:
                if v in protect:
                    continue
                try:
                    (udir / f"v{v:06d}.json").unlink()
                except FileNotFoundError:
                    pass
                except OSError as err:  # a read-only store: one line, not one per version
                    log.warning("calibration store: cannot remove unit %d version %d (%s); the older "
                                "versions are kept until the store can be written", serial, v, err)
                    break
                del recs[v]
                gone.append(v)
            if gone:
                _fsync_dir(udir)
                which = f"v{gone[0]}" if len(gone) == 1 else f"{len(gone)} versions: {_spans(gone)}"
                # "v11 to v18" read as a range when v17 was kept (an operator's audit): spans, exactly
                log.info("calibration store: unit %d: removed %s, beyond the newest %d "
                         "(store.keep_versions); the sets the unit held last are kept", serial, which, keep)
            return gone

    def reload(self) -> None:
        """Forget the in-memory view; the next read rebuilds it from the files."""
        with self._lock:
            self._cache.clear()
            self._max_seen.clear()

    def close(self) -> None:
        """Nothing to flush: every write was fsynced before it returned. Kept for symmetry."""
