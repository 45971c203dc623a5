"""What a unit can hold, and the projection of a learnt set onto it.

Why: the daemon learns the full model it is configured with (say the temperature polynomial plus
gravity terms), but a unit holds only what its firmware can apply. Our own protocol carries any term
set of up to ``MAX_TERMS`` (21) terms (docs/protocol.md); a PX4 or ArduPilot autopilot holds one
offset polynomial in temperature per axis and no gravity terms (docs/mavlink.md). So before a push:

1. the learnt set C over the session's terms N is split into the part the unit can hold, D over a
   held term set S (a subset of N), and the remainder C - D (over N) that a host consumer applies;
2. D is the held part of C, corrected so that D reproduces C at the poses the unit was seen in as
   well as the held terms can: a gravity term of a unit that sits level is a constant there, and
   the constant term takes it. The correction uses the held terms in their order (1 first), each
   only if the poses determine it, so nothing the data did not see is moved;
3. the drift the unit is left with at its poses (RMS over the poses of (C - D) . phi, deg/h) is
   reported and stored beside the set, with the remainder as a coefficient set.

One capability object per unit, taken from the link (``link.capabilities``) when it has one, else
``PROTOCOL``. ``reboot_required``: the unit applies a pushed set only after its next reboot (PX4 with
TC_G_ENABLE off at boot; docs/mavlink.md). Units: coefficients deg/s per term unit, drift deg/h.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gyrocal.protocol.messages import MAX_TERMS

DPH = 3600.0


@dataclass(frozen=True)
class UnitCapabilities:
    """Which term sets a unit can hold (``term_sets`` None: any set the protocol encodes, up to
    ``max_terms``), whether a pushed set waits for a reboot (None: not known), and whether the unit
    clamps its temperature into the set's TMIN..TMAX before it evaluates the set (an autopilot does;
    our protocol's unit applies its polynomial at every temperature)."""

    kind: str = "protocol"
    term_sets: tuple[tuple[str, ...], ...] | None = None
    max_terms: int = MAX_TERMS
    reboot_required: bool | None = False
    clamps_temperature: bool = False
    board_rotation: dict[str, float] | None = None
    """The unit's board rotation parameters when it holds its set in a frame turned from the samples'
    (an autopilot: sensor vs body frame, docs/mavlink.md "Board rotation"); recorded with each push."""
    own_boot_bias: bool = False
    """The unit measures its own gyro bias at each boot and puts it into the constant of the set it
    holds (ArduPilot's boot gyro calibration rewrites INS_GYROFFS). Its read-back after a reboot is the
    stored version with the same temperature terms and another constant: that set, not a foreign one
    (reconcile.py)."""
    ack_within_s: float | None = None
    """[s] How long this unit may take to answer a COEFF_WRITE when that is longer than our protocol's
    (an autopilot writes a set one parameter at a time, each lost echo costing a timeout); the daemon
    waits max(push.ack_timeout_s, this) per attempt. None: the protocol's unit, push.ack_timeout_s."""

    def holds(self, names: list[str] | tuple[str, ...]) -> bool:
        if len(names) > self.max_terms:
            return False
        return self.term_sets is None or tuple(names) in self.term_sets

    def held_subset(self, names: list[str] | tuple[str, ...]) -> tuple[str, ...] | None:
        """The largest term set the unit holds made only of ``names`` (``names`` itself if held)."""
        if self.holds(names):
            return tuple(names)
        if self.term_sets is None:
            return None  # more than max_terms: the protocol cannot carry it, nothing to choose from
        fits = [s for s in self.term_sets if set(s) <= set(names) and len(s) <= self.max_terms]
        return max(fits, key=len) if fits else None

    def as_dict(self) -> dict[str, Any]:
        out = {"kind": self.kind, "max_terms": self.max_terms, "reboot_required": self.reboot_required,
               "clamps_temperature": self.clamps_temperature,
               "term_sets": None if self.term_sets is None else [list(s) for s in self.term_sets]}
        if self.board_rotation is not None:
            out["board_rotation"] = dict(self.board_rotation)
        if self.own_boot_bias:
            out["own_boot_bias"] = True
        if self.ack_within_s is not None:
            out["ack_within_s"] = self.ack_within_s
        return out


PROTOCOL = UnitCapabilities()
"""Our own protocol (docs/protocol.md): any registered term set of up to 21 terms."""


def frame_changed(caps: UnitCapabilities, prior: Any) -> str | None:
    """Why a stored set must not warm-start this switch-on's session, or None.

    An autopilot's samples are in its body frame, and the stored set and its temperature information
    (learner.py) were learnt in the body frame of the board rotation recorded with its push
    (``push.board_rotation``). The sensor's thermal curve is fixed to the board, so after a remount (a
    changed SENS_BOARD_ROT / AHRS_ORIENTATION) it appears turned in the body frame: the old set would
    be a wrong prior. A record without a recorded rotation (older, or our protocol's unit) is kept.
    """
    was = (getattr(prior, "push", None) or {}).get("board_rotation")
    now = caps.board_rotation
    if prior is None or was is None or now is None or dict(was) == dict(now):
        return None
    return f"the board rotation changed since v{prior.version} was learnt ({was} -> {now})"


