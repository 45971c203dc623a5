"""Control commands for the engine: recalibrate, rollback, push, and the SIGHUP reload.

Why a mixin of the engine: commands run on the engine loop (handed over through its inbox), so they
may touch the session and the store directly; they live here to keep engine.py about the loop.

Every command is validated before anything is stored or sent (push.check_set: at most MAX_TERMS
terms, a known term set, 3 finite rows, within range), and answered with a clear error otherwise.
A push the session refuses (start_push returning a reason) is answered as refused, and the session
stays where it was: a bad command never freezes it in PUSHING.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from gyrocal.daemon.config import load_config
from gyrocal.daemon.push import check_set, parse_temp_range
from gyrocal.daemon.session import State
from gyrocal.daemon.store import APPLIED_STATUSES, CalibrationRecord, utc_now
from gyrocal.errors import ConfigError
from gyrocal.protocol import termsets

RECALIBRATE_COALESCE_S = 2.0
"""A recalibrate this soon [s] after a session started (a switch-on's HELLO, another recalibrate) is
served by that session: no second one."""

log = logging.getLogger("gyrocal.engine")


class CommandsMixin:
    """Engine methods for control commands; see the module docstring."""

    cfg: Any
    store: Any
    session: Any
    link: Any
    last_hello: Any
    notifier: Any

    def _start_session(self, hello: Any, now: float) -> None:  # the engine's
        raise NotImplementedError

    # -- commands -----------------------------------------------------------------------------
    def _command(self, req: dict[str, Any], now: float) -> dict[str, Any]:
        """Carry out one operator command, and log it with who gave it and how it ended: one line."""
        reply = self._do_command(req, now)
        cmd = req.get("cmd")
        what = {"rollback": f"rollback{' --to ' + str(req['to']) if req.get('to') is not None else ''}",
                "push": f"push of {len(req.get('terms') or [])} terms"}.get(str(cmd), str(cmd))
        outcome = reply.get("message") if reply.get("ok") else f"refused: {reply.get('error')}"
        log.log(logging.INFO if reply.get("ok") else logging.WARNING, "operator command %s from %s: %s",
                what, req.get("from", "a client"), outcome)
        return reply

    def _do_command(self, req: dict[str, Any], now: float) -> dict[str, Any]:
        cmd = req.get("cmd")
        try:
            if cmd == "recalibrate":
                if self.last_hello is None:
                    return {"ok": False, "error": "no unit has announced itself (HELLO) yet"}
                s = self.session
                if s is not None and now - s.started < RECALIBRATE_COALESCE_S and not s.last_push \
                        and s.operator_hold is None:
                    # a trigger wired to the switch-on (an ignition line) lands beside the unit's own
                    # HELLO, which starts the session already: two sessions per switch-on, and a storm of
                    # 100 triggers 100 sessions in 5 s (an operator's audit). One young session that has
                    # pushed nothing answers them all (after a push, a recalibrate asks for a new one)
                    return {"ok": True, "message": f"a session started {now - s.started:.1f} s ago (boot "
                                                   f"{s.hello.boot_count}): it serves this request"}
                guess = None if s is None else s.unconfirmed
                self._start_session(self.last_hello, now)
                self.session.unconfirmed = guess  # still no HELLO from the unit since its restart
                return {"ok": True, "message": "new calibration session started"}
            if cmd in ("rollback", "push"):
                return self._push_command(req, now)
        except Exception as err:  # a bad command must not stop the loop
            log.exception("command %r failed", cmd)
            return {"ok": False, "error": str(err)}
        return {"ok": False, "error": f"unknown command {cmd!r}; use status, recalibrate, rollback, push"}

    def _push_command(self, req: dict[str, Any], now: float) -> dict[str, Any]:
        s = self.session
        if s is None:
            return {"ok": False, "error": "no unit session yet; wait for the unit's HELLO"}
        if s.state is State.PUSHING:
            return {"ok": False, "error": "a push is already under way; try again in a few seconds"}
        if s.unconfirmed is not None:
            return {"ok": False, "error": "the unit restarted without a HELLO and has not said who it is "
                                          "yet; nothing was pushed (check `gyrocal status`)"}
        serial = s.hello.serial
        if self.link is None or not self.link.connected:  # a rollback as a file: never into a dead link
            return {"ok": False, "error": "the unit is not connected; nothing was pushed or stored"}
        if req["cmd"] == "rollback":
            target = req.get("to")
            history = [r for r in self.store.history(serial) if r.push.get("status") in APPLIED_STATUSES]
            if target is None:
                current = s.applied.version if s.applied is not None else None
                older = [r for r in history if current is None or r.version < current]
                if not older:
                    return {"ok": False, "error": "no earlier acked calibration to roll back to"}
                rec = older[-1]
            else:
                rec = self.store.get(serial, int(target))
                if rec is None:
                    return {"ok": False, "error": f"unit {serial} has no calibration v{target}"}
                if rec.push.get("status") not in APPLIED_STATUSES:
                    return {"ok": False, "error": (
                        f"unit {serial} never verifiably held v{target} (its push ended "
                        f"{rec.push.get('status')!r}); a rollback goes back to a set the unit held. To "
                        f"send it anyway as a new version: gyrocal push --file FILE with its terms and "
                        f"coefficients")}
            why = check_set(list(rec.terms), rec.coefficients_dps)
            if why is not None:
                return {"ok": False, "error": f"stored v{rec.version} cannot be pushed: {why}"}
            return self._started(s.start_push(rec.version, list(rec.terms),
                                              np.asarray(rec.coefficients_dps), now), rec.version,
                                 s, "a rollback")
        terms = req.get("terms")
        if not isinstance(terms, list) or not terms:
            return {"ok": False, "error": "push needs 'terms': a list of term names"}
        terms = [str(t) for t in terms]
        try:  # any set built from the protocol's atoms goes to the unit, which alone knows its table
            termsets.register_unit_terms(terms)
        except ConfigError as err:
            return {"ok": False, "error": f"terms {terms}: {err}"}
        why = check_set(terms, req.get("coefficients"))
        if why is None and not s.caps.holds(terms):  # checked before anything is stored (operations.md)
            why = f"the unit ({s.caps.kind}) cannot hold the terms {terms}; nothing was stored"
        if why is not None:
            return {"ok": False, "error": why}
        coeffs = np.asarray(req["coefficients"], dtype=np.float64)
        stats: dict[str, Any] = {"source": "file"}
        if req.get("temp_range_c") is not None:  # what the set was learnt over (cli_control.file_temp_range)
            try:
                stats["temp_range_c"] = list(parse_temp_range(req["temp_range_c"], "temp_range_c"))
            except ConfigError as err:
                return {"ok": False, "error": str(err)}
        try:
            rec = self.store.add(CalibrationRecord(
                serial=serial, version=0, terms=terms, coefficients_dps=coeffs.tolist(),
                uncertainty_dps=[[float("nan")] * len(terms)] * 3, identifiable={}, stats=stats,
                session={"boot_count": s.hello.boot_count, "fw": s.hello.fw_version},
                push={"status": "pending"}),
                min_version=s.version_floor())
        except Exception as err:  # never a unit set the store does not know: refuse the push
            return {"ok": False, "error": f"store unavailable ({err}); nothing was pushed"}
        hold = getattr(self.link, "hold_range", None)  # an autopilot writes it as TMIN..TMAX
        if hold is not None and "temp_range_c" in stats:
            hold(rec.version, *stats["temp_range_c"])
        return self._started(s.start_push(rec.version, terms, coeffs, now), rec.version, s, "a file push")

    @staticmethod
    def _started(error: str | None, version: int, session: Any, what: str) -> dict[str, Any]:
        if error is not None:
            return {"ok": False, "error": f"push of v{version} refused: {error}", "version": version}
        session.hold_for_operator(version, what)
        return {"ok": True, "message": f"pushing v{version}", "version": version}

    def _reload(self) -> None:
        self.notifier.reloading()
        if self.cfg.source.startswith("<"):
            log.info("SIGHUP: no config file to reload")
        else:
            try:
                new = load_config(self.cfg.source)
            except Exception as err:  # a broken edit must not kill a running daemon
                log.error("SIGHUP: config not reloaded: %s", err)
                self.last_reload = {"utc": utc_now(), "ok": False, "error": str(err)}
            else:
                self.last_reload = {"utc": utc_now(), "ok": True}
                if new.link != self.cfg.link:  # each field, old -> new, as every reload line says
                    log.warning("SIGHUP: %s; link settings take effect at the next restart",
                                ", ".join(_changed_fields(self.cfg, new, ("link",))))
                for top in ("state_dir", "control_socket", "watchdog"):  # read once, at start
                    if getattr(new, top) != getattr(self.cfg, top):
                        log.warning("SIGHUP: %s changed from %s to %s; it takes effect at the next restart",
                                    top, getattr(self.cfg, top), getattr(new, top))
                changed = _changed_fields(self.cfg, new, ("validation", "push", "monitor", "store"))
                now_ = [c for c in changed if c.split(" ")[0] not in AT_SWITCH_ON]
                if now_:  # read by the session at its next check
                    log.info("SIGHUP: changed, in effect now: %s", "; ".join(now_))
                later = [c for c in changed if c.split(" ")[0] in AT_SWITCH_ON]
                later += _changed_fields(self.cfg, new, ("estimator",), skip=("terms",))
                # the still detector is made, and the site read, at a session's start: named as every
                # other field (they said "still settings changed" and the new latitude alone: an
                # integrator's fault campaign, rc33 G6)
                later += _changed_fields(self.cfg, new, ("still", "site"))
                if later:  # the learner (method, forgetting, step, convergence) is built at a switch-on
                    log.info("SIGHUP: changed, in effect at the next switch-on (or `gyrocal recalibrate`): "
                             "%s", "; ".join(later))
                for section in ("validation", "push", "monitor", "store", "still", "estimator", "site"):
                    setattr(self.cfg, section, getattr(new, section))
                if new.terms != self.cfg.terms:  # the learner of a session is built at its switch-on
                    log.info("SIGHUP: estimator.terms changed to %s; they take effect at the next switch-on "
                             "(or `gyrocal recalibrate`)", ",".join(new.terms))
                    self.cfg.terms = new.terms
                log.info("SIGHUP: configuration reloaded from %s", self.cfg.source)
        self.notifier.ready()


AT_SWITCH_ON = frozenset({"validation.block_s", "validation.holdout_every", "monitor.window_s"})
"""Fields of the at-once sections that a session reads when it starts (its blocks and windows)."""


def _changed_fields(old: Any, new: Any, sections: tuple[str, ...], skip: tuple[str, ...] = ()) -> list[str]:
    """``section.field old -> new`` for each field of ``sections`` a reload changes (one level of
    nesting spelled out, e.g. estimator.convergence.window), so every change is said in the log."""
    out = []
    for sec in sections:
        a, b = getattr(old, sec) or {}, getattr(new, sec) or {}
        for key in sorted(set(a) | set(b)):
            if key in skip or a.get(key) == b.get(key):
                continue
            if isinstance(a.get(key), dict) and isinstance(b.get(key), dict):
                out += [f"{sec}.{key}.{k} {_shown(a[key].get(k))} -> {_shown(b[key].get(k))}"
                        for k in sorted(set(a[key]) | set(b[key])) if a[key].get(k) != b[key].get(k)]
            else:
                out.append(f"{sec}.{key} {_shown(a.get(key))} -> {_shown(b.get(key))}")
    return out


def _shown(v: Any) -> str:
    return "default" if v is None else repr(v)
