"""Safe-state supervisor of the service: a pure state machine with timeouts (sans-I/O).

The service tells the supervisor when each source was last good — the PLC answered a read, the
piezo amplifier was heard on CAN, a valid measurement arrived (or none was expected because no
board is under the camera) — and whether each condition holds — the machine reports no e-stop
and a turning spindle, the PLC's registers make sense, the quality log takes the records, the
service's own code ran without an unexpected error — and asks it, every cycle, which state to
be in and what to command in the safe state:

* ``RUN``: the control loops own the setpoints.
* ``SAFE``: entered as soon as any source has been gone for longer than its timeout or any
  condition fails. The feed is held or ramped down to ``safe_feed_mm_s`` (rate-limited, inside
  the machine's limits, as configured), the piezo offsets go to zero and the amplifier is
  disabled.
* Recovery is automatic: once every source is back and every condition has held for the
  recovery time, the state returns to ``RUN``. With hysteresis: a timed source counts as back
  only when heard within ``RECOVERY_FRESH_FRACTION`` of its timeout (it leaves RUN at the whole
  timeout). With a growing back-off: the recovery time is ``recovery_s`` after the first entry
  and doubles (``BACKOFF_FACTOR``) with every entry that follows a short RUN, up to
  ``BACKOFF_MAX_FACTOR`` times ``recovery_s``; a RUN of ``BACKOFF_RESET_S`` resets it. A cause
  that comes back at once therefore cycles ever more slowly instead of every ``recovery_s``.

The supervisor starts in ``SAFE`` (nothing heard yet). Time is always passed in (``now_s``,
seconds on any monotonic clock); the supervisor never reads a clock.

:class:`AmplifierMonitor` judges the piezo amplifier's own word (its status, TPDO1): a fault
(state 3 or fault bits: over-temperature, stroke limit = offsets refused, setpoint timeout,
overcurrent) or a state that is not what the service commands (not enabled and tracking while
enable is commanded), confirmed for ``AMP_CONFIRM_S``, is the ``amplifier`` condition failing. A
stroke-limit bit alone while the amplifier tracks (it refused a table and still plays the one
before, which the CAN client re-plans at once) is confirmed only after
``AMP_REFUSAL_CONFIRM_S``.
It also remembers when the amplifier was last seen *not* playing the offsets, so that the
uniformity loop never learns from board cut meanwhile.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

from config.machine import SafetyConfig
from core.checks import check_finite, check_positive
from protocol.piezo_canopen import AmpFault, AmpState

FAULT_STROKE_LIMIT = int(AmpFault.STROKE_LIMIT)
STATE_DISABLED, STATE_ENABLED, STATE_RAMPING, STATE_FAULT = (
    int(AmpState.DISABLED), int(AmpState.ENABLED), int(AmpState.RAMPING), int(AmpState.FAULT))

TIMED_SOURCES = ("plc", "can", "measurement")
"""Sources that must be heard within their timeout."""
CONDITIONS = ("machine", "plc_data", "amplifier", "log", "service")
"""Conditions that must hold: the machine fit to run, the PLC's registers sensible, the piezo
amplifier doing what it is told, the quality log writable, the service's own code free of
unexpected errors."""
SOURCES = TIMED_SOURCES + CONDITIONS
"""What the supervisor watches, in the order reasons are reported."""
AMP_CONFIRM_S = 0.1
"""How long the amplifier must report a fault or a state other than commanded before it counts
as failed, s: a few status periods (10 ms) and command cycles (20 ms), well inside the CAN
timeout, so the latency of an enable or disable is never mistaken for a failure."""
AMP_REFUSAL_CONFIRM_S = 0.3
"""Confirmation time of a stroke-limit bit alone while the amplifier tracks, s: long enough for
the CAN client to re-plan the refused table (``controller.fieldbus.piezo_client.REFUSAL_GRACE_S``)
and the
amplifier to take the new one, short enough that an amplifier refusing everything goes safe."""
RECOVERY_FRESH_FRACTION = 0.5
"""In SAFE a timed source counts as back only when heard within this fraction of its timeout."""
BACKOFF_FACTOR = 2.0
"""The recovery time grows by this factor with each safe entry after a short RUN."""
BACKOFF_MAX_FACTOR = 8.0
"""... up to this multiple of ``recovery_s``."""
BACKOFF_RESET_S = 10.0
"""A RUN this long resets the back-off (the next entry waits ``recovery_s`` again), s."""
WARM_START_CONFIRM_S = 0.05
"""At a warm start (:meth:`Supervisor.warm_start`) every source and condition must hold this long
before the first RUN instead of ``recovery_s`` (when shorter), s: nothing failed, the machine
ran before the service started, and each confirmation cycle cuts board without the offsets."""
AMP_FAULT_BITS = {
    0: "over-temperature",
    1: "stroke limit (offsets refused)",
    2: "setpoint timeout",
    3: "overcurrent",
}
"""Names of the status's fault bits (``docs/piezo_canopen.md``)."""
AMP_STATES = {
    STATE_DISABLED: "disabled",
    STATE_ENABLED: "enabled",
    STATE_RAMPING: "ramping to zero",
    STATE_FAULT: "fault",
}
"""Names of the status's states."""


