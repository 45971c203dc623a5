"""gyrocal.model: functional-link terms and the on-line estimators (docs/estimators.md).

The daemon's entry points::

    from gyrocal.model import make_estimator, Estimator, ConvergenceConfig, block_terms
    est = make_estimator("rls", terms, forgetting=1.0, convergence=ConvergenceConfig.from_dict(d, src))
    e = est.update_many(block_terms(est.spec, cols), gyro_dps, t_s)   # or est.update(phi, y, t)
    est.coefficients, est.uncertainty, est.identifiability, est.convergence(), est.state()
"""

from gyrocal.model.convergence import ConvergenceConfig, ConvergenceStatus
from gyrocal.model.estimator import Estimator, InputGuard
from gyrocal.model.identifiability import Identifiability, determined_part
from gyrocal.model.methods import LMS, NLMS, RLS, BatchLS, SeedSchedule, make_estimator
from gyrocal.model.normalise import Normaliser
from gyrocal.model.prep import block_terms, prepare

__all__ = [
    "BatchLS", "ConvergenceConfig", "ConvergenceStatus", "Estimator", "Identifiability", "InputGuard",
    "LMS", "NLMS", "Normaliser", "RLS", "SeedSchedule", "block_terms", "determined_part", "make_estimator",
    "prepare",
]
