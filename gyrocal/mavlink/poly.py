"""Exact conversion between polynomials in temperature about different reference points.

Our term set is ``1, temp, temp^2, temp^3`` with temp in degC from 0: per axis
``c0 + c1*T + c2*T^2 + c3*T^3``. The autopilots evaluate ``a0 + a1*d + a2*d^2 + a3*d^3`` with
``d = T - Tref`` (PX4: Tref = TC_Gn_TREF; ArduPilot: a fixed 35 degC). The binomial expansion maps one
to the other exactly (in float64); the reverse shift is the same map with -Tref.
"""

from __future__ import annotations

from math import comb

import numpy as np

DEG_PER_RAD = 180.0 / np.pi


def shift(coeffs: np.ndarray, tref: float) -> np.ndarray:
    """Coefficients of p(Tref + d) in powers of d, from those of p(T) in powers of T.

    ``coeffs``: (..., K) lowest power first. a_k = sum_{j>=k} c_j * C(j, k) * Tref^(j-k).
    """
    c = np.asarray(coeffs, dtype=np.float64)
    k_max = c.shape[-1]
    m = np.zeros((k_max, k_max))
    for j in range(k_max):
        for k in range(j + 1):
            m[j, k] = comb(j, k) * tref ** (j - k)
    return c @ m


def evaluate(coeffs: np.ndarray, x: np.ndarray) -> np.ndarray:
    """p(x) per axis: ``coeffs`` (3, K) lowest power first, x (N,) -> (N, 3)."""
    x = np.asarray(x, dtype=np.float64)
    powers = x[:, None] ** np.arange(np.asarray(coeffs).shape[-1])[None, :]
    return powers @ np.asarray(coeffs, dtype=np.float64).T
