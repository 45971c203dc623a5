"""The Earth's rotation in a tumbling unit's body frame: north found from the data, then removed.

Why: a gyro at rest reads the Earth's rotation (15.041 deg/h) as true rate (gyrocal/model/earth.py).
The daemon learns the rate at rest as drift, so without this it learnt the Earth's rotation into the
unit's set. On a unit that turns with the Earth, the demo unit and the fibre unit were never pushed
(the part along north changes with every pose's heading, which no gravity term can follow, and the
push gate saw 1.7-2 deg/h it could not remove), and the tactical unit was left with 6-11 deg/h
instead of 3-5 (`benchmarks/bench_earth.py`).

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

A gap in seq that the unit may have turned through, or a rest whose gravity disagrees with the carried
frame, loses the reference. The next rest starts a new one, with its own unknown horizontal vector; the
fit keeps every reference's sums, so the drift they share carries over, and a new reference needs a
rest or two once the drift is known, not another tumble. Until its north is found, its samples find
north only: nothing learns from them.
"""

from __future__ import annotations

import numpy as np

from gyrocal.model.earth import OMEGA_IE_DPS, horizontal_basis
from gyrocal.protocol.messages import SEQ_MODULO

HEADING_SIGMA_DEG = 3.0
"""North is fixed once the fit's 1-sigma heading error is below this [deg]: 15 deg/h x cos(latitude)
x sin(3 deg) = 0.55 deg/h at 45 deg at one sigma. The demo and fibre units fix it at 2.3-2.9 deg about
20 s into the tumble and are left with 0.19-0.25 deg/h (bench_earth.py); it is not refined after."""
GAP_TURN_MAX_DEG = 1.0
"""A gap in seq is bridged when the unit can have turned less than this [deg] during it (at the rate of
the sample after it); a longer turn loses the reference, since its part about the vertical is unseen."""
MAX_REFERENCES = 64
"""References kept in the fit's sums; beyond, the sums start over (north is found again from a tumble)."""
UP_TOLERANCE_DEG = 3.0
"""A rest whose measured up differs from the carried one by more than this [deg] has lost the
reference (the unit turned while samples were lost)."""


