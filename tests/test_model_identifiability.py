"""Identifiability: rank and named null space on real imu_tk data, on few poses, and the wording."""

from __future__ import annotations

import numpy as np
import pytest

from gyrocal.datasets.imu_tk import default_dir, load_imu_tk
from gyrocal.model.identifiability import describe
from gyrocal.model.methods import make_estimator
from gyrocal.model.normalise import Normaliser
from gyrocal.model.prep import prepare
from gyrocal.model.terms import SEED000_TERMS, TermSpec
from gyrocal.sim.schedule import Schedule
from gyrocal.sim.truth import SessionStream, TruthModel

SPEC = TermSpec.parse(SEED000_TERMS)


def test_describe_writes_small_integer_weights_over_term_names() -> None:
    names = list(SEED000_TERMS)
    assert describe(np.array([0.5, 0, 0, 0, -0.5, -0.5, -0.5, 0, 0, 0]), names) == "1 - gx^2 - gy^2 - gz^2"
    assert describe(np.array([0, 2, 0, -1, 0, 0, 0, 0, 0, 0]) / 3, names) == "2*gx - gz"


@pytest.mark.skipif(not default_dir().is_dir(), reason="imu_tk data not present")
def test_rank_is_9_on_real_imu_tk_data_and_the_undetermined_combination_is_named() -> None:
    log = load_imu_tk()
    assert len(log) == 51175
    data = prepare(log, SPEC)
    assert 20000 < len(data.phi) < 51175  # still periods only
    rls = make_estimator("rls", SPEC, normaliser=Normaliser.from_data(SPEC, data.phi, data.y))
    rls.update_many(data.phi, data.y, data.t)
    ident = rls.identifiability
    assert ident.rank == 9
    assert ident.undetermined == ["1 - gx^2 - gy^2 - gz^2"]
    assert ident.undetermined_terms == ["1", "gx^2", "gy^2", "gz^2"]
    sig = rls.uncertainty
    assert np.isinf(sig[:, [0, 4, 5, 6]]).all() and np.isfinite(sig[:, [1, 2, 3, 7, 8, 9]]).all()
    # the noise floor PROVENANCE.md reports (~0.32 deg/s per sample)
    assert np.all((rls.residual_rms_dps > 0.25) & (rls.residual_rms_dps < 0.4))


def test_a_unit_that_visited_three_faces_has_rank_3_and_the_missing_terms_are_named() -> None:
    poses = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]])
    stream = SessionStream(TruthModel(), Schedule(poses, 5.0, 1.0), 100.0, seed=1, boot=0)
    cols = stream.chunk(3000)
    from gyrocal.logformat import LogData
    log = LogData({k: cols[k] for k in ("t", "wx", "wy", "wz", "ax", "ay", "az", "session")})
    data = prepare(log, SPEC)
    est = make_estimator("rls", SPEC, normaliser=Normaliser.from_data(SPEC, data.phi, data.y))
    est.update_many(data.phi, data.y, data.t)
    ident = est.identifiability
    # three poses: the data can fit three levels + nothing else  -> rank 3
    assert ident.rank == 3
    assert len(ident.undetermined) == 7 and ident.determined_terms == []
    assert {"gx*gy", "gy*gz", "gx*gz", "1 - gx - gy - gz"} <= set(ident.undetermined)
    assert np.isinf(est.uncertainty).all()
    assert not est.convergence().converged
