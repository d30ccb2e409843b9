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
* Recovery is automatic: once every source is back and every condition has held for
  ``recovery_s`` (confirmation time), the state returns to ``RUN``.

The supervisor starts in ``SAFE`` (nothing heard yet). Time is always passed in (``now_s``,
seconds on any monotonic clock); the supervisor never reads a clock.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from config.machine import SafetyConfig
from planer.checks import check_finite, check_positive

TIMED_SOURCES = ("plc", "can", "measurement")
"""Sources that must be heard within their timeout."""
CONDITIONS = ("machine", "plc_data", "log", "service")
"""Conditions that must hold: the machine fit to run, the PLC's registers sensible, the quality
log writable, the service's own code free of unexpected errors."""
SOURCES = TIMED_SOURCES + CONDITIONS
"""What the supervisor watches, in the order reasons are reported."""


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
    """

    def __init__(self, cfg: SafetyConfig, *, now_s: float) -> None:
        t0 = check_finite("now_s", now_s)
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

    def machine_ok(self, ok: bool) -> None:
        """Whether the machine reports itself fit to run (no e-stop, spindle turning)."""
        self.set_ok("machine", ok)

    def set_ok(self, condition: str, ok: bool) -> None:
        """Whether ``condition`` (one of :data:`CONDITIONS`) holds now."""
        if condition not in self._ok:
            raise ValueError(f"condition must be one of {', '.join(CONDITIONS)}; got {condition!r}")
        self._ok[condition] = bool(ok)

    def last_heard(self, source: str) -> float | None:
        """Time ``source`` (``"plc"``, ``"can"``, ``"measurement"``) was last good."""
        return self._last[source]

    # ------------------------------------------------------------------ state
    def missing(self, now_s: float) -> tuple[str, ...]:
        """Sources gone for longer than their timeout at ``now_s`` (never heard counts)."""
        t = check_finite("now_s", now_s)
        out = []
        for src in SOURCES:
            if src in self._ok:
                if not self._ok[src]:
                    out.append(src)
                continue
            last = self._last[src]
            if last is None or t - last > self._timeouts[src]:
                out.append(src)
        return tuple(out)

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
            if gone:
                self.state, self.since_s, changed = SafetyState.SAFE, t, True
                self._ok_since = None
                self.entries += 1
        elif gone:
            self._ok_since = None
        else:
            if self._ok_since is None:
                self._ok_since = t
            if t - self._ok_since >= self.cfg.recovery_s:
                self.state, self.since_s, changed = SafetyState.RUN, t, True
                self._ok_since = None
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
        increasing it unless it lies below the machine's minimum.

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
        if self.cfg.safe_state == "hold":
            return cur_c
        target = min(max(self.cfg.safe_feed_mm_s, lo), hi)
        if cur_c <= target:
            return cur_c
        return max(target, cur_c - self.cfg.ramp_mm_s2 * dt)

    @staticmethod
    def safe_offsets_um(knives: int) -> list[float]:
        """Piezo offsets in the safe state: zero for every knife."""
        return [0.0] * int(knives)
