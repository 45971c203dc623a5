"""The Earth's rotation in a tumbling unit's body frame: north found from the data, then removed.

Why: a gyro at rest reads the Earth's rotation (15.041 deg/h) as true rate (gyrocal/model/earth.py).
The daemon learns the rate at rest as drift, so without this it learnt the Earth's rotation into the
unit's set. On a unit that turns with the Earth, the demo unit and the fibre unit were never pushed
(the part along north changes with every pose's heading, which no gravity term can follow, and the
push gate saw 1.7-2 deg/h it could not remove), and the tactical unit was left with 6-10 deg/h
instead of 3 (`benchmarks/bench_earth.py`).

With ``site.latitude_deg`` the vertical part is known at every sample from the accelerometers. The
part along north needs the heading, which a unit that knows only gravity cannot see. But a tumble
turns the unit through known angles: the daemon integrates the gyro output during each move (never
during a rest, so the drift at rest turns nothing) and carries the frame of the first rest, the
reference, to every sample: body <- reference is ``C.T``. The horizontal Earth rate is then one
constant vector h in the reference frame, horizontal, of length Omega cos(latitude), seen in the body
as ``C.T @ h``. It is found jointly with the drift coefficients D by least squares over the still
samples, y_i = D_i phi + (C.T h)_i for each axis i, from running sums (D is profiled out): the
gyrocompass of a tumble. Once its direction is known to 3 deg, it is fixed, the session restarts its
learning, and the Earth's whole rotation is taken out of every sample before anything learns from it.

A jump in seq or a turn seen at rest that the integration cannot follow (the unit moved while samples
were lost) loses the reference: north is found again from the samples after it.
"""

from __future__ import annotations

import numpy as np

from gyrocal.model.earth import OMEGA_IE_DPS, vertical_earth_rate_dps
from gyrocal.protocol.messages import SEQ_MODULO

HEADING_SIGMA_DEG = 3.0
"""North is fixed once the fit's 1-sigma heading error is below this [deg]: 15 deg/h x cos(latitude)
x sin(3 deg) = 0.55 deg/h at 45 deg, of which the next fit removes most (it is refit from the data
after the restart, never trusted blindly)."""
UP_TOLERANCE_DEG = 3.0
"""A rest whose measured up differs from the carried one by more than this [deg] has lost the
reference (the unit turned while samples were lost)."""


