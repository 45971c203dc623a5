"""The README's main job: `gyrocal demo --json` prints Contract 4 and cuts the drift tenfold."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


@pytest.mark.slow
def test_demo_json_is_contract_4_and_the_push_cuts_drift_tenfold() -> None:
    out = subprocess.run([sys.executable, "-m", "gyrocal.cli", "demo", "--json"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert set(res) >= {"pushed", "acked", "version", "link", "drift_rms_before", "drift_rms_after"}
    assert res["pushed"] and res["acked"] and res["version"] == 1 and res["link"] == "serial"
    for a in "xyz":
        assert res["drift_rms_after"][a] * 10 <= res["drift_rms_before"][a]
        # the README promises the prediction too (it was printed for the other grades only)
        assert 0 < res["predicted_drift_after"][a] < res["drift_rms_before"][a]