class SafetyState(str, enum.Enum):
    """State of the service: control loops active, or the safe state."""

    RUN = "run"
    SAFE = "safe"


@dataclass(frozen=True)
class SafetyStatus:
    """Result of one :meth:`Supervisor.step`.

    Attributes
    ----------
    state : SafetyState
        The state to be in now.
    missing : tuple of str
        Sources currently gone (beyond their timeout), a subset of :data:`SOURCES`.
    changed : bool
        Whether this step changed the state.
    since_s : float
        Time the current state was entered.
    """

    state: SafetyState
    missing: tuple[str, ...]
    changed: bool
    since_s: float


class Supervisor:
    """Timeouts on the PLC, the CAN bus, the measurements and the machine; safe-state actions.

    Parameters
    ----------
    cfg : SafetyConfig
        Timeouts (``plc_timeout_s``, ``can_timeout_s``, ``measurement_timeout_s``), confirmation
        time ``recovery_s`` and the safe action (``safe_state`` = ``"hold"`` | ``"ramp_down"``,
        ``safe_feed_mm_s``, ``ramp_mm_s2``).
    now_s : float
        Start time. Measurements get one ``measurement_timeout_s`` of grace from here; the PLC
        and the CAN bus must be heard first.
    backoff_factor, backoff_max_factor, backoff_reset_s, fresh_fraction : float
        The recovery's back-off and hysteresis (module constants by default): the recovery time
        after the n-th entry in a row of short RUNs is ``recovery_s * backoff_factor**(n-1)``,
        at most ``recovery_s * backoff_max_factor``; a RUN of ``backoff_reset_s`` resets n;
        a timed source counts as back within ``fresh_fraction`` of its timeout.
    """

    def __init__(
        self,
        cfg: SafetyConfig,
        *,
        now_s: float,
        backoff_factor: float = BACKOFF_FACTOR,
        backoff_max_factor: float = BACKOFF_MAX_FACTOR,
        backoff_reset_s: float = BACKOFF_RESET_S,
        fresh_fraction: float = RECOVERY_FRESH_FRACTION,
    ) -> None:
        t0 = check_finite("now_s", now_s)
        if not backoff_factor >= 1.0:
            raise ValueError(f"backoff_factor must be >= 1, got {backoff_factor!r}")
        if not backoff_max_factor >= 1.0:
            raise ValueError(f"backoff_max_factor must be >= 1, got {backoff_max_factor!r}")
        self.backoff_factor = float(backoff_factor)
        self.backoff_max_factor = float(backoff_max_factor)
        self.backoff_reset_s = check_positive("backoff_reset_s", backoff_reset_s)
        if not 0.0 < fresh_fraction <= 1.0:
            raise ValueError(f"fresh_fraction must be in (0, 1], got {fresh_fraction!r}")
        self.fresh_fraction = float(fresh_fraction)
        self.backoff_level = 0
        """Safe entries in a row, each after a RUN shorter than ``backoff_reset_s``."""
        self.cfg = cfg
        self._timeouts = {
            "plc": cfg.plc_timeout_s,
            "can": cfg.can_timeout_s,
            "measurement": cfg.measurement_timeout_s,
        }
        self._last: dict[str, float | None] = {"plc": None, "can": None, "measurement": t0}
        self._ok = dict.fromkeys(CONDITIONS, True)
        self.state = SafetyState.SAFE
        self.since_s = t0
        self._ok_since: float | None = None
        self.entries = 0
        """How many times the SAFE state was entered from RUN."""
        self.ran = False
        """Whether the state has been RUN at all (``False``: still starting up)."""
        self.warm = False
        """A warm start (:meth:`warm_start`): the safe feed holds until the first RUN."""

    # ------------------------------------------------------------------ inputs
    def _note(self, source: str, now_s: float) -> None:
        t = check_finite("now_s", now_s)
        last = self._last[source]
        self._last[source] = t if last is None else max(last, t)

    def plc_answered(self, now_s: float) -> None:
        """The PLC answered a request at ``now_s``."""
        self._note("plc", now_s)

    def can_heard(self, now_s: float) -> None:
        """A frame from the amplifier (status or heartbeat) was received at ``now_s``."""
        self._note("can", now_s)

    def measurement_valid(self, now_s: float) -> None:
        """A valid measurement arrived at ``now_s``."""
        self._note("measurement", now_s)

    def measurement_not_expected(self, now_s: float) -> None:
        """No measurement is due (no board under the camera): the measurement timeout rests."""
        self._note("measurement", now_s)

    def warm_start(self, now_s: float) -> None:
        """The service resumes a remembered state on a machine that runs (a restart).

        Until the first RUN the safe action holds the feed the PLC has instead of ramping it
        down: the machine ran well before the service started and nothing has failed since.
        The first RUN needs every source heard and every condition held for
        :data:`WARM_START_CONFIRM_S` instead of ``recovery_s`` (each cycle of it cuts board
        without the offsets). Everything else of the start stays: the offsets stay zero and the
        amplifier disabled until RUN, and a failing source or condition (a PLC that does not
        answer, data that make no sense) keeps the service in SAFE; a machine that stops ends
        the warm start. Ignored once the service has run.
        """
        check_finite("now_s", now_s)
        if not self.ran:
            self.warm = True

    def machine_ok(self, ok: bool) -> None:
        """Whether the machine reports itself fit to run (no e-stop, spindle turning)."""
        self.set_ok("machine", ok)

    def set_ok(self, condition: str, ok: bool) -> None:
        """Whether ``condition`` (one of :data:`CONDITIONS`) holds now."""
        if condition not in self._ok:
            raise ValueError(f"condition must be one of {', '.join(CONDITIONS)}; got {condition!r}")
        self._ok[condition] = bool(ok)
        if condition == "machine" and not ok:
            self.warm = False  # a machine that stops is no running machine to hold

    # ------------------------------------------------------------------ state
    def missing(self, now_s: float, *, fraction: float = 1.0) -> tuple[str, ...]:
        """Sources gone and conditions failing at ``now_s``.

        A timed source is gone when not heard for longer than ``fraction`` of its timeout (never
        heard counts); ``fraction < 1`` is the stricter test of the recovery (hysteresis).
        """
        t = check_finite("now_s", now_s)
        out = []
        for src in SOURCES:
            if src in self._ok:
                if not self._ok[src]:
                    out.append(src)
                continue
            last = self._last[src]
            if last is None or t - last > self._timeouts[src] * fraction:
                out.append(src)
        return tuple(out)

    @property
    def recovery_required_s(self) -> float:
        """How long everything must hold before RUN now, s (the back-off)."""
        if self.warm:  # the first RUN of a warm start: nothing failed before
            return min(self.cfg.recovery_s, WARM_START_CONFIRM_S)
        n = max(self.backoff_level - 1, 0)
        factor = min(self.backoff_factor**n, self.backoff_max_factor)
        return self.cfg.recovery_s * factor

    def step(self, now_s: float) -> SafetyStatus:
        """Advance the state machine to ``now_s``.

        Returns
        -------
        SafetyStatus
            The state, the sources gone, whether it changed.
        """
        t = check_finite("now_s", now_s)
        gone = self.missing(t)
        changed = False
        if self.state is SafetyState.RUN:
            if t - self.since_s >= self.backoff_reset_s:
                self.backoff_level = 0  # a good period: the next entry starts afresh
            if gone:
                self.state, self.since_s, changed = SafetyState.SAFE, t, True
                self._ok_since = None
                self.entries += 1
                self.backoff_level += 1
        elif gone or self.missing(t, fraction=self.fresh_fraction):
            self._ok_since = None  # hysteresis: back only when clearly back
        else:
            if self._ok_since is None:
                self._ok_since = t
            if t - self._ok_since >= self.recovery_required_s - 1e-9:
                self.state, self.since_s, changed = SafetyState.RUN, t, True
                self._ok_since = None
                self.ran, self.warm = True, False
        return SafetyStatus(state=self.state, missing=gone, changed=changed, since_s=self.since_s)

    @property
    def safe(self) -> bool:
        """Whether the current state is ``SAFE``."""
        return self.state is SafetyState.SAFE

    # ------------------------------------------------------------------ safe actions
    def safe_feed(
        self, current_mm_s: float, *, dt_s: float, feed_min_mm_s: float, feed_max_mm_s: float
    ) -> float:
        """Feed setpoint to command in the safe state, one cycle of ``dt_s`` after ``current_mm_s``.

        ``hold`` keeps the current setpoint (clamped to the limits); ``ramp_down`` moves it toward
        ``safe_feed_mm_s`` (clamped to the limits) by at most ``ramp_mm_s2 * dt_s``, never
        increasing it unless it lies below the machine's minimum. A warm start
        (:meth:`warm_start`) holds until the first RUN whatever the configuration.

        Parameters
        ----------
        current_mm_s : float
            Setpoint now, mm/s.
        dt_s : float
            Time since the last safe setpoint, s (>= 0).
        feed_min_mm_s, feed_max_mm_s : float
            The machine's limits, mm/s.

        Returns
        -------
        float
            The setpoint, mm/s, inside ``[feed_min_mm_s, feed_max_mm_s]``.
        """
        cur = check_finite("current_mm_s", current_mm_s)
        dt = check_positive("dt_s", dt_s, allow_zero=True)
        lo = check_finite("feed_min_mm_s", feed_min_mm_s)
        hi = check_finite("feed_max_mm_s", feed_max_mm_s)
        if lo > hi:
            raise ValueError(f"feed_min_mm_s {lo} > feed_max_mm_s {hi}")
        cur_c = min(max(cur, lo), hi)
        if self.cfg.safe_state == "hold" or self.warm:
            return cur_c
        target = min(max(self.cfg.safe_feed_mm_s, lo), hi)
        if cur_c <= target:
            return cur_c
        return max(target, cur_c - self.cfg.ramp_mm_s2 * dt)

    @staticmethod
    def safe_offsets_um(knives: int) -> list[float]:
        """Piezo offsets in the safe state: zero for every knife."""
        return [0.0] * int(knives)


