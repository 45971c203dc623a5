"""Reader ``tlog``: MAVLink telemetry logs (.tlog) through pymavlink (``pip install 'gyrocal[formats]'``).

A .tlog, as ground stations (QGroundControl, Mission Planner, MAVProxy) write it, is a sequence of
records: an 8-byte big-endian timestamp [us since the Unix epoch, the ground station's clock] and
one MAVLink packet as received. ``mavutil.mavlink_connection(path)`` reads it (an mmap index by
message id, then a decode of the wanted types).

Which IMU messages, and in what units, is the MAVLink link's business: ``gyrocal.mavlink.imu.decode``
converts HIGHRES_IMU (rad/s, m/s^2), SCALED_IMU/2/3 and RAW_IMU (mrad/s, mG, truncated to int16:
read at each step's centre) to deg/s and g, and gives each message's time since boot and
temperature (docs/mavlink.md says what each autopilot puts in them). Per IMU instance (``--instance``):

- the stream: HIGHRES_IMU (instance = its ``id`` field) if the log holds it, else SCALED_IMU(n)
  (SCALED_IMU = 0, SCALED_IMU2 = 1, SCALED_IMU3 = 2), else RAW_IMU (its ``id``); the same
  instance's other streams are counted in ``dropped`` as ``lower_priority_<type>``. ``--topic``
  names the message to read instead. A PX4 (its HEARTBEAT) sends in HIGHRES_IMU the IMU it
  selected, whichever it is, with ``id`` never set (0), minus EKF2's gyro bias estimate
  (MavlinkStreamHighresIMU): its SCALED_IMU(n), IMU n itself, is read instead when the log has it,
  and a HIGHRES_IMU read all the same gets no temperature (its chip is not known), with a warning.
  Before, HIGHRES_IMU was taken for IMU 0 with SCALED_IMU's temperature, another chip's after a
  failover (a foreign-log audit);
- the temperature: the stream's own (SCALED/RAW_IMU; 0 means not given), or for HIGHRES_IMU (whose
  ``temperature`` is the barometer's) the SCALED_IMU(n), else RAW_IMU, of that instance; the last
  value received is held, as the live link does, and samples before the first one are dropped
  (``no_temperature``). A log without any IMU temperature gives no temp column, with a warning;
- one vehicle: the system and component of the first IMU message; others are ``other_source``;
- sessions: the boot time going back (more than 0.5 s, ``BootDetector``) starts a new session;
  a sample not after the previous one (a message logged twice) is ``time_not_increasing``;
- a message whose gyro and accel are all exactly zero (ArduPilot sends SCALED_IMU2/3 so for an
  IMU it does not have) is ``all_zero``; IMU records pymavlink indexed but could not decode (bad
  CRC) are ``unreadable``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import CANONICAL_UNITS, LogData
from gyrocal.readers import ReadOptions, require

HIGHRES, RAW = "HIGHRES_IMU", "RAW_IMU"
MAV_AUTOPILOT_PX4 = 12
BOOT_BACK_S = 0.5
"""Boot time going back by more than this [s] is a new boot (``BootDetector``'s margin)."""


@dataclass
class _Stream:
    """The decoded messages of one (message type, instance), in file order."""

    order: list[int] = field(default_factory=list)  # position among the file's IMU messages
    t: list[float] = field(default_factory=list)  # s since boot
    gyro: list[tuple[float, float, float]] = field(default_factory=list)  # deg/s
    accel: list[tuple[float, float, float]] = field(default_factory=list)  # g
    temp: list[float] = field(default_factory=list)  # degC, NaN = not given
    all_zero: list[bool] = field(default_factory=list)


def _instance(msg: Any, kind: str, scaled: tuple[str, ...]) -> int:
    if kind in scaled:
        return scaled.index(kind)
    return int(getattr(msg, "id", 0) or 0)  # a MAVLink 2 extension field: 0 when not sent


def _open(path: str) -> Any:
    require("pymavlink", "reading MAVLink .tlog logs")
    from gyrocal.mavlink import pymav

    if not Path(path).is_file():  # else pymavlink takes the name for a serial port
        raise LogFormatError(f"{path}: cannot open the log (no such file)")

    try:
        return pymav.mavutil().mavlink_connection(path, dialect="ardupilotmega")
    except OSError as err:
        raise LogFormatError(f"{path}: cannot open the log ({err.strerror})") from err
    except Exception as err:  # pymavlink raises what its parsing hits on a damaged file
        raise LogFormatError(f"{path}: pymavlink cannot read it as a .tlog ({err})") from err


def read_tlog(path: str, options: ReadOptions) -> LogData:
    """One IMU instance of a .tlog as log columns (deg/s, g, degC, s); see the module docstring."""
    from gyrocal.mavlink import imu

    conn = _open(path)
    types = (HIGHRES, *imu.SCALED_BY_INSTANCE, RAW)
    streams: dict[tuple[str, int], _Stream] = {}
    source: tuple[int, int] | None = None
    other_source = 0
    n = 0
    seen = dict.fromkeys(types, 0)  # messages pymavlink decoded, by type
    meta: dict[str, str] = {}
    first = getattr(conn, "messages", {})
    autopilot: dict[tuple[int, int], int] = {}  # MAV_AUTOPILOT of each HEARTBEAT's sender
    try:
        version = first.get("AUTOPILOT_VERSION")
        while True:
            m = conn.recv_match(type=[*types, "HEARTBEAT"])
            if m is None:
                break
            kind = m.get_type()
            if kind == "HEARTBEAT":
                autopilot.setdefault((m.get_srcSystem(), m.get_srcComponent()), int(m.autopilot))
                continue
            seen[kind] = seen.get(kind, 0) + 1
            src = (m.get_srcSystem(), m.get_srcComponent())
            if source is None:
                source = src
            elif src != source:
                other_source += 1
                continue
            r = imu.decode(m)
            if r is None:
                continue
            s = streams.setdefault((kind, _instance(m, kind, imu.SCALED_BY_INSTANCE)), _Stream())
            s.order.append(n)
            s.t.append(r.t_s)
            s.gyro.append(r.gyro_dps)
            s.accel.append(r.accel_g)
            s.temp.append(np.nan if r.temp_c is None else r.temp_c)
            s.all_zero.append(not any(r.gyro_dps) and not any(r.accel_g))
            n += 1
        names = getattr(conn, "id_to_name", {})
        counts = {names.get(k, str(k)): c for k, c in getattr(conn, "counts", {}).items()}
    except LogFormatError:
        raise
    except Exception as err:  # as above
        raise LogFormatError(f"{path}: MAVLink record unreadable ({err})") from err
    finally:
        close = getattr(conn, "close", None)
        if close is not None:
            close()
    unreadable = sum(max(counts.get(k, 0) - seen[k], 0) for k in types)
    inst = options.instance
    mine = [(HIGHRES, inst), (imu.SCALED_BY_INSTANCE[inst], inst) if inst < 3 else None, (RAW, inst)]
    present = [key for key in mine if key is not None and key in streams]
    real = [key for key in present if not all(streams[key].all_zero)]
    have = sorted({f"{k}[{i}]" for (k, i), s in streams.items() if not all(s.all_zero)})
    if not real:
        zero = [f"{k}[{i}]" for k, i in present]
        why = f" ({', '.join(zero)} all zero: the autopilot has no such IMU)" if zero else ""
        raise LogFormatError(f"{path}: no IMU messages of instance {inst}{why}; streams with data: "
                             f"{', '.join(have) or 'none'} (--instance N)")
    warnings: list[str] = []
    px4 = source is not None and autopilot.get(source) == MAV_AUTOPILOT_PX4
    if options.topic is not None:
        if options.topic not in types:
            raise ConfigError(f"--topic {options.topic}: a .tlog's IMU messages are {', '.join(types)}")
        real = [key for key in real if key[0] == options.topic]
        if not real:
            raise LogFormatError(f"{path}: no {options.topic} messages of instance {inst}; streams with "
                                 f"data: {', '.join(have) or 'none'} (--instance N, --topic NAME)")
    elif px4 and real[0][0] == HIGHRES and len(real) > 1:
        real = real[1:]
        warnings.append(f"{path}: a PX4's HIGHRES_IMU is the IMU it selected (its id is never set) minus "
                        f"EKF2's gyro bias estimate; {real[0][0]}[{inst}], IMU {inst} itself, is read "
                        "instead (1 mrad/s steps; --topic HIGHRES_IMU reads HIGHRES_IMU)")
    chosen = real[0]
    px4_highres = px4 and chosen[0] == HIGHRES
    if px4_highres:
        warnings.append(f"{path}: a PX4's HIGHRES_IMU is the IMU it selected, not always IMU {inst} (its "
                        "id is never set), minus EKF2's gyro bias estimate: an offset fitted to it is what "
                        "EKF2 had not removed, and it gets no temperature (which chip's is not known)")
    dropped: dict[str, int] = {}
    for key in present:
        if key != chosen:
            dropped[f"lower_priority_{key[0].lower()}"] = len(streams[key].t)
    if unreadable > 0:
        dropped["unreadable"] = unreadable
    if other_source:
        dropped["other_source"] = other_source
    s = streams[chosen]
    order = np.asarray(s.order)
    t = np.asarray(s.t, dtype=np.float64)
    g = np.asarray(s.gyro, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(s.accel, dtype=np.float64).reshape(-1, 3)
    keep = ~np.asarray(s.all_zero, dtype=bool)
    # the temperature: held from the last message of the temperature stream (file order)
    temp_src = chosen if chosen[0] != HIGHRES else None if px4_highres else next(
        (k for k in mine[1:] if k is not None and k in streams and np.isfinite(streams[k].temp).any()), None)
    temp: np.ndarray | None = None
    if temp_src is not None:
        ts = streams[temp_src]
        tv = np.asarray(ts.temp, dtype=np.float64)
        ok = np.isfinite(tv)
        if ok.any():
            t_order, t_val = np.asarray(ts.order)[ok], tv[ok]
            j = np.searchsorted(t_order, order, side="right") - 1  # the last one at or before
            temp = np.where(j >= 0, t_val[np.maximum(j, 0)], np.nan)
            no_temp = keep & ~np.isfinite(temp)
            if no_temp.any():
                dropped["no_temperature"] = int(no_temp.sum())
            keep &= np.isfinite(temp)
            meta["temperature_from"] = f"{temp_src[0]}[{temp_src[1]}]"
    if temp is None and not px4_highres:  # that one's warning says so
        warnings.append(f"{path}: {chosen[0]}[{inst}] comes without an IMU temperature; the log has no "
                        "temp column (a fit of temperature terms needs one)")
    if (~np.asarray(s.all_zero, dtype=bool)).sum() < len(s.t):
        dropped["all_zero"] = int(np.asarray(s.all_zero).sum())
    # sessions: boot time going back; a sample not after the previous one is dropped
    session = np.zeros(t.size)
    k, last = 0, None
    idx = np.flatnonzero(keep)
    for i in idx:
        ti = t[i]
        if last is not None and ti < last - BOOT_BACK_S:
            k += 1
        elif last is not None and ti <= last:
            keep[i] = False
            dropped["time_not_increasing"] = dropped.get("time_not_increasing", 0) + 1
            continue
        session[i] = k
        last = ti
    finite = np.isfinite(t) & np.isfinite(g).all(axis=1) & np.isfinite(a).all(axis=1)
    if (keep & ~finite).any():
        dropped["nonfinite"] = int((keep & ~finite).sum())
    keep &= finite
    cols = {"t": t[keep]}
    for c, ax in enumerate("xyz"):
        cols[f"w{ax}"] = g[keep, c]
    for c, ax in enumerate("xyz"):
        cols[f"a{ax}"] = a[keep, c]
    if temp is not None:
        cols["temp"] = temp[keep]
    cols["session"] = session[keep]
    selected = " (the IMU PX4 selected)" if px4_highres else ""
    meta.update({"sensor": f"MAVLink {chosen[0]}[{inst}]{selected}",
                 "frame": "FRD body",
                 "correction": "after the autopilot's offsets and board rotation"
                 + (", minus EKF2's gyro bias estimate" if px4_highres else "") + " (docs/mavlink.md)",
                 "source_system": f"{source[0]}/{source[1]}" if source else "",
                 "imu_streams": ", ".join(have), "units": CANONICAL_UNITS})
    others = sum(len(st.t) for key, st in streams.items() if key[1] != inst)
    if others:
        meta["other_instance_messages"] = str(others)
    if version is not None and (source is None or version.get_srcSystem() == source[0]):
        uid2 = list(getattr(version, "uid2", []) or [])
        meta["unit_serial"] = str(imu.derive_serial(int(version.uid), uid2, inst, source[0] if source else 0))
        meta["firmware"] = imu.fw_text(version.flight_sw_version)
    return LogData(cols, meta, [], path, dropped, warnings,
                   data_rows=int(cols["t"].size) + sum(dropped.values()))
