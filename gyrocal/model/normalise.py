"""Input and output normalisation, kept in the model so coefficients stay in physical units.

Seed 000 section 5 normalises the data before learning ("学习前, 对数据进行归一化处理") but does not
say how. We choose an affine map per term, then one global factor, so that the seed's learning
factor (0.95 -> 0.4) is a stable LMS step:

    z_j = kappa * (phi_j - m_j) / s_j      for every non-constant term j
    z_0 = kappa                              for the constant term ``1``
    y_n = y / s_y

m_j is the term's mean, s_j its largest deviation (never below its deviation over the term's
nominal range, so noise-only terms are not stretched into false excitation), and
kappa = 1 / max ||z|| over the reference data, so that ||z|| <= 1 and LMS with alpha < 2 cannot
diverge on that data. Centring the terms matters: gx^2 has mean ~1/3 and would otherwise be nearly
collinear with ``1``.

The map is linear in phi (the constant term absorbs the offsets): z = M phi with
M = kappa * (diag(1/s) - (m/s) e0^T). A model y = W^T z in normalised units is therefore the
physical model y = c^T phi with c = s_y * M^T W  [deg/s per term unit], and a covariance Cov(W)
maps to Cov(c) = s_y^2 M^T Cov(W) M.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gyrocal.errors import ConfigError
from gyrocal.model.terms import TermSpec

NOMINAL_ATOM_RANGES: dict[str, tuple[float, float]] = {
    "temp": (-40.0, 85.0),   # degC, an industrial sensor's range
    "dtemp": (-0.05, 0.05),  # degC/s (3 degC/min)
    "t_on": (0.0, 3600.0),   # s since switch-on
    "t": (0.0, 3600.0),      # s
}
"""Ranges used by ``Normaliser.nominal`` for atoms other than gravity (which is a unit vector)."""


@dataclass
class Normaliser:
    """z = a * phi - c (elementwise, fast per sample) and y_n = y / y_scale.

    ``a`` (P,) and ``c`` (P,) encode M; ``c`` is nonzero only when the spec has a constant term
    at index ``const_index``. ``y_scale`` [deg/s] is one number shared by the three axes.
    """

    a: np.ndarray
    c: np.ndarray
    y_scale: float = 1.0
    const_index: int | None = None

    @property
    def M(self) -> np.ndarray:
        """The (P, P) matrix with z = M phi."""
        m = np.diag(self.a)
        if self.const_index is not None:
            m[:, self.const_index] -= self.c
        return m

    @classmethod
    def identity(cls, spec: TermSpec, y_scale: float = 1.0) -> Normaliser:
        p = len(spec)
        return cls(np.ones(p), np.zeros(p), float(y_scale), _const_index(spec))

    @classmethod
    def from_data(cls, spec: TermSpec, phi: np.ndarray, y: np.ndarray | None = None,
                  floor: np.ndarray | None = None) -> Normaliser:
        """The seed's normalisation fitted to reference data: phi (N, P) in term units, y (N, 3) deg/s.

        A term's scale is its largest deviation in the data but never below ``floor`` (P,), by
        default the term's deviation over its nominal range (``nominal_deviation``): a term that
        the data barely moves (gx*gy on a unit that only sat on its faces, where it is accelerometer
        noise) is not stretched to look excited, so the rank test sees it as not excited.
        """
        phi = np.asarray(phi, dtype=np.float64)
        if phi.ndim != 2 or phi.shape[1] != len(spec) or phi.shape[0] == 0:
            raise ConfigError(
                f"normalisation needs a non-empty (N, {len(spec)}) term matrix, got {phi.shape}")
        k0 = _const_index(spec)
        mean = phi.mean(axis=0) if k0 is not None else np.zeros(phi.shape[1])
        dev = np.abs(phi - mean).max(axis=0)
        s = np.maximum(dev, nominal_deviation(spec) if floor is None else floor)
        s = np.where(s > 0, s, 1.0)
        if k0 is not None:
            mean[k0], s[k0] = 0.0, 1.0
        a, c = 1.0 / s, mean / s
        z = phi * a - c
        kappa = 1.0 / max(float(np.sqrt((z * z).sum(axis=1)).max()), 1e-300)
        ys = 1.0
        if y is not None and np.size(y):
            ys = float(np.abs(y).max()) or 1.0
        return cls(a * kappa, c * kappa, ys, k0)

    @classmethod
    def nominal(cls, spec: TermSpec, y_scale: float = 1.0) -> Normaliser:
        """A normaliser for streaming before any data is seen, from the terms' nominal ranges."""
        phi = _nominal_terms(spec)
        out = cls.from_data(spec, phi, floor=np.zeros(len(spec)))
        out.y_scale = float(y_scale)
        return out

    def z(self, phi: np.ndarray) -> np.ndarray:
        """Normalised terms, same shape as phi ((P,) or (N, P))."""
        return phi * self.a - self.c

    def to_physical(self, w: np.ndarray) -> np.ndarray:
        """Normalised weights W (P, 3) -> physical coefficients (3, P) [deg/s per term unit]."""
        return (self.y_scale * (self.M.T @ w)).T

    def from_physical(self, coeffs: np.ndarray) -> np.ndarray:
        """Physical coefficients (3, P) -> normalised weights W (P, 3)."""
        return np.linalg.solve(self.M.T, np.asarray(coeffs, dtype=np.float64).T) / self.y_scale

    def state(self) -> dict[str, Any]:
        return {"a": self.a.tolist(), "c": self.c.tolist(), "y_scale": self.y_scale,
                "const_index": self.const_index}

    @classmethod
    def from_state(cls, d: dict[str, Any]) -> Normaliser:
        return cls(np.asarray(d["a"], dtype=np.float64), np.asarray(d["c"], dtype=np.float64),
                   float(d["y_scale"]), d["const_index"])


def _const_index(spec: TermSpec) -> int | None:
    names: Sequence[str] = spec.names
    return names.index("1") if "1" in names else None


def _nominal_terms(spec: TermSpec, n: int = 4096) -> np.ndarray:
    """Terms (n, P) over nominal atoms: gravity a random unit vector, others uniform over their range.

    Ranges are ``NOMINAL_ATOM_RANGES`` ((-1, 1) for any other column). Deterministic (seed 0).
    """
    rng = np.random.default_rng(0)
    g = rng.normal(size=(n, 3))
    g /= np.linalg.norm(g, axis=1)[:, None]
    cols: dict[str, np.ndarray] = {"gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2]}
    for atom in sorted(spec.atoms):
        if atom not in cols and atom.isidentifier():  # exp()/sin() atoms derive from t_on, t
            lo, hi = NOMINAL_ATOM_RANGES.get(atom, (-1.0, 1.0))
            cols[atom] = rng.uniform(lo, hi, n)
    cols.setdefault("t_on", rng.uniform(*NOMINAL_ATOM_RANGES["t_on"], n))
    cols.setdefault("t", rng.uniform(*NOMINAL_ATOM_RANGES["t"], n))
    return spec.design(cols)


def nominal_deviation(spec: TermSpec) -> np.ndarray:
    """Each term's largest deviation from its mean over the nominal ranges (P,), term units."""
    phi = _nominal_terms(spec)
    return np.abs(phi - phi.mean(axis=0)).max(axis=0)