# ---------------------------------------------------------------------------------- amplifier
def _state_text(state: int) -> str:
    return f"state {state} ({AMP_STATES.get(state, 'unknown')})"


def amp_problem(*, state: int, fault: int, enable: bool) -> str | None:
    """What is wrong with one amplifier status given what the service commands (pure).

    Parameters
    ----------
    state : int
        The amplifier's state (0 disabled, 1 enabled and tracking, 2 ramping to zero, 3 fault).
    fault : int
        Its fault bits (:data:`AMP_FAULT_BITS`).
    enable : bool
        Whether the service commands enable.

    Returns
    -------
    str or None
        ``None`` when the status is what was commanded without any fault, else the problem
        (``"fault overcurrent, state 3 (fault)"``, ``"state 0 (disabled) while enable is
        commanded"``).
    """
    st, bits = int(state), int(fault)
    parts = []
    if bits:
        names = [AMP_FAULT_BITS.get(b, f"bit {b}") for b in range(8) if bits >> b & 1]
        parts.append("fault " + ", ".join(names))
    if st == STATE_FAULT or st not in AMP_STATES:
        parts.append(_state_text(st))
    elif enable and st != STATE_ENABLED:
        parts.append(f"{_state_text(st)} while enable is commanded")
    elif not enable and st != STATE_DISABLED:
        parts.append(f"{_state_text(st)} while disable is commanded")
    return ", ".join(parts) or None


