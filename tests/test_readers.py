"""Readers: every format gives the same samples in deg/s, g, degC, s, and counts what it dropped."""

from __future__ import annotations

import json
import math
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest

from gyrocal.cli import main
from gyrocal.errors import ConfigError, LogFormatError
from gyrocal.logformat import read_log, write_log
from gyrocal.protocol.messages import Hello, Sample
from gyrocal.protocol.serial_framing import encode_frame
from gyrocal.readers import ReadOptions, detect_kind, options_from_args, read_any
from gyrocal.readers.units import parse_units
from gyrocal.sim.schedule import tumble
from gyrocal.sim.truth import SessionStream, TruthModel
from tests.foreign_logs import write_dataflash, write_rosbag, write_rosbag1

DATA = Path(__file__).resolve().parent.parent / "data"
COLS = ("t", "wx", "wy", "wz", "ax", "ay", "az", "temp", "session")
D2R, G0 = math.pi / 180.0, 9.80665


@pytest.fixture(scope="module")
def sim_cols() -> dict[str, np.ndarray]:
    cols = SessionStream(TruthModel(), tumble(), 100.0, seed=2, boot=0).chunk(7200)
    return {k: np.asarray(cols[k], dtype=np.float64) for k in COLS}


@pytest.fixture(scope="module")
def dps_log(sim_cols: dict[str, np.ndarray], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("readers") / "dps.csv"
    write_log(path, sim_cols)
    return path


def _fit(args: list[str], capsys: pytest.CaptureFixture) -> tuple[dict, str]:
    assert main(["fit", *args, "--json"]) == 0
    out = capsys.readouterr()
    return json.loads(out.out), out.err


def test_written_logs_declare_their_units(dps_log: Path) -> None:
    head = dps_log.read_text().splitlines()[0]
    assert head == "# units: gyro=deg/s accel=g temp=degC time=s"


def test_si_csv_with_other_names_warns_and_the_units_flag_fixes_it(
        sim_cols: dict[str, np.ndarray], dps_log: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture) -> None:
    si = {"time_ms": sim_cols["t"] * 1e3, "temperature": sim_cols["temp"] + 273.15}
    for a in "xyz":
        si[f"gyro_{a}"] = sim_cols[f"w{a}"] * D2R
        si[f"acc_{a}"] = sim_cols[f"a{a}"] * G0
    path = tmp_path / "si.csv"
    header = list(si)
    np.savetxt(path, np.column_stack([si[h] for h in header]), delimiter=",", fmt="%.12g",
               header=",".join(header), comments="")
    cmap = "t=time_ms,temp=temperature," + ",".join(f"w{a}=gyro_{a},a{a}=acc_{a}" for a in "xyz")
    ref, _ = _fit([str(dps_log)], capsys)
    wrong, err = _fit([str(path), "--columns", cmap, "--units", "time=ms,temp=K"], capsys)
    assert "looks like m/s^2" in err and "--units" in err and wrong["warnings"]
    units = "gyro=rad/s,accel=m/s^2,time=ms,temp=K"
    fixed, err = _fit([str(path), "--columns", cmap, "--units", units], capsys)
    assert "warning" not in err and not fixed["warnings"]
    for a in "xyz":
        got = np.array(fixed["coefficients"][a], dtype=float)
        np.testing.assert_allclose(got, np.array(ref["coefficients"][a], dtype=float), rtol=1e-5, atol=1e-9)
    # the '# units:' header line does the same as the flag
    body = path.read_text()
    path.write_text("# units: gyro=rad/s accel=m/s^2 time=ms temp=K\n" + body)
    log = read_log(path, rename=dict(p.split("=") for p in cmap.split(",")))
    np.testing.assert_allclose(log["wx"], sim_cols["wx"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(log["az"], sim_cols["az"], rtol=1e-9, atol=1e-12)
    assert not log.warnings


def test_bad_column_map_and_units_name_the_fix(dps_log: Path) -> None:
    with pytest.raises(LogFormatError, match=r"--columns wx=gyro_x: no such column"):
        read_any(dps_log, options=ReadOptions(columns={"wx": "gyro_x"}))
    with pytest.raises(ConfigError, match=r"unit 'furlong/s' unknown for gyro"):
        parse_units("gyro=furlong/s")
    with pytest.raises(ConfigError, match=r"--columns: 'wx' is not OURS=THEIRS"):
        options_from_args(Namespace(columns="wx", units=None))
    with pytest.raises(ConfigError, match="unknown log extension"):
        detect_kind("x.xyz")


def test_missing_columns_come_with_a_column_map_to_try(tmp_path: Path) -> None:
    path = tmp_path / "other.csv"
    path.write_text("timestamp,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z\n0,0,0,0,0,0,1\n")
    hint = "t=timestamp,wx=gyro_x,wy=gyro_y,wz=gyro_z,ax=acc_x,ay=acc_y,az=acc_z"
    with pytest.raises(LogFormatError, match=f"perhaps --columns {hint}"):
        read_any(path)
    log = read_any(path, options=ReadOptions(columns=dict(p.split("=") for p in hint.split(","))))
    assert len(log) == 1 and log["az"][0] == 1.0


def test_text_columns_of_a_foreign_csv_are_left_out_with_a_warning(tmp_path: Path) -> None:
    path = tmp_path / "foreign.csv"
    path.write_text("t,frame,wx,wy,wz,ax,ay,az,note\n" + "".join(
        f"{i / 100},imu_link,0.1,0.2,0.3,0,0,1,{'ok' if i % 2 else 'still'}\n" for i in range(30)))
    log = read_any(path)
    assert len(log) == 30 and not log.has("frame") and not log.has("note")
    assert any("column 'frame' is not numeric" in w for w in log.warnings)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,wx,wy,wz,ax,ay,az\n0,0.1,0.2,0.3,0,0,1\n0.01,0.1,x,0.3,0,0,1\n")
    with pytest.raises(LogFormatError, match=r"bad.csv:3: column 'wy' holds 'x'"):
        read_any(bad)


def test_fit_counts_the_nan_rows_it_dropped(sim_cols: dict[str, np.ndarray], tmp_path: Path,
                                            capsys: pytest.CaptureFixture) -> None:
    cols = {k: v.copy() for k, v in sim_cols.items()}
    cols["wx"][100:150] = np.nan
    path = tmp_path / "nan.csv"
    write_log(path, cols)
    res, _ = _fit([str(path)], capsys)
    assert res["skipped"]["nonfinite"] == 50 and res["source_rows"] == 7200 and res["rows"] == 7150
    assert res["skipped"]["not_still"] == 7150 - res["samples"]
    assert main(["fit", str(path)]) == 0
    assert "50 nonfinite" in capsys.readouterr().out


def test_empty_and_all_nan_logs_name_the_real_cause(sim_cols: dict[str, np.ndarray], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    empty = tmp_path / "empty.csv"
    empty.write_text("t,wx,wy,wz,ax,ay,az\n")
    nan = tmp_path / "nan.csv"
    nan.write_text("t,wx,wy,wz,ax,ay,az\n" + "0,nan,0,0,0,0,1\n" * 20)
    for flag in ([], ["--all-samples"]):
        assert main(["fit", str(empty), *flag]) == 2
        err = capsys.readouterr().err
        assert "no data rows" in err and "still" not in err
        assert main(["fit", str(nan), *flag]) == 2
        err = capsys.readouterr().err
        assert "all 20 data rows were dropped (20 nonfinite)" in err and "still" not in err


def test_nlms_uncertainty_includes_its_distance_from_least_squares(dps_log: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    batch, _ = _fit([str(dps_log), "--method", "batch"], capsys)
    nlms, _ = _fit([str(dps_log), "--method", "nlms"], capsys)
    assert batch["uncertainty_kind"] == "ls_1sigma" and nlms["uncertainty_kind"] == "ls_1sigma_plus_offset"
    for a in "xyz":
        for j, (c, cb, s, sb) in enumerate(zip(nlms["coefficients"][a], batch["coefficients"][a],
                                               nlms["uncertainty"][a], batch["uncertainty"][a], strict=True)):
            if s is None:
                continue
            # the reported sigma covers the gap to the least-squares solution, and is never below LS's
            assert abs(c - cb) <= s * (1 + 1e-9) and s >= sb * (1 - 1e-9), (a, j)
            off = nlms["offset_from_ls_sigma"][a][j]
            assert off == pytest.approx(abs(c - cb) / sb, rel=1e-6, abs=1e-9)
    assert main(["fit", str(dps_log), "--method", "nlms"]) == 0
    assert "LS-sigma from the least-squares solution" in capsys.readouterr().out


def test_python_can_recordings_decode_with_our_dbc(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    import can

    blf = read_any(DATA / "sim_can" / "virtual_unit.blf")
    assert len(blf) == 4000 and blf.metadata["unit_serial"] == "4242"
    assert blf.metadata["applied_version"] == "3"
    assert not blf.dropped and np.all(np.diff(blf["t"]) > 0) and set(blf["session"]) == {0.0}
    assert np.allclose(np.median(np.linalg.norm(blf.accel_g, axis=1)), 1.0, atol=0.02)
    asc = read_any(DATA / "sim_can" / "virtual_unit_short.asc")
    assert len(asc) == 500 and asc.metadata["host_frames"] == "2"
    # the same frames in candump's .log format, written by python-can, read the same
    candump = tmp_path / "short.log"
    with can.Logger(str(candump)) as out:
        for frame in can.LogReader(str(DATA / "sim_can" / "virtual_unit_short.asc")):
            out(frame)
    again = read_any(candump)
    for c in ("t", "wx", "az", "temp"):
        np.testing.assert_array_equal(again[c], asc[c])
    res, _ = _fit([str(DATA / "sim_can" / "virtual_unit.blf"), "--terms", "1", "--all-samples"], capsys)
    assert res["samples"] == 4000 and res["skipped"]["nonfinite"] == 0
    # CAN carries accel in 1 mg steps: still periods must still be found (27 s of 40 s are dwell)
    res, _ = _fit([str(DATA / "sim_can" / "virtual_unit.blf")], capsys)
    assert res["samples"] > 1500 and res["identifiable"]["rank"] == 9


def _samples(n: int, seq0: int = 0) -> list[Sample]:
    return [Sample(seq0 + i, i / 100, (0.01, 0.02, 0.03), (0.0, 0.0, 1.0), 30.0) for i in range(n)]


def test_serial_capture_counts_garbage_and_crc_failures_and_splits_sessions(tmp_path: Path) -> None:
    cap = tmp_path / "run.cap"
    bad = bytearray(encode_frame(_samples(1, 50)[0]))
    bad[-1] ^= 0xFF  # corrupt the CRC
    data = (b"\x00\x13garbage" + encode_frame(Hello(77, "1.2.3", 5, 100))
            + b"".join(encode_frame(s) for s in _samples(50)) + bytes(bad)
            + encode_frame(Hello(77, "1.2.3", 6, 100)) + b"".join(encode_frame(s) for s in _samples(30))
            + encode_frame(_samples(1)[0])[:7])  # cut by the end of the capture
    cap.write_bytes(data)
    log = read_any(cap)
    assert len(log) == 80 and list(np.bincount(log["session"].astype(int))) == [50, 30]
    assert log.metadata["unit_serial"] == "77" and log.dropped["crc_errors"] == 1
    assert log.dropped["garbage_bytes"] >= 9 and log.dropped["truncated_bytes"] == 7
    (tmp_path / "x.bin").write_bytes(data)  # a .bin without DataFlash's header is a serial capture
    assert detect_kind(tmp_path / "x.bin") == "serial"


def test_px4_ulog_reads_sensor_gyro_or_falls_back_to_sensor_combined() -> None:
    pytest.importorskip("pyulog")
    path = DATA / "px4_ulog" / "sample_log_small.ulg"
    log = read_any(path)
    assert len(log) == 1298 and "sensor_combined" in log.warnings[0] and "AFTER" in log.warnings[0]
    assert np.median(np.linalg.norm(log.accel_g, axis=1)) == pytest.approx(1.0, abs=0.05)
    assert not log.has("temp")
    raw = read_any(path, options=ReadOptions(topic="sensor_gyro", instance=1))
    assert len(raw) + raw.dropped.get("no_accel", 0) == 6 and raw.has("temp")
    assert 20 < float(np.median(raw["temp"])) < 40 and raw.metadata["frame"] == "FRD board"
    with pytest.raises(LogFormatError, match=r"instances logged: \[0, 1, 2\]"):
        read_any(path, options=ReadOptions(topic="sensor_gyro", instance=5))


def test_ardupilot_dataflash_imu_instances(sim_cols: dict[str, np.ndarray], tmp_path: Path) -> None:
    pytest.importorskip("pymavlink")
    n = 400
    g = np.column_stack([sim_cols[f"w{a}"][:n] for a in "xyz"]) * D2R
    acc = np.column_stack([sim_cols[f"a{a}"][:n] for a in "xyz"]) * G0
    path = tmp_path / "flight.bin"
    write_dataflash(path, sim_cols["t"][:n], g, acc, sim_cols["temp"][:n], instances=2)
    assert detect_kind(path) == "dataflash"
    log = read_any(path)
    assert len(log) == n and log.metadata["other_instance_records"] == str(n)
    np.testing.assert_allclose(log["wx"], sim_cols["wx"][:n], atol=1e-4)  # float32 in the file
    np.testing.assert_allclose(log["az"], sim_cols["az"][:n], atol=1e-6)
    np.testing.assert_allclose(log["temp"], sim_cols["temp"][:n], atol=1e-4)
    second = read_any(path, options=ReadOptions(instance=1))
    np.testing.assert_allclose(second["wx"] - log["wx"], 0.01 / D2R, atol=1e-4)
    with pytest.raises(LogFormatError, match=r"instances seen: \[0, 1\]"):
        read_any(path, options=ReadOptions(instance=2))


def test_old_ardupilot_dataflash_layouts_read_their_time_and_temperature(sim_cols: dict[str, np.ndarray],
                                                                           tmp_path: Path) -> None:
    """Copter 3.2 / Solo logs: IMU and IMU2 messages, TimeMS [ms], Temp. The reader crashed with a
    traceback (KeyError 'TimeUS'); a 3.3-3.6 log's Temp was dropped with no word; the other IMU's
    records were not counted (a foreign-log audit)."""
    pytest.importorskip("pymavlink")
    n = 300
    g = np.column_stack([sim_cols[f"w{a}"][:n] for a in "xyz"]) * D2R
    acc = np.column_stack([sim_cols[f"a{a}"][:n] for a in "xyz"]) * G0
    t = 12.0 + np.arange(n) * 0.02  # 50 Hz, whole ms
    path = tmp_path / "old.bin"
    write_dataflash(path, t, g, acc, sim_cols["temp"][:n], instances=2, old=True)
    log = read_any(path)
    np.testing.assert_allclose(log["t"], t, atol=1e-9)
    np.testing.assert_allclose(log["temp"], sim_cols["temp"][:n], atol=1e-4)
    np.testing.assert_allclose(log["wx"], sim_cols["wx"][:n], atol=1e-4)
    assert log.metadata["other_instance_records"] == str(n) and not log.warnings
    second = read_any(path, options=ReadOptions(instance=1))
    np.testing.assert_allclose(second["wx"] - log["wx"], 0.01 / D2R, atol=1e-4)
    # a board with no temperature sensor logs Temp = 0.0: no temp column, and a warning
    write_dataflash(path, t, g, acc, np.zeros(n), old=True)
    log = read_any(path)
    assert "temp" not in log.columns and any("without a temperature" in w for w in log.warnings)


def test_a_bag_whose_stamps_never_move_is_read_on_its_record_times(sim_cols: dict[str, np.ndarray],
                                                                      tmp_path: Path) -> None:
    """A driver that leaves header.stamp at 0: all 4000 samples were read at t = 0, with no word."""
    pytest.importorskip("rosbags")
    n = 200
    g = np.column_stack([sim_cols[f"w{a}"][:n] for a in "xyz"]) * D2R
    acc = np.column_stack([sim_cols[f"a{a}"][:n] for a in "xyz"]) * G0
    bag = tmp_path / "bag"
    write_rosbag(bag, 100.0 + sim_cols["t"][:n], g, acc, sim_cols["temp"][:n], zero_stamps=True)
    log = read_any(bag)
    np.testing.assert_allclose(log["t"], 100.0 + sim_cols["t"][:n], atol=1e-6)
    assert log.metadata["time_from"] == "record time" and any("header.stamp" in w for w in log.warnings)
    assert np.all(np.abs(log["temp"] - sim_cols["temp"][:n]) < 0.5)


def test_times_counted_from_1970_keep_their_microseconds_when_written(tmp_path: Path) -> None:
    """`convert` wrote t with 10 significant digits: a 250 Hz log stamped from 1970 (a PX4 SITL .ulg,
    every ROS bag) came out as runs of equal whole seconds."""
    t = 1710773350.354 + np.arange(500) * 0.004
    cols = {"t": t, **{c: np.zeros(500) for c in ("wx", "wy", "wz", "ax", "ay")}, "az": np.ones(500)}
    write_log(tmp_path / "epoch.csv", cols)
    back = read_any(tmp_path / "epoch.csv")
    np.testing.assert_allclose(np.diff(back["t"]), 0.004, atol=1e-6)
    np.testing.assert_allclose(back["t"], t, rtol=0, atol=1e-6)


def test_rosbag2_imu_with_temperature(sim_cols: dict[str, np.ndarray], tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    n = 300
    g = np.column_stack([sim_cols[f"w{a}"][:n] for a in "xyz"]) * D2R
    acc = np.column_stack([sim_cols[f"a{a}"][:n] for a in "xyz"]) * G0
    bag = tmp_path / "bag"
    write_rosbag(bag, 100.0 + sim_cols["t"][:n], g, acc, sim_cols["temp"][:n])
    log = read_any(bag)
    assert len(log) == n and log.metadata["frame"] == "imu_link"
    np.testing.assert_allclose(log["wy"], sim_cols["wy"][:n], atol=1e-9)
    np.testing.assert_allclose(log["ay"], sim_cols["ay"][:n], atol=1e-12)
    assert np.all(np.abs(log["temp"] - sim_cols["temp"][:n]) < 0.5)


def test_mcap_and_ros1_bags(sim_cols: dict[str, np.ndarray], tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    n = 200
    g = np.column_stack([sim_cols[f"w{a}"][:n] for a in "xyz"]) * D2R
    acc = np.column_stack([sim_cols[f"a{a}"][:n] for a in "xyz"]) * G0
    write_rosbag(tmp_path / "m", sim_cols["t"][:n] + 1.0, g, acc, mcap=True)
    lone = tmp_path / "lone.mcap"  # an .mcap file on its own, without the bag's metadata.yaml
    lone.write_bytes(next((tmp_path / "m").glob("*.mcap")).read_bytes())
    write_rosbag1(tmp_path / "r1.bag", sim_cols["t"][:n] + 1.0, g, acc)
    for path in (tmp_path / "m", lone, tmp_path / "r1.bag"):
        log = read_any(path)
        assert len(log) == n, path
        np.testing.assert_allclose(log["wz"], sim_cols["wz"][:n], atol=1e-9)
        np.testing.assert_allclose(log["ax"], sim_cols["ax"][:n], atol=1e-12)


def test_convert_a_foreign_log_to_csv_and_back(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "blf.csv"
    assert main(["convert", str(DATA / "sim_can" / "virtual_unit.blf"), str(out)]) == 0
    back = read_log(out)
    direct = read_any(DATA / "sim_can" / "virtual_unit.blf")
    assert back.metadata["unit_serial"] == "4242" and back.metadata["units"].startswith("gyro=deg/s")
    np.testing.assert_allclose(back["wz"], direct["wz"], rtol=1e-9)


@pytest.mark.parametrize("name", ["x.bin", "x.ulg", "x.blf", "x.asc", "x.log", "x.mcap", "x.db3", "x.bag",
                                  "x.cap", "df.bin", "cut.blf", "cut.ulg", "x.tlog", "cut.tlog"])
def test_damaged_or_foreign_files_end_in_one_line_never_a_traceback(name: str, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture) -> None:
    rng = np.random.default_rng(sum(map(ord, name)))
    junk = rng.integers(0, 256, 6000, dtype=np.uint8).tobytes()
    path = tmp_path / name
    if name == "df.bin":
        junk = b"\xa3\x95" + junk  # DataFlash's header, then garbage
    elif name.startswith("cut."):  # a real recording cut in the middle
        src = DATA / {"blf": "sim_can/virtual_unit.blf", "ulg": "px4_ulog/sample_log_small.ulg",
                      "tlog": "ardusub_tlog/small.tlog"}[name.split(".")[-1]]
        junk = src.read_bytes()[: src.stat().st_size // 2]
    elif name in ("x.asc", "x.log"):
        junk = b"".join(b"line %d of something else\n" % i for i in range(50))
    path.write_bytes(junk)
    rc = main(["fit", str(path), "--terms", "1", "--all-samples"])
    # a bus another test of this worker left to the garbage collector may say so here (python-can's
    # "UdpMulticastBus was not properly shut down"): not this command's output
    err = "".join(ln for ln in capsys.readouterr().err.splitlines(keepends=True) if " can.bus: " not in ln)
    assert "Traceback" not in err
    if rc != 0:
        assert rc == 2 and err.startswith("gyrocal: error: ") and str(path.name) in err


def test_a_csv_with_a_utf8_bom_reads_like_one_without(tmp_path: Path) -> None:
    """Excel writes a byte order mark first: the header then read "\\ufefft", and the error said
    "required column(s) t missing" (every column, with the BOM before a `# units:` line): a
    foreign-log audit. The BOM is skipped, by the whole-file and the streaming readers."""
    from gyrocal.readers import ReadOptions, read_any

    n = 50
    cols = {"t": np.arange(n) * 0.01, "wx": np.full(n, 0.1), "wy": np.zeros(n), "wz": np.zeros(n),
            "ax": np.zeros(n), "ay": np.zeros(n), "az": np.ones(n), "temp": np.full(n, 25.0)}
    plain = tmp_path / "plain.csv"
    write_log(plain, cols, {"units": "t=s, gyro=deg/s, accel=g, temp=degC"})
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes().replace(b"\n", b"\r\n"))
    a, b = read_log(plain), read_log(bom)
    assert len(b) == n and np.array_equal(a["wx"], b["wx"]) and np.array_equal(a["t"], b["t"])
    assert len(read_any(str(bom), None, ReadOptions())) == n


def test_a_text_can_log_cut_mid_line_keeps_its_frames_and_counts_the_cut(tmp_path: Path) -> None:
    """A logger killed mid-write leaves a last line without its newline; python-can then raised and
    the whole file was refused (a foreign-log audit). The frames before it stand, the cut bytes are
    counted as truncated_bytes (as the .cap and .blf readers do)."""
    from gyrocal.readers import ReadOptions, read_any

    src = Path(__file__).resolve().parents[1] / "data" / "sim_can" / "virtual_unit_short.asc"
    whole = read_any(str(src), None, ReadOptions())
    text = src.read_bytes().rstrip(b"\n")
    lines = text.split(b"\n")
    last_frame = max(i for i, ln in enumerate(lines) if b" Rx " in ln or b" Tx " in ln)
    cut = b"\n".join(lines[:last_frame]) + b"\n" + lines[last_frame][:20]
    f = tmp_path / "cut.asc"
    f.write_bytes(cut)
    log = read_any(str(f), None, ReadOptions())
    assert log.dropped.get("truncated_bytes") == 20
    assert len(whole) - 1 <= len(log) <= len(whole)


def test_a_can_log_of_a_unit_on_another_node_reads_with_its_node_id(tmp_path: Path) -> None:
    """protocol.md allows nodes 0..15, but a recording of a node-3 unit was unreadable ("no sample
    could be read") and a DBC with its ids moved was refused (a foreign-log audit). `--instance N` is
    the node id for a CAN log; frames of other nodes are foreign, not host frames."""
    import can

    from gyrocal.readers import ReadOptions, read_any

    src = Path(__file__).resolve().parents[1] / "data" / "sim_can" / "virtual_unit_short.asc"
    node0 = read_any(str(src), None, ReadOptions())
    moved = tmp_path / "node3.asc"
    with can.ASCWriter(str(moved)) as out:
        for m in can.LogReader(str(src)):
            if not m.is_error_frame and not m.is_extended_id and 0x100 <= m.arbitration_id < 0x200:
                m.arbitration_id += 3
            out.on_message_received(m)
    node3 = read_any(str(moved), None, ReadOptions(instance=3))
    assert len(node3) == len(node0) and np.array_equal(node3["wx"], node0["wx"])
    assert node3.metadata.get("applied_version") == node0.metadata.get("applied_version")
    with pytest.raises(LogFormatError, match=r"no sample of the unit on node 0; .* node 3 \(\d+ frames\)"):
        read_any(str(moved), None, ReadOptions())  # node 0 hears none of it, and says which node does
    # a bus of another protocol: no node id would help, and the advice was "--instance N" all the same
    other = tmp_path / "other.asc"
    with can.ASCWriter(str(other)) as out:
        for k in range(50):
            out.on_message_received(can.Message(timestamp=k * 0.01, arbitration_id=0x3A0 + k % 4,
                                                data=bytes(8), is_extended_id=False))
    with pytest.raises(LogFormatError, match="none of its 50 frames carries an id of gyrocal's protocol"):
        read_any(str(other), None, ReadOptions())
    with pytest.raises(ConfigError, match="node id, 0..15"):
        read_any(str(moved), None, ReadOptions(instance=16))


def test_a_kelvin_temperature_and_a_column_typo_are_said(tmp_path: Path) -> None:
    """A log in K was read as 298 degC with no word, and `--columns tmp=temp_K` quietly left the log
    without temp (a foreign-log audit): a warning names the units, the typo is an error."""
    from gyrocal.readers import options_from_args

    n = 60
    cols = {"t": np.arange(n) * 0.01, "wx": np.zeros(n), "wy": np.zeros(n), "wz": np.zeros(n),
            "ax": np.zeros(n), "ay": np.zeros(n), "az": np.ones(n), "temp": np.full(n, 298.15)}
    f = tmp_path / "k.csv"
    write_log(f, cols)
    log = read_log(f)
    assert any("looks like kelvin" in w and "temp=K" in w for w in log.warnings)
    cols["temp"] = np.full(n, 25.0)
    write_log(f, cols)
    assert not read_log(f).warnings
    cols["t"] = np.arange(n) * 10.0  # 100 Hz in ms, read as s
    rows = "\n".join(",".join(f"{cols[c][i]:g}" for c in cols) for i in range(n))
    f.write_text(",".join(cols) + "\n" + rows + "\n")  # no '# units:' line
    assert any("looks like a time column in ms" in w for w in read_log(f).warnings)
    # a file that says its time is in s is taken at its word: gyrocal convert's own 2 Hz ArduSub log
    # was warned of as ms (an outside check)
    cols["t"] = np.arange(n) * 0.5
    write_log(f, cols)  # writes '# units: ... time=s'
    assert not any("time column" in w for w in read_log(f).warnings)
    with pytest.raises(ConfigError, match="'tmp' is not one of our columns"):
        options_from_args(Namespace(columns="t=time,tmp=temp_K", units=None))


def test_a_session_that_is_not_a_whole_number_is_refused(tmp_path: Path) -> None:
    """`session` is the switch-on index; 1.5 and -1 were taken as sessions (a foreign-log audit)."""
    from gyrocal.readers import ReadOptions, read_any

    n = 20
    cols = {"t": np.arange(n) * 0.01, "wx": np.zeros(n), "wy": np.zeros(n), "wz": np.zeros(n),
            "ax": np.zeros(n), "ay": np.zeros(n), "az": np.ones(n), "session": np.full(n, 1.5)}
    for bad in (1.5, -1.0):
        cols["session"] = np.full(n, bad)
        f = tmp_path / "s.csv"
        write_log(f, cols)
        with pytest.raises(LogFormatError, match="column 'session'"):
            read_log(f)
        with pytest.raises(LogFormatError, match="column 'session'"):
            read_any(str(f), None, ReadOptions())


def test_a_gyro_in_rad_s_read_as_deg_s_is_warned_of_on_a_tumble(tmp_path: Path) -> None:
    """rad/s read as deg/s made every figure 57x too small with no word when the accel was in g (an
    outside check). Over the moves between rests the gyro integrates to the turn the accel shows."""
    from gyrocal.sim.schedule import tumble
    from gyrocal.sim.truth import SessionStream, TruthModel

    c = SessionStream(TruthModel(), tumble(1.5, 0.6), 100.0, seed=4, boot=0).chunk(6000)
    cols = {k: c[k] for k in ("t", "wx", "wy", "wz", "ax", "ay", "az")}
    f = tmp_path / "tumble.csv"
    write_log(f, cols)
    assert not any("rad/s" in w for w in read_log(f).warnings)
    for a in "xyz":
        cols[f"w{a}"] = np.radians(cols[f"w{a}"])  # rad/s, in a file that says deg/s
    write_log(f, cols)
    said = [w for w in read_log(f).warnings if "looks like rad/s" in w]
    assert len(said) == 1 and "--units gyro=rad/s" in said[0]


def test_a_header_row_behind_a_hash_is_the_header(tmp_path: Path) -> None:
    """EuRoC and TUM-VI write "#timestamp [ns],w_RS_S_x [rad s^-1],...": it was taken for metadata
    and the first data row for the header (a foreign-log audit)."""
    path = tmp_path / "imu0.csv"
    rows = [f"{1403636579758555392 + k * 5_000_000},0.01,-0.02,0.005,9.81,0.02,0.002" for k in range(200)]
    path.write_text("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                    "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n" + "\n".join(rows) + "\n")
    cols = ("t=timestamp [ns],wx=w_RS_S_x [rad s^-1],wy=w_RS_S_y [rad s^-1],wz=w_RS_S_z [rad s^-1],"
            "ax=a_RS_S_x [m s^-2],ay=a_RS_S_y [m s^-2],az=a_RS_S_z [m s^-2]")
    opts = options_from_args(Namespace(columns=cols, units="gyro=rad/s,accel=m/s^2,time=ns"))
    log = read_any(path, None, opts)
    assert len(log) == 200
    np.testing.assert_allclose(np.diff(log["t"]), 0.005, atol=1e-6)
    np.testing.assert_allclose(log["wx"], 0.01 * 180 / math.pi)
    np.testing.assert_allclose(log["ax"], 9.81 / G0)


def test_rows_no_sensor_could_give_are_dropped_before_fit_and_analyze(
        sim_cols: dict[str, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The protocol's "no reading" temperature (-327.68 degC) gave an x constant of +271 deg/h where
    the truth was -180 in an outside user's CAN log; one temperature of 1e308 ended `analyze` in a
    LinAlgError traceback; one rate of 1e300 deg/s ended `fit --method lms --all-samples` in an
    OverflowError, and refused a still fit as having "no still period" (rc36b H1, H5, H6, M4). Such
    rows are dropped and counted, as the daemon drops them (readers/plausible.py)."""
    terms = ["--terms", "1", "gx", "gy", "gz", "temp"]
    clean = tmp_path / "clean.csv"
    write_log(clean, sim_cols)
    ref, _ = _fit([str(clean), *terms], capsys)
    cols = {k: v.copy() for k, v in sim_cols.items()}
    cols["temp"][500:600] = -327.68  # a sensor with no reading for 1 s
    cols["temp"][3000] = 1e308
    cols["wx"][4000] = 1e300
    cols["wy"][4100] = 5000.0  # beyond the +-2147.48 deg/s the wire carries
    bad = tmp_path / "bad.csv"
    write_log(bad, cols)
    res, _ = _fit([str(bad), *terms], capsys)
    assert res["skipped"]["implausible_temperature"] == 101 and res["skipped"]["out_of_range"] == 2
    for ax in ("x", "y", "z"):  # the same fit as the clean log's, within its own uncertainty
        got, want, sig = (np.array(r[ax], dtype=float) for r in (res["coefficients"], ref["coefficients"],
                                                                ref["uncertainty"]))
        assert np.all(np.abs(got - want) < 3 * sig + 1e-9), (ax, got, want, sig)
    assert main(["fit", str(bad), "--all-samples", "--method", "lms"]) == 0
    assert main(["analyze", str(bad), "--json", str(tmp_path / "a.json")]) == 0
    assert "Traceback" not in capsys.readouterr().err


def test_a_log_that_is_not_utf8_is_one_line_naming_the_line_and_the_fix(
        dps_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A Latin-1 degree sign in a comment ended in a UnicodeDecodeError traceback (rc36b H4)."""
    text = dps_log.read_bytes().split(b"\n")
    path = tmp_path / "latin1.csv"
    path.write_bytes(b"\n".join([text[0], "# sensor: Temperatur in \u00b0C".encode("latin-1"), *text[1:]]))
    for cmd in (["fit", str(path)], ["replay", str(path)]):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and "latin1.csv: not UTF-8 text at line 2" in err, err
        assert "save it as UTF-8" in err


def test_a_can_log_with_a_sample_sent_twice_with_other_values_uses_neither_copy(tmp_path: Path) -> None:
    """Forged copies (+0.5 deg/s on x) sent just before the unit's own samples, on its ids: the first
    copy was believed (x constant +273 deg/h where the truth was -180: rc36b H2). Which copy is the
    unit's cannot be told, so a log reader drops both and counts them."""
    import can

    from gyrocal.protocol.can_codec import CanCodec

    codec = CanCodec()
    frames = list(codec.encode(Hello(77, "1.2.3", 5, 100)))
    for s in _samples(200):
        if s.seq % 10 == 5:  # a forged copy first
            forged = Sample(s.seq, s.t_s, (0.51, 0.02, 0.03), s.accel_g, s.temp_c)
            frames += codec.encode(forged)[-3:]
        frames += codec.encode(s)
    path = tmp_path / "forged.asc"
    with can.Logger(str(path)) as out:
        for i, f in enumerate(frames):
            f.timestamp = 1000.0 + i * 1e-4
            out(f)
    log = read_any(path)
    assert log.dropped["conflicting"] == 20 and log.dropped["conflicting_first"] == 20
    assert len(log) == 180 and np.all(log["wx"] == 0.01)


def test_fit_uses_every_session_of_a_log_not_the_first_alone(
        sim_cols: dict[str, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Time restarts at each switch-on, and the estimator's time check dropped every session after the
    first as time_backwards (17,166 of 19,000 rows of an outside user's log with a power cycle: rc36b
    M2). Every session is fitted, with a warning that the constant is their mean."""
    two = {k: np.concatenate([v, v]) for k, v in sim_cols.items()}
    two["session"] = np.repeat([0.0, 1.0], len(sim_cols["t"]))
    path = tmp_path / "two.csv"
    write_log(path, two)
    single = tmp_path / "one.csv"
    write_log(single, sim_cols)
    one, _ = _fit([str(single)], capsys)
    res, err = _fit([str(path)], capsys)
    assert res["skipped"].get("time_backwards", 0) == 0 and res["samples"] == 2 * one["samples"]
    assert "2 sessions (switch-ons): every one is fitted" in err


def test_lms_epochs_leave_out_the_pairs_the_guard_refuses() -> None:
    """rc36b H6, in the estimator: a pair beyond the guard's max_rate_dps (counted out_of_range by
    absorb) never reaches the seed's epochs: the weights are those of the pairs without it. One wx of
    1e300 deg/s ended `fit --method lms --all-samples` in an OverflowError traceback."""
    from gyrocal.model.methods import LMS

    rng = np.random.default_rng(3)
    phi = np.column_stack([np.ones(40), rng.uniform(-1, 1, 40)])
    y = np.column_stack([0.01 + 0.002 * phi[:, 1], np.zeros(40), np.zeros(40)])
    bad_phi, bad_y = np.vstack([phi, [1.0, 0.5]]), np.vstack([y, [2100.0, 0.0, 0.0]])
    a, b = LMS(["1", "gx"], seed=1), LMS(["1", "gx"], seed=1)
    assert a.absorb(bad_phi, bad_y) == 40 and a.counts["out_of_range"] == 1
    a.train_seed(bad_phi, bad_y)
    b.train_seed(phi, y)
    np.testing.assert_array_equal(a.W, b.W)
