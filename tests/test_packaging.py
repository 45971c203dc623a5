"""The wheel: it carries the example config, the unit file, the udev rule and the LICENSE; an install
from it writes them out with `gyrocal install-files`, and `convert` without SRC says where the data
is instead of guessing a path outside the install."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel_install(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Build the wheel (no deps) and unpack-install it into a target directory of its own."""
    tmp = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(REPO), "--no-deps", "-q", "-w", str(tmp)],
                   check=True, capture_output=True, timeout=300)
    (whl,) = tmp.glob("gyrocal-*.whl")
    site = tmp / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site),
                    str(whl)], check=True, capture_output=True, timeout=300)
    return whl, site


def _run_installed(site: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """`gyrocal ARGS` from the unpacked wheel (dependencies from this interpreter's environment)."""
    env = {**os.environ, "PYTHONPATH": str(site)}
    env.pop("GYROCAL_DATA", None)
    code = "import sys, gyrocal; from gyrocal.cli import main; print(gyrocal.__file__, file=sys.stderr); " \
           "sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=120)


@pytest.mark.slow
def test_the_wheel_carries_the_shipped_files_and_the_license(wheel_install) -> None:
    whl, _ = wheel_install
    names = zipfile.ZipFile(whl).namelist()
    shipped = ("gyrocal.example.yaml", "gyrocal.service", "99-gyrocal-imu.rules", "gyrocal.dbc",
               "default.yaml")
    for f in shipped:
        assert f"gyrocal/configs/{f}" in names
    assert any(n.endswith("/LICENSE") for n in names)
    with zipfile.ZipFile(whl) as z:  # real contents, not symlinks
        unit = z.read("gyrocal/configs/gyrocal.service")
    assert unit == (REPO / "configs" / "gyrocal.service").read_bytes()


@pytest.mark.slow
def test_install_files_from_the_wheel_writes_them_out(wheel_install, tmp_path: Path) -> None:
    _, site = wheel_install
    out = _run_installed(site, tmp_path, "install-files", str(tmp_path / "etc"))
    assert out.returncode == 0, out.stderr
    assert out.stderr.splitlines()[0].startswith(str(site))  # the wheel's gyrocal, not the checkout's
    for f in ("gyrocal.example.yaml", "gyrocal.service", "99-gyrocal-imu.rules", "gyrocal.dbc"):
        assert (tmp_path / "etc" / f).read_bytes() == (REPO / "configs" / f).read_bytes()
    again = _run_installed(site, tmp_path, "install-files", str(tmp_path / "etc"))
    assert again.returncode == 2 and "--force" in again.stderr


@pytest.mark.slow
def test_convert_without_src_from_the_wheel_says_where_the_data_is(wheel_install, tmp_path: Path) -> None:
    _, site = wheel_install
    out = _run_installed(site, tmp_path, "convert", "imucal", str(tmp_path / "o.csv"))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "not in the wheel" in out.stderr and "GYROCAL_DATA" in out.stderr and "shared" not in out.stderr


def test_install_files_exec_points_the_unit_at_this_install(tmp_path: Path) -> None:
    from gyrocal.cli import main

    assert main(["install-files", str(tmp_path), "--exec", "/opt/gyrocal/bin/gyrocal"]) == 0
    unit = (tmp_path / "gyrocal.service").read_text()
    assert "ExecStart=/opt/gyrocal/bin/gyrocal run --config /etc/gyrocal/gyrocal.yaml" in unit


def test_the_completion_script_is_valid_bash_and_completes_commands_and_options(tmp_path: Path) -> None:
    bash = "/bin/bash"
    if not Path(bash).exists():
        pytest.skip("no bash")
    from gyrocal.completion import script

    (tmp_path / "c.sh").write_text(script())
    probe = f"""source {tmp_path / 'c.sh'}
COMP_WORDS=(gyrocal sta); COMP_CWORD=1; _gyrocal; echo "${{COMPREPLY[*]}}"
COMP_WORDS=(gyrocal status --wa); COMP_CWORD=2; _gyrocal; echo "${{COMPREPLY[*]}}"
COMP_WORDS=(gyrocal sim --link ""); COMP_CWORD=3; _gyrocal; echo "${{COMPREPLY[*]}}"
"""
    out = subprocess.run([bash, "-c", probe], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["status", "--watch", "pty can mavlink"]