class AmplifierMonitor:
    """Whether the piezo amplifier plays the offsets it is sent (pure; time passed in).

    The service tells it what it commands (:meth:`commanded`) and shows it every status
    (:meth:`observe`). A status received before the last change of the command is no verdict
    on that command and is ignored. A problem (:func:`amp_problem`) reported by every status for
    ``confirm_s`` is confirmed (:attr:`problem`); the first healthy status clears it.

    Parameters
    ----------
    confirm_s : float
        Confirmation time, s (>= 0).
    refusal_confirm_s : float
        Confirmation time of a stroke-limit bit alone while the amplifier tracks, s (>= 0).
    """

    def __init__(
        self, *, confirm_s: float = AMP_CONFIRM_S, refusal_confirm_s: float = AMP_REFUSAL_CONFIRM_S
    ) -> None:
        self.confirm_s = check_positive("confirm_s", confirm_s, allow_zero=True)
        self.refusal_confirm_s = check_positive(
            "refusal_confirm_s", refusal_confirm_s, allow_zero=True
        )
        self.enable = False
        self._since = -math.inf  # when the command last changed
        self._bad_since: float | None = None
        self.problem: str | None = None
        """The confirmed problem, or ``None``."""
        self.untracked_s: float | None = None
        """The last time the offsets were known not to be played: disable commanded, a status
        saying not tracking, or an enable not yet confirmed by a status."""

    def commanded(self, enable: bool, *, now_s: float) -> None:
        """The service commands ``enable`` (from ``now_s``)."""
        en = bool(enable)
        if en != self.enable:
            self.enable = en
            self._since = check_finite("now_s", now_s)
            self._bad_since = None

    def observe(self, status: Any, *, now_s: float) -> str | None:
        """Judge the last status (``state``, ``fault``, ``t_s`` received) at ``now_s``.

        Returns
        -------
        str or None
            The confirmed problem (also :attr:`problem`), ``None`` when healthy or unconfirmed.
        """
        t = check_finite("now_s", now_s)
        fresh = status is not None and float(status.t_s) > self._since
        if not self.enable or not fresh:
            self.untracked_s = t
        if not fresh:
            return self.problem
        found = amp_problem(state=status.state, fault=status.fault, enable=self.enable)
        if found is None:
            self._bad_since = None
            self.problem = None
            return None
        self.untracked_s = t
        if self._bad_since is None:
            self._bad_since = float(status.t_s)
        refusal = (int(status.fault) == FAULT_STROKE_LIMIT and int(status.state) == STATE_ENABLED
                   and self.enable)
        confirm = max(self.confirm_s, self.refusal_confirm_s) if refusal else self.confirm_s
        if t - self._bad_since >= confirm - 1e-9:
            self.problem = found
        return self.problem
