"""Terms held at 0 when the data cannot separate them: the determined part of a model, as a set.

Why: during one first-order warm-up the temperature rate is close to a straight line in the
temperature (dtemp ~ (T_end - T) / tau), and ``temp*dtemp`` close to a mix of ``temp`` and ``temp^2``.
Seed 000's ten gravity terms plus ``temp, temp^2, dtemp, temp*dtemp`` (the built-in set 0x549E) then
stop at rank 12 of 13 on a whole factory tumble, and a unit with no stored set was never calibrated:
280 switch-ons of a fleet engineer's year, 18 with no set, then a constant alone. Seed 000 (eq. 3)
sets the weights the data did not excite to zero; the minimum-norm solution does that in the
normaliser's coordinates, where it mixes the constant and the gravity terms into the temperature
ones. Holding whole terms at 0 instead keeps every term that is learnt a least-squares fit of its
own, with its own covariance: the set is exact wherever the data was (the warm-up seen), and a later
switch-on's warm-up, whose rate law differs, separates the terms held (the information carried
across switch-ons, daemon/learner.py).

Only terms with an atom beyond gravity (temperature, its rate, time since switch-on, a sinusoid) are
held (``find_held`` says which first): gravity terms undetermined (a unit seen at few poses) are not made
up by dropping terms; that case is the constant alone's (daemon/session.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from gyrocal.model.identifiability import rank_aware_solve, split_subspaces
from gyrocal.model.terms import parse_term

GRAVITY_ATOMS = frozenset({"gx", "gy", "gz", "ax", "ay", "az"})


@dataclass(frozen=True)
class HeldZero:
    """Which terms are held at 0 (P,) bool, and an orthonormal basis (P, P-k) of the normalised weights
    that keep their physical coefficients 0 (c = M^T w, so M[:, held]^T w = 0)."""

    mask: np.ndarray
    basis: np.ndarray

    def names(self, names: Sequence[str]) -> list[str]:
        return [n for n, h in zip(names, self.mask, strict=True) if h]

    def solve(self, R: np.ndarray, b: np.ndarray, tol: float) -> tuple[np.ndarray, ...]:
        """The least-squares weights (P, 3) with the held terms 0, and the eigen-split of the
        information they were solved with, in the full weight space: (W, l_r, V_r, V_null)."""
        n = self.basis
        u, lam_r, v_r, v_n = rank_aware_solve(n.T @ R @ n, n.T @ b, np.zeros((n.shape[1], 3)), tol)
        return n @ u, lam_r, n @ v_r, n @ v_n


def holdable(name: str) -> bool:
    """A term that may be held at 0: one with an atom beyond gravity (temp, dtemp, t_on, sin(F) ...)."""
    term = parse_term(name)
    return bool(term.atoms) and not term.atoms <= GRAVITY_ATOMS


def _level(name: str) -> int:
    """The degree in temperature of a term made of ``temp`` alone (temp: 1, temp^2: 2), else 0: a
    term of the switch-on's course (dtemp, t_on, a transient, a sinusoid, or a product with one)."""
    term = parse_term(name)
    return sum(f.power for f in term.factors) if term.atoms == {"temp"} else 0


def _keeping_zero(m: np.ndarray, held: Sequence[int]) -> np.ndarray:
    """Orthonormal basis of {w : M[:, held]^T w = 0}."""
    c = m[:, list(held)]
    _, s, vt = np.linalg.svd(c.T)
    k = int(np.sum(s > 1e-12 * max(float(s.max()), 1e-300)))
    return vt[k:].T


MAX_CANDIDATES = 8
"""Terms weighed for holding (the last listed): 2^8 choices at most, each one small eigen-split."""


def find_held(R: np.ndarray, m: np.ndarray, names: Sequence[str], undetermined: Sequence[str],
              structural_rank: Callable[[tuple[str, ...]], int], tol: float) -> HeldZero | None:
    """The terms to hold at 0 so that the rest are determined, or None.

    R (P, P): information in normalised terms (z = M phi); ``undetermined``: the terms that appear
    in a null direction. A choice fits when the information, restricted to weights that keep the
    held terms 0, has the largest rank the kept terms can reach (``structural_rank``: the
    unit-gravity identity stays a null direction, which changes no prediction) and that is more than
    the constant (a constant alone waits for a steady temperature: daemon/session.py). Of the choices that
    fit, the first in this order: the fewest temperature-level terms held (``temp``, ``temp^2``: a
    set's level terms are what carries to another temperature), the highest of their degrees held
    first; then the most course terms held (``dtemp``, ``temp*dtemp``: over one warm-up the rate is
    a function of the level, dtemp ~ (T_end - T) / tau, so what one warm-up says of them is the
    unit's thermal lag as much as its drift); then the last listed. One warm-up of a unit whose drift
    is a quadratic in temperature gives temp and temp^2 with both rate terms held; a warm-up of 3
    degC gives temp alone.
    """
    cands = [i for i, n in enumerate(names) if n in undetermined and holdable(n)][-MAX_CANDIDATES:]
    level = {i: _level(names[i]) for i in cands}

    def order(held: tuple[int, ...]) -> tuple:
        lv = sorted((level[i] for i in held if level[i]), reverse=True)
        return (len(lv), [-d for d in lv], -sum(1 for i in held if not level[i]), [-i for i in held])

    choices = [c for k in range(1, len(cands) + 1) for c in combinations(cands, k)]
    for held in sorted(choices, key=order):
        basis = _keeping_zero(m, held)
        lam_r, _, _ = split_subspaces(basis.T @ R @ basis, tol)
        kept = tuple(n for i, n in enumerate(names) if i not in held)
        if lam_r.size > 1 and lam_r.size == structural_rank(kept):
            mask = np.zeros(len(names), dtype=bool)
            mask[list(held)] = True
            return HeldZero(mask, basis)
    return None