class EarthTrack:
    """One switch-on's reference frame, the horizontal Earth rate in it, and the sums that find it."""

    def __init__(self, latitude_deg: float, n_terms: int) -> None:
        self.latitude_deg = float(latitude_deg)
        self.north_rate_dps = OMEGA_IE_DPS * abs(np.cos(np.radians(latitude_deg)))
        self.n_terms = n_terms
        self.C: np.ndarray | None = None  # body -> reference, at the last sample
        self.up_ref: np.ndarray | None = None  # up in the reference frame (unit vector)
        self.h: np.ndarray | None = None  # horizontal Earth rate in the reference frame [deg/s]
        self.heading_sigma_deg = float("inf")
        self.fit_magnitude = float("nan")  # |h| the fit gave, over Omega cos(latitude)
        self.references = 0  # reference frames started (1 + times it was lost)
        self.found_before = False  # north was fixed once this session: the drift is learnt clean
        self.last_loss: str | None = None  # why the last reference was lost
        self._last: tuple[int, float, bool] | None = None  # seq, t [s], still of the last sample
        self._reset_sums()

    def _reset_sums(self) -> None:
        """The sums shared by every reference (terms, rates) and none yet of its own."""
        p = self.n_terms
        self._m = np.zeros((p, p))
        self._phi_y = np.zeros((p, 3))
        self._n = 0
        self._ss = 0.0
        self._refs: list[dict[str, np.ndarray | float]] = []  # per reference: its sums and its up

    def _new_reference(self, up: np.ndarray) -> None:
        if len(self._refs) >= MAX_REFERENCES:  # a link that loses samples for hours: start the sums over
            self._reset_sums()
        p = self.n_terms
        self._refs.append({"phi_h": np.zeros((3, p, 3)), "h_y": np.zeros(3), "n": 0.0, "up": up.copy()})

    @property
    def known(self) -> bool:
        return self.h is not None

    def _lose(self, why: str) -> None:
        self.last_loss = why
        self.C = None
        self.h = None
        self.heading_sigma_deg = float("inf")

    def advance(self, seq: np.ndarray, t: np.ndarray, w_dps: np.ndarray, a_g: np.ndarray,
                still: np.ndarray) -> np.ndarray:
        """Carry the reference through these samples (time order); returns C (N, 3, 3) per sample,
        NaN where there is no reference (before the first rest, or after it was lost).

        At the first rest after a move or a gap, the carried frame is checked against the measured
        gravity (``UP_TOLERANCE_DEG``), and a gap is bridged (at the rate of the sample after it) only
        when it can have turned the unit by less than ``GAP_TURN_MAX_DEG``. The frame is not turned
        back onto gravity at each rest: tried, and on the tumble with the Earth turning, the heading
        error then grew from 0.03 to 90 deg within 60 s, where the plain integration stayed within
        1.4 deg over 300 s (the demo unit, 400 Hz; not understood, so not shipped)."""
        n = seq.size
        out = np.full((n, 3, 3), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            up_b = a_g / np.linalg.norm(a_g, axis=1, keepdims=True)
        cos_tol = np.cos(np.radians(UP_TOLERANCE_DEG))
        for i in range(n):  # per sample: the integration is a recursion
            s, ti, st = int(seq[i]), float(t[i]), bool(still[i])
            gap = False
            if self._last is not None and self.C is not None:
                ls, lt, lst = self._last
                gap = (s - ls) % SEQ_MODULO != 1
                dt = ti - lt
                turn = float(np.linalg.norm(w_dps[i])) * max(dt, 0.0)
                if gap and turn > GAP_TURN_MAX_DEG:
                    self._lose(f"at unit time {ti:.1f} s, {dt:.3f} s of samples lost while the unit turned "
                               f"about {turn:.1f} deg")  # the turn about the vertical cannot be bridged
                elif gap or not st or not lst:
                    self._turn(w_dps[i], dt)
            if self.C is not None and st and (gap or not self._last[2]) and np.all(np.isfinite(up_b[i])):
                u = self.C @ up_b[i]
                if float(self.up_ref @ u) < cos_tol:  # the carried frame disagrees with gravity
                    off = float(np.degrees(np.arccos(np.clip(self.up_ref @ u, -1.0, 1.0))))
                    self._lose(f"at unit time {ti:.1f} s, gravity {off:.1f} deg off the carried frame")
            if self.C is None and st and np.all(np.isfinite(up_b[i])):
                self.C = np.eye(3)
                self.up_ref = up_b[i].copy()
                self.references += 1
                self._new_reference(self.up_ref)
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

    def horizontal_dps(self, c: np.ndarray) -> np.ndarray:
        """The Earth rate's part along north [deg/s] (N, 3) in the body, C.T h per sample, where north
        is known and the sample has a reference; 0 elsewhere."""
        e = np.zeros((c.shape[0], 3))
        if self.h is not None:
            ok = np.isfinite(c[:, 0, 0])
            e[ok] = np.einsum("nji,j->ni", c[ok], self.h)
        return e

    def add(self, phi: np.ndarray, y: np.ndarray, c: np.ndarray) -> None:
        """Running sums over still samples: terms (N, P), rate at rest less the vertical Earth rate and
        plus the unit's compensation (N, 3) [deg/s], and their C (N, 3, 3) in the current reference."""
        ok = np.isfinite(c[:, 0, 0]) & np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(phi), axis=1)
        if not ok.any() or not self._refs:
            return
        phi, y, c = phi[ok], y[ok], c[ok]
        ref = self._refs[-1]
        self._m += phi.T @ phi
        self._phi_y += phi.T @ y
        for i in range(3):
            hi = c[:, :, i]  # (C.T)[i, :] per sample: axis i sees h as hi @ h
            ref["phi_h"][i] += phi.T @ hi
            ref["h_y"] += hi.T @ y[:, i]
        ref["n"] += float(ok.sum())
        self._n += int(ok.sum())
        self._ss += float(np.sum(y * y))

    def fit(self, min_rank: int) -> bool:
        """Try to find north in the current reference; True when it was fixed now.

        One least squares over every reference's still samples: the drift coefficients shared, a
        horizontal vector per reference, the coefficients profiled out. Needs the terms at full rank
        and the current reference's heading to a 1-sigma below HEADING_SIGMA_DEG."""
        if self.h is not None or self.C is None or not self._refs or self._refs[-1]["n"] < 100:
            return False
        ev, vec = np.linalg.eigh(self._m)
        keep = ev > 1e-9 * max(float(ev.max()), 1e-300)
        if int(keep.sum()) < min_rank:
            return False
        m_pinv = (vec[:, keep] / ev[keep]) @ vec[:, keep].T
        k = len(self._refs)
        bases = [horizontal_basis(r["up"]) for r in self._refs]  # (3, 2) each
        # G (K, 3 axes, P, 2): each reference's sums turned into its horizontal plane
        g = np.stack([np.einsum("ipk,kl->ipl", r["phi_h"], bases[j]) for j, r in enumerate(self._refs)])
        n_ref = np.array([float(r["n"]) for r in self._refs])
        a = np.kron(np.diag(n_ref), np.eye(2))  # B.T (n I) B per reference: C is a rotation
        a -= np.einsum("jipa,pq,kiqb->jakb", g, m_pinv, g).reshape(2 * k, 2 * k)
        h_y = np.stack([bases[j].T @ r["h_y"] for j, r in enumerate(self._refs)])  # (K, 2)
        b = (h_y - np.einsum("jipa,pq,qi->ja", g, m_pinv, self._phi_y)).reshape(2 * k)
        if np.linalg.cond(a) > 1e10:
            return False
        u_all = np.linalg.solve(a, b)
        fitted = sum(float(self._phi_y[:, i] @ m_pinv @ self._phi_y[:, i]) for i in range(3))
        dof = max(3 * self._n - 3 * min_rank - 2 * k, 1)
        var = max((self._ss - fitted - float(u_all @ b)) / dof, 1e-30)
        u = u_all[-2:]
        cov = var * np.linalg.inv(a)[-2:, -2:]
        mag = float(np.linalg.norm(u))
        if mag <= 0:
            return False
        direction = u / mag  # the heading error is the part of the scatter across the direction
        across = np.array([-direction[1], direction[0]])
        sigma = float(np.degrees(np.sqrt(across @ cov @ across) / self.north_rate_dps))
        self.heading_sigma_deg = sigma
        if sigma > HEADING_SIGMA_DEG:
            return False
        self.fit_magnitude = float(mag / self.north_rate_dps) if self.north_rate_dps > 0 else float("nan")
        self.h = bases[-1] @ (direction * self.north_rate_dps)  # its length is the latitude's
        self.found_before = True
        return True

    def status(self) -> dict[str, object]:
        return {"latitude_deg": self.latitude_deg, "north_found": self.h is not None,
                "heading_sigma_deg": None if not np.isfinite(self.heading_sigma_deg)
                else round(self.heading_sigma_deg, 2),
                "fit_magnitude": (None if not np.isfinite(self.fit_magnitude)
                                  else round(self.fit_magnitude, 3)),
                "references": self.references, "last_loss": self.last_loss, "samples": self._n}