def of_link(link: Any) -> UnitCapabilities:
    """The link's capability object if it declares one, else our protocol's."""
    caps = getattr(link, "capabilities", None)
    return caps if isinstance(caps, UnitCapabilities) else PROTOCOL


@dataclass
class Projection:
    """A learnt set split into what the unit holds and what the host must apply."""

    held_names: tuple[str, ...]
    held_dps: np.ndarray  # (3, S) deg/s per term unit: what is pushed
    embedded_dps: np.ndarray  # (3, P) the held set in the learnt term order (zeros elsewhere)
    remainder_dps: np.ndarray  # (3, P) learnt minus embedded: the host consumer's part
    left_poses_dps: np.ndarray  # (3,) RMS over the poses of the remainder's drift [deg/s]
    poses: int

    @property
    def exact(self) -> bool:
        return not np.any(self.remainder_dps)

    def record(self, names: list[str]) -> dict[str, Any]:
        """The store's ``host_remainder`` field: apply ``coefficients_dps`` over ``terms`` on the host
        (subtract sum_j c_j phi_j from the unit's output, as the unit does with its own set)."""
        return {"terms": list(names), "coefficients_dps": self.remainder_dps.tolist(),
                "held_terms": list(self.held_names), "poses": self.poses,
                "drift_left_poses_dph": dict(zip("xyz", (self.left_poses_dps * DPH).tolist(), strict=True))}


def project(names: list[str], coeffs_dps: np.ndarray, held: tuple[str, ...],
            poses_phi: np.ndarray) -> Projection:
    """Split ``coeffs_dps`` (3, P) over ``names`` into the ``held`` terms and a remainder.

    ``poses_phi`` (K, P): the terms at the poses the unit was seen in (block means). See the module
    docstring for the rule; with ``held == names`` the set is unchanged and the remainder is zero.
    """
    c = np.asarray(coeffs_dps, dtype=np.float64)
    idx = [list(names).index(n) for n in held]
    d = c[:, idx].copy()
    phi = np.asarray(poses_phi, dtype=np.float64).reshape(-1, len(names))
    if tuple(held) != tuple(names) and len(phi):
        rest = c.copy()
        rest[:, idx] = 0.0
        r = phi @ rest.T  # (K, 3) the drift of the terms the unit cannot hold, at each pose
        a = phi[:, idx]
        scale = np.maximum(np.linalg.norm(a, axis=0), 1e-300)
        chosen: list[int] = []
        for j in range(len(idx)):  # the held terms in order, each only if the poses determine it
            trial = a[:, [*chosen, j]] / scale[[*chosen, j]]
            sv = np.linalg.svd(trial, compute_uv=False)
            if sv[-1] > 1e-6 * sv[0]:
                chosen.append(j)
        if chosen:
            sol, *_ = np.linalg.lstsq(a[:, chosen], r, rcond=None)  # (len(chosen), 3)
            d[:, chosen] += sol.T
    emb = np.zeros_like(c)
    emb[:, idx] = d
    rem = c - emb
    left = np.sqrt(np.mean((phi @ rem.T) ** 2, axis=0)) if len(phi) else np.full(3, np.nan)
    return Projection(tuple(held), d, emb, rem, left, len(phi))


def learnt_set(record: Any, names: list[str]) -> np.ndarray | None:
    """The set learnt over ``names`` (3, P) [deg/s per term unit] that ``record`` holds, or None.

    A record in ``names`` itself is its own coefficients. A projected record (the unit held a subset)
    gives back the learnt set as the held part embedded in the learnt order plus ``host_remainder``
    (the projection's split, C = embedded + remainder), so the next switch-on warm-starts from what was
    learnt rather than cold (issue 10). None when neither matches ``names`` or a value is not finite.
    """
    try:
        terms = list(record.terms)
        held = np.asarray(record.coefficients_dps, dtype=np.float64)
        if terms == list(names):
            c = held
        else:
            rem = record.host_remainder or {}
            if list(rem.get("terms") or []) != list(names) or not set(terms) <= set(names):
                return None
            c = np.asarray(rem["coefficients_dps"], dtype=np.float64).copy()
            if c.shape != (3, len(names)) or held.shape != (3, len(terms)):
                return None
            for j, n in enumerate(terms):
                c[:, list(names).index(n)] += held[:, j]
    except (AttributeError, KeyError, TypeError, ValueError):
        return None
    return c if c.shape == (3, len(names)) and np.all(np.isfinite(c)) else None

