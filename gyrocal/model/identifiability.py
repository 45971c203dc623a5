"""What the data determined: rank, null space in readable words, and the rank-aware solve.

The information matrix R = sum_i lambda^(n-i) z_i z_i^T (normalised terms, shape (P, P)) is shared
by the three gyro axes. Its eigen-decomposition R = V diag(l) V^T splits the weight space into
the identifiable subspace (l_i > tol * l_max) and the null space (everything else).

Policy (docs/estimators.md): the estimate is the least-squares solution in the identifiable
subspace; in the null space it keeps the prior (zero for a fresh unit, the previous calibration
for a warm start):

    W = W0 + V_r diag(1/l_r) V_r^T (b - R W0)                 (seed eq. 4, rank-aware)

With W0 = 0 this is the minimum-norm solution in normalised units (seed eq. 3 sets the
unexcited weights to zero in the same spirit). A coefficient whose physical direction touches
the null space is never reported as learned: its uncertainty is +inf.

A null direction is reported over the term names in physical units, e.g. the unit-gravity
identity gx^2 + gy^2 + gz^2 = 1 gives the relation ``1 - gx^2 - gy^2 - gz^2`` (= 0 on all data):
adding any amount of (d0, d4, d5, d6) = (1, -1, -1, -1) to the coefficients changes no prediction.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

DEFAULT_RANK_TOL = 1e-6
"""Eigenvalues below this fraction of the largest count as not excited."""


@dataclass
class Identifiability:
    """Rank and null space of the information matrix, in words a person can read."""

    rank: int
    n_terms: int
    eigenvalues: np.ndarray
    null_physical: np.ndarray = field(repr=False)  # (P - rank, P) rref basis over physical terms
    undetermined: list[str]                          # one relation per null direction
    determined_terms: list[str]                      # terms whose own coefficient is determined
    undetermined_terms: list[str]                    # terms that appear in a null direction

    def as_contract(self) -> dict:
        """The Contract 3 ``identifiable`` object, extended with the per-term split."""
        return {"rank": self.rank, "undetermined": list(self.undetermined),
                "determined_terms": list(self.determined_terms),
                "undetermined_terms": list(self.undetermined_terms)}

    def summary(self) -> str:
        if not self.undetermined:
            return f"rank {self.rank} of {self.n_terms}: every coefficient is determined"
        rel = "; ".join(f"{u} = 0" for u in self.undetermined)
        return (f"rank {self.rank} of {self.n_terms}: the data cannot separate "
                f"{', '.join(self.undetermined_terms)} (relation{'s' if len(self.undetermined) > 1 else ''} "
                f"on the data: {rel}); determined on their own: {', '.join(self.determined_terms) or 'none'}")


def split_subspaces(
    R: np.ndarray, tol: float = DEFAULT_RANK_TOL
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-split of a symmetric (P, P) R: (l_r (r,), V_r (P, r), V_null (P, P-r))."""
    lam, v = np.linalg.eigh(0.5 * (R + R.T))
    top = float(lam[-1]) if lam.size else 0.0
    keep = lam > tol * top if top > 0 else np.zeros(lam.shape, dtype=bool)
    return lam[keep], v[:, keep], v[:, ~keep]


def rank_aware_solve(
    R: np.ndarray, b: np.ndarray, w0: np.ndarray, tol: float = DEFAULT_RANK_TOL
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """W = W0 + V_r diag(1/l_r) V_r^T (b - R W0); returns (W (P,3), l_r, V_r, V_null)."""
    lam_r, v_r, v_n = split_subspaces(R, tol)
    w = w0 + v_r @ ((v_r.T @ (b - R @ w0)) / lam_r[:, None])
    return w, lam_r, v_r, v_n


def analyse(
    R: np.ndarray, names: Sequence[str], M: np.ndarray, tol: float = DEFAULT_RANK_TOL
) -> Identifiability:
    """Identifiability of the physical coefficients from R (normalised coordinates, z = M phi)."""
    lam_r, _, v_n = split_subspaces(R, tol)
    p = len(names)
    null = rref(M.T @ v_n) if v_n.shape[1] else np.zeros((0, p))
    touched = np.any(np.abs(null) > 1e-6, axis=0) if null.size else np.zeros(p, dtype=bool)
    lam = np.linalg.eigvalsh(0.5 * (R + R.T))
    return Identifiability(
        rank=int(lam_r.size), n_terms=p, eigenvalues=lam[::-1], null_physical=null,
        undetermined=[describe(row, names) for row in null],
        determined_terms=[n for n, t in zip(names, touched, strict=True) if not t],
        undetermined_terms=[n for n, t in zip(names, touched, strict=True) if t],
    )


def rref(basis: np.ndarray, tol: float = 1e-9, clean: float = 1e-3) -> np.ndarray:
    """Reduced row-echelon form of a null basis given as columns (P, d): rows (d, P), sparse to read.

    Pivots are taken from the last term backwards, so each relation is solved for the
    highest-order term (gx*gz, ..., gz^2) and reads like the identity it is. Entries below
    ``clean`` times the row's largest are noise in the eigenvectors and are set to zero.
    """
    a = np.array(basis.T, dtype=np.float64)[:, ::-1]
    a /= np.abs(a).max()
    rows, cols = a.shape
    r = 0
    for c in range(cols):
        if r == rows:
            break
        piv = r + int(np.argmax(np.abs(a[r:, c])))
        if abs(a[piv, c]) < tol:
            continue
        a[[r, piv]] = a[[piv, r]]
        a[r] /= a[r, c]
        for i in range(rows):
            if i != r:
                a[i] -= a[i, c] * a[r]
        r += 1
    a = a[:, ::-1]
    big = np.abs(a).max(axis=1, keepdims=True)
    a[np.abs(a) < clean * np.where(big > 0, big, 1.0)] = 0.0
    return a


def describe(weights: np.ndarray, names: Sequence[str]) -> str:
    """Write a direction over term names with small-integer weights: ``1 - gx^2 - gy^2 - gz^2``."""
    w = np.asarray(weights, dtype=np.float64)
    nz = np.flatnonzero(np.abs(w) > 1e-6 * np.abs(w).max())
    w = w / w[nz[0]]
    for k in range(1, 13):  # the smallest multiplier that makes the weights near-integers
        if np.all(np.abs(k * w[nz] - np.round(k * w[nz])) < 2e-3 * k):
            w = np.round(k * w)
            break
    parts = []
    for i in nz:
        mag, name = abs(w[i]), names[i]
        num = "" if abs(mag - 1) < 1e-9 else (f"{mag:g}" if mag == round(mag) else f"{mag:.3g}")
        term = (num or "1") if name == "1" else (f"{num}*{name}" if num else name)
        sign = "-" if w[i] < 0 else "+"
        parts.append(("-" if sign == "-" else "") + term if not parts else f" {sign} {term}")
    return "".join(parts)


def determined_part(coeffs: np.ndarray, ident: Identifiability) -> np.ndarray:
    """Coefficients (3, P) with their components along the null directions removed.

    Two coefficient sets that differ only in what the data cannot see have the same determined
    part, so comparing determined parts compares what the data could decide.
    """
    n = ident.null_physical
    if n.size == 0:
        return np.array(coeffs, dtype=np.float64)
    q, _ = np.linalg.qr(n.T)  # orthonormal basis of the null directions (P, d)
    c = np.asarray(coeffs, dtype=np.float64)
    return c - (c @ q) @ q.T