class EarthTrack:
    """One switch-on's reference frame, the horizontal Earth rate in it, and the sums that find it."""

    def __init__(self, latitude_deg: float, n_terms: int) -> None:
        self.latitude_deg = float(latitude_deg)
        self.horizontal_dps = OMEGA_IE_DPS * abs(np.cos(np.radians(latitude_deg)))
        self.n_terms = n_terms
        self.C: np.ndarray | None = None  # body -> reference, at the last sample
        self.up_ref: np.ndarray | None = None  # up in the reference frame (unit vector)
        self.h: np.ndarray | None = None  # horizontal Earth rate in the reference frame [deg/s]
        self.heading_sigma_deg = float("inf")
        self.fit_magnitude = float("nan")  # |h| the fit gave, over Omega cos(latitude)
        self.references = 0  # reference frames started (1 + times it was lost)
        self._last: tuple[int, float, bool] | None = None  # seq, t [s], still of the last sample
        self._reset_sums()

    def _reset_sums(self) -> None:
        p = self.n_terms
        self._m = np.zeros((p, p))
        self._phi_y = np.zeros((p, 3))
        self._phi_h = np.zeros((3, p, 3))
        self._h_y = np.zeros(3)
        self._n = 0
        self._ss = 0.0

    @property
    def known(self) -> bool:
        return self.h is not None

    def _lose(self) -> None:
        self.C = None
        self.h = None
        self.heading_sigma_deg = float("inf")
        self._reset_sums()

    def advance(self, seq: np.ndarray, t: np.ndarray, w_dps: np.ndarray, a_g: np.ndarray,
                still: np.ndarray) -> np.ndarray:
        """Carry the reference through these samples (time order); returns C (N, 3, 3) per sample,
        NaN where there is no reference (before the first rest, or after it was lost)."""
        n = seq.size
        out = np.full((n, 3, 3), np.nan)
        up_b = a_g / np.linalg.norm(a_g, axis=1, keepdims=True)
        cos_tol = np.cos(np.radians(UP_TOLERANCE_DEG))
        for i in range(n):  # per sample: the integration is a recursion
            s, ti, st = int(seq[i]), float(t[i]), bool(still[i])
            if self._last is not None and self.C is not None:
                ls, lt, lst = self._last
                if (s - ls) % SEQ_MODULO != 1 and not (lst and st):
                    self._lose()  # samples lost while the unit may have turned
                elif not st or not lst:
                    self._turn(w_dps[i], ti - lt)
            if self.C is None and st and np.all(np.isfinite(up_b[i])):
                self.C = np.eye(3)
                self.up_ref = up_b[i].copy()
                self.references += 1
            if self.C is not None and st and float(self.up_ref @ (self.C @ up_b[i])) < cos_tol:
                self._lose()  # the carried frame disagrees with gravity: it no longer holds
            self._last = (s, ti, st)
            if self.C is not None:
                out[i] = self.C
        return out

    def _turn(self, w_dps: np.ndarray, dt: float) -> None:
        """C <- C exp([w dt]x): the body turned by w [deg/s] for dt [s] (Rodrigues)."""
        v = np.radians(np.asarray(w_dps, dtype=np.float64)) * max(dt, 0.0)
        ang = float(np.linalg.norm(v))
        if ang < 1e-12:
            return
        k = v / ang
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        r = np.eye(3) + np.sin(ang) * kx + (1 - np.cos(ang)) * (kx @ kx)
        self.C = self.C @ r

    def earth_dps(self, c: np.ndarray, a_g: np.ndarray) -> np.ndarray:
        """The Earth rate [deg/s] (N, 3) in the body: the vertical part from the accelerometers, the
        horizontal part where north is known and the sample has a reference (else 0 there)."""
        e = vertical_earth_rate_dps(a_g, self.latitude_deg)
        if self.h is not None:
            ok = np.isfinite(c[:, 0, 0])
            e[ok] += np.einsum("nji,j->ni", c[ok], self.h)  # C.T @ h per sample
        return e

    def add(self, phi: np.ndarray, y: np.ndarray, c: np.ndarray) -> None:
        """Running sums over still samples: terms (N, P), rate at rest less the vertical Earth rate and
        plus the unit's compensation (N, 3) [deg/s], and their C (N, 3, 3)."""
        ok = np.isfinite(c[:, 0, 0]) & np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(phi), axis=1)
        if not ok.any():
            return
        phi, y, c = phi[ok], y[ok], c[ok]
        self._m += phi.T @ phi
        self._phi_y += phi.T @ y
        for i in range(3):
            hi = c[:, :, i]  # (C.T)[i, :] per sample: axis i sees h as hi @ h
            self._phi_h[i] += phi.T @ hi
            self._h_y += hi.T @ y[:, i]
        self._n += int(ok.sum())
        self._ss += float(np.sum(y * y))

    def fit(self, min_rank: int) -> bool:
        """Try to find north; True when it was fixed now. Needs the terms at full rank (every drift
        coefficient determined apart from h) and a heading 1-sigma below HEADING_SIGMA_DEG."""
        if self.h is not None or self._n < 100 or self.up_ref is None:
            return False
        ev, vec = np.linalg.eigh(self._m)
        keep = ev > 1e-9 * max(float(ev.max()), 1e-300)
        if int(keep.sum()) < min_rank:
            return False
        m_pinv = (vec[:, keep] / ev[keep]) @ vec[:, keep].T
        a = self._n * np.eye(3)
        b = self._h_y.copy()
        for i in range(3):
            a -= self._phi_h[i].T @ m_pinv @ self._phi_h[i]
            b -= self._phi_h[i].T @ m_pinv @ self._phi_y[:, i]
        ref = np.array([1.0, 0.0, 0.0]) if abs(self.up_ref[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = ref - self.up_ref * float(ref @ self.up_ref)
        e1 /= np.linalg.norm(e1)
        basis = np.column_stack([e1, np.cross(self.up_ref, e1)])  # the horizontal plane (3, 2)
        ar = basis.T @ a @ basis
        if np.linalg.cond(ar) > 1e8:
            return False
        u = np.linalg.solve(ar, basis.T @ b)
        # residual variance of the joint fit [deg/s]^2, for the heading's 1-sigma
        fitted = sum(float(self._phi_y[:, i] @ m_pinv @ self._phi_y[:, i]) for i in range(3))
        var = max((self._ss - fitted - float(u @ (basis.T @ b))) / max(3 * self._n - 3 * min_rank - 2, 1),
                  1e-30)
        cov = var * np.linalg.inv(ar)
        mag = float(np.linalg.norm(u))
        if mag <= 0:
            return False
        direction = u / mag  # the heading error is the part of the scatter across the direction
        across = np.array([-direction[1], direction[0]])
        self.heading_sigma_deg = float(np.degrees(np.sqrt(across @ cov @ across) / self.horizontal_dps))
        if self.heading_sigma_deg > HEADING_SIGMA_DEG:
            return False
        self.fit_magnitude = float(mag / self.horizontal_dps) if self.horizontal_dps > 0 else float("nan")
        self.h = basis @ (direction * self.horizontal_dps)  # its length is the latitude's
        return True

    def status(self) -> dict[str, object]:
        return {"latitude_deg": self.latitude_deg, "north_found": self.h is not None,
                "heading_sigma_deg": None if not np.isfinite(self.heading_sigma_deg)
                else round(self.heading_sigma_deg, 2),
                "fit_magnitude": (None if not np.isfinite(self.fit_magnitude)
                                  else round(self.fit_magnitude, 3)),
                "references": self.references, "samples": self._n}
