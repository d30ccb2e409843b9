"""The piezo amplifier's CAN frames (``config/piezo.dbc``): a pure, sans-I/O codec over cantools.

Frames (standard 11-bit ids; see ``docs/piezo_can.md``):

==================  =====  =======  ===========================================================
message             id     sender   contents
==================  =====  =======  ===========================================================
PIEZO_COMMAND       0x200  SERVICE  enable, number of knives, the service's alive counter
PIEZO_OFFSETS_0_3   0x210  SERVICE  per-knife offsets of knives 0-3, 0.001 um per bit, signed
PIEZO_OFFSETS_4_7   0x211  SERVICE  knives 4-7
PIEZO_STATUS        0x280  AMP      displacement, temperature, fault bits, state, alive counter
PIEZO_LIMITS        0x281  AMP      stroke, accepted offset range, slew limit, setpoint timeout
AMP_HEARTBEAT       0x702  AMP      NMT state (5 operational)
==================  =====  =======  ===========================================================

Values are packed by cantools from the DBC file (scaling, rounding to the nearest raw step,
range checks); this module adds errors that name the knife or signal and never imports python-can.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cantools

from config.loading import default_path, naming_file
from core.errors import ConfigError

COMMAND = "PIEZO_COMMAND"
OFFSETS = ("PIEZO_OFFSETS_0_3", "PIEZO_OFFSETS_4_7")
STATUS = "PIEZO_STATUS"
HEARTBEAT = "AMP_HEARTBEAT"
LIMITS = "PIEZO_LIMITS"

MAX_KNIVES = 8
KNIVES_PER_FRAME = 4

STATUS_PERIOD_S = 0.010
"""The amplifier sends PIEZO_STATUS every 10 ms."""
HEARTBEAT_PERIOD_S = 0.100
"""The amplifier sends AMP_HEARTBEAT every 100 ms."""
LIMITS_PERIOD_S = HEARTBEAT_PERIOD_S
"""The amplifier sends PIEZO_LIMITS with every heartbeat (the first at start)."""
COMMAND_PERIOD_MAX_S = 0.050
"""The service sends PIEZO_COMMAND at least every 50 ms."""

STATE_DISABLED, STATE_ENABLED, STATE_RAMPING, STATE_FAULT = 0, 1, 2, 3
FAULT_OVER_TEMPERATURE = 1 << 0
FAULT_STROKE_LIMIT = 1 << 1
FAULT_SETPOINT_TIMEOUT = 1 << 2
FAULT_OVERCURRENT = 1 << 3
NMT_OPERATIONAL, NMT_PRE_OPERATIONAL, NMT_STOPPED = 5, 127, 4

Frame = tuple[int, bytes]
"""A CAN frame as ``(arbitration_id, data)``."""

_REQUIRED = {
    COMMAND: ("enable", "knives", "alive_counter"),
    OFFSETS[0]: tuple(f"offset_knife_{k}" for k in range(4)),
    OFFSETS[1]: tuple(f"offset_knife_{k}" for k in range(4, 8)),
    STATUS: ("displacement_um", "temperature_c", "fault", "state", "alive_counter"),
    HEARTBEAT: ("nmt_state",),
    LIMITS: (
        "stroke_um", "offset_min_um", "offset_max_um", "slew_max_um_ms", "setpoint_timeout_ms",
    ),
}


def _check_scale(message: str, sig: Any) -> None:
    """A signal's scale and offset must be finite, the scale non-zero (else nothing decodes)."""
    scale, offset = float(sig.scale), float(sig.offset)
    if not (math.isfinite(scale) and scale != 0.0 and math.isfinite(offset)):
        raise ConfigError(
            f"piezo DBC: {message}.{sig.name}: scale {sig.scale} and offset {sig.offset} must "
            "be finite, the scale non-zero"
        )
    if sig.length < 1:
        raise ConfigError(f"piezo DBC: {message}.{sig.name}: length must be >= 1 bit")


def _check_range(message: str, sig: Any) -> None:
    """A signal the codec encodes needs a ``[min|max]`` that its raw bit field can carry."""
    _check_scale(message, sig)
    where = f"piezo DBC: {message}.{sig.name}"
    if sig.minimum is None or sig.maximum is None:
        raise ConfigError(f"{where}: needs a range [min|max]")
    lo, hi = float(sig.minimum), float(sig.maximum)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ConfigError(
            f"{where}: range [{sig.minimum}|{sig.maximum}] must be finite with min <= max"
        )
    n = int(sig.length)
    raw_lo, raw_hi = (-(2 ** (n - 1)), 2 ** (n - 1) - 1) if sig.is_signed else (0, 2**n - 1)
    for x in (lo, hi):
        raw = round((x - float(sig.offset)) / float(sig.scale))
        if not raw_lo <= raw <= raw_hi:
            raise ConfigError(
                f"{where}: range [{sig.minimum}|{sig.maximum}] does not fit its {n}-bit "
                f"{'signed' if sig.is_signed else 'unsigned'} field"
            )


class PiezoCodec:
    """Encoder and decoder of the amplifier's frames, built once from the DBC file.

    Parameters
    ----------
    db : cantools.database.can.Database
        The loaded DBC database; must define the six messages and their signals.
    """

    def __init__(self, db: Any) -> None:
        self._db = db
        self._msgs = {}
        for name, signals in _REQUIRED.items():
            try:
                msg = db.get_message_by_name(name)
            except KeyError:
                raise ConfigError(f"piezo DBC: message {name} missing") from None
            have = {s.name for s in msg.signals}
            for sig in signals:
                if sig not in have:
                    raise ConfigError(f"piezo DBC: message {name} lacks signal {sig}")
            for sig in msg.signals:
                _check_range(name, sig)
            self._msgs[name] = msg
        for msg in db.messages:
            for sig in msg.signals:
                _check_scale(msg.name, sig)
        self._by_id = {m.frame_id: m for m in db.messages}
        self.ids: dict[str, int] = {name: m.frame_id for name, m in self._msgs.items()}
        """Arbitration id of each message, by name."""
        self.offset_ids: tuple[int, int] = (self.ids[OFFSETS[0]], self.ids[OFFSETS[1]])
        self.command_id: int = self.ids[COMMAND]
        self.status_id: int = self.ids[STATUS]
        self.heartbeat_id: int = self.ids[HEARTBEAT]
        self.limits_id: int = self.ids[LIMITS]

    @classmethod
    def load(cls, path: str | Path | None = None) -> PiezoCodec:
        """Load the DBC file (default ``config/piezo.dbc``); problems raise ``ConfigError``."""
        p = Path(default_path("piezo.dbc") if path is None else path)
        try:
            db = cantools.database.load_file(str(p), database_format="dbc", strict=True)
        except FileNotFoundError:
            raise ConfigError(f"DBC file not found: {p}") from None
        except OSError as exc:  # a folder, no permission, an I/O error
            raise ConfigError(f"cannot read DBC file {p}: {exc.strerror or exc}") from None
        except (cantools.database.Error, UnicodeDecodeError) as exc:
            # cantools' parse and strict-check errors (UnsupportedDatabaseFormatError wraps the
            # DBC parser's message); text it cannot decode
            raise ConfigError(f"{p}: not a valid DBC file: {exc}") from None
        with naming_file(p):  # a message or signal missing: name the file too
            return cls(db)

    def signal_range(self, message: str, signal: str) -> tuple[float, float]:
        """Physical ``(minimum, maximum)`` of a signal as the DBC file states it."""
        sig = self._msgs[message].get_signal_by_name(signal)
        return float(sig.minimum), float(sig.maximum)

    # ------------------------------------------------------------------ encoding
    def _encode(self, name: str, values: dict[str, float | int]) -> Frame:
        msg = self._msgs[name]
        for sig_name, v in values.items():
            sig = msg.get_signal_by_name(sig_name)
            if isinstance(v, bool):
                v = int(v)
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{name}.{sig_name} must be a number, got {v!r}") from None
            if not math.isfinite(fv):
                raise ValueError(f"{name}.{sig_name} must be finite, got {v!r}")
            if sig.scale == 1 and sig.offset == 0 and not fv.is_integer():
                raise ValueError(f"{name}.{sig_name} must be an integer, got {v!r}")
            tol = abs(sig.scale) * 0.5
            if not sig.minimum - tol <= fv <= sig.maximum + tol:
                raise ValueError(
                    f"{name}.{sig_name} = {v!r} outside [{sig.minimum}, {sig.maximum}]"
                )
            # within half a step of the range: the nearest step is the range's end (rounding
            # it on the wire would step past the raw field: 32.7675 um -> 32768 > 32767)
            fv = min(max(fv, float(sig.minimum)), float(sig.maximum))
            values[sig_name] = int(fv) if sig.scale == 1 and sig.offset == 0 else fv
        data = msg.encode(values, scaling=True, strict=False)
        return msg.frame_id, bytes(data)

    def encode_command(self, *, enable: bool, knives: int, alive_counter: int) -> Frame:
        """PIEZO_COMMAND: enable, number of knives (1..8), alive counter (0..255).

        Returns
        -------
        (arbitration_id, data) : tuple of int and bytes (4 bytes)
        """
        return self._encode(
            COMMAND,
            {"enable": int(bool(enable)), "knives": knives, "alive_counter": alive_counter},
        )

    def encode_offsets(self, offsets_um: Sequence[float]) -> list[Frame]:
        """PIEZO_OFFSETS frames carrying per-knife offsets.

        Parameters
        ----------
        offsets_um : sequence of float, length 1..8
            Offset of each knife, um; positive moves the cutterhead up while that knife cuts.
            Rounded to the nearest 0.001 um.

        Returns
        -------
        list of (arbitration_id, data)
            One frame for up to 4 knives, two for 5..8 (unused knives of a frame are 0).

        Raises
        ------
        ValueError
            Wrong number of knives, or an offset outside the signal's range (naming the knife).
        """
        offs = list(offsets_um)
        if not 1 <= len(offs) <= MAX_KNIVES:
            raise ValueError(f"offsets_um must have 1..{MAX_KNIVES} values, got {len(offs)}")
        frames = []
        for f, name in enumerate(OFFSETS):
            part = offs[f * KNIVES_PER_FRAME : (f + 1) * KNIVES_PER_FRAME]
            if not part:
                break
            values: dict[str, float | int] = {}
            for j in range(KNIVES_PER_FRAME):
                k = f * KNIVES_PER_FRAME + j
                v = part[j] if j < len(part) else 0.0
                lo, hi = self.signal_range(name, f"offset_knife_{k}")
                try:
                    fv = float(v)
                except (TypeError, ValueError):
                    raise ValueError(f"offsets_um[{k}] (knife {k}) must be a number") from None
                if not math.isfinite(fv) or not lo - 0.0005 <= fv <= hi + 0.0005:
                    raise ValueError(
                        f"offsets_um[{k}] (knife {k}) = {v!r} µm outside [{lo}, {hi}] µm"
                    )
                values[f"offset_knife_{k}"] = fv
            frames.append(self._encode(name, values))
        return frames

    def encode_status(
        self,
        *,
        displacement_um: float,
        temperature_c: float,
        fault: int,
        state: int,
        alive_counter: int,
    ) -> Frame:
        """PIEZO_STATUS: displacement (um), temperature (degC), fault bits, state, alive counter.

        Displacement beyond the signal range is saturated to it (a status report, not a command).
        """
        lo, hi = self.signal_range(STATUS, "displacement_um")
        d = float(displacement_um)
        d = min(max(d, lo), hi) if math.isfinite(d) else d  # NaN is refused by _encode
        return self._encode(
            STATUS,
            {
                "displacement_um": d,
                "temperature_c": temperature_c,
                "fault": fault,
                "state": state,
                "alive_counter": alive_counter,
            },
        )

    def encode_heartbeat(self, *, nmt_state: int = NMT_OPERATIONAL) -> Frame:
        """AMP_HEARTBEAT with the NMT state (5 operational, 127 pre-operational, 4 stopped)."""
        return self._encode(HEARTBEAT, {"nmt_state": nmt_state})

    def encode_limits(
        self,
        *,
        stroke_um: float,
        offset_min_um: float,
        offset_max_um: float,
        slew_max_um_ms: float = 0,
        setpoint_timeout_ms: float,
    ) -> Frame:
        """PIEZO_LIMITS: the limits the amplifier enforces.

        Parameters
        ----------
        stroke_um : float
            The actuator's stroke, um (0..65.535, 1 nm per bit).
        offset_min_um, offset_max_um : float
            The offsets it accepts in a table, um (a table with one outside is refused).
        slew_max_um_ms : float
            Largest output slew rate, um/ms (0..255, whole numbers; 0: not limited).
        setpoint_timeout_ms : float
            Its setpoint timeout, ms (0..510, sent in steps of 2 ms: rounded to the nearest).

        Returns
        -------
        (arbitration_id, data) : tuple of int and bytes (8 bytes)

        Raises
        ------
        ValueError
            A value outside its signal's range, not a number, or a slew that is not whole.
        """
        try:
            timeout = float(setpoint_timeout_ms)
        except (TypeError, ValueError):
            raise ValueError(
                f"{LIMITS}.setpoint_timeout_ms must be a number, got {setpoint_timeout_ms!r}"
            ) from None
        if math.isfinite(timeout):
            timeout = 2.0 * round(timeout / 2.0)  # the wire's step
        return self._encode(
            LIMITS,
            {
                "stroke_um": stroke_um,
                "offset_min_um": offset_min_um,
                "offset_max_um": offset_max_um,
                "slew_max_um_ms": slew_max_um_ms,
                "setpoint_timeout_ms": timeout,
            },
        )

    # ------------------------------------------------------------------ decoding
    def decode(self, arbitration_id: int, data: bytes) -> tuple[str, dict[str, float | int]]:
        """Decode a frame of the DBC file.

        Returns
        -------
        (message_name, signals) : tuple of str and dict
            Scaled physical values; enumerations as integers (``state`` 0..3).

        Raises
        ------
        ValueError
            An id that is not an integer, an unknown id, data that is not bytes, or data shorter
            than the message; the message names the id or the message. Never another type.
        """
        try:
            if isinstance(arbitration_id, bool):
                raise TypeError("bool")
            fid = operator.index(arbitration_id)  # int or numpy integer; not float or str
        except TypeError:
            raise ValueError(
                f"CAN arbitration id must be an integer, got {arbitration_id!r}"
            ) from None
        msg = self._by_id.get(fid)
        if msg is None:
            raise ValueError(f"unknown CAN arbitration id 0x{fid:X}")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise ValueError(f"{msg.name}: data must be bytes, got {type(data).__name__}")
        if len(data) < msg.length:
            raise ValueError(f"{msg.name}: {len(data)} data bytes, expected {msg.length}")
        try:
            vals = msg.decode(bytes(data[: msg.length]), decode_choices=False, scaling=True)
        except cantools.database.DecodeError as exc:  # e.g. a multiplexer value the DBC lacks
            raise ValueError(f"{msg.name}: cannot decode: {exc}") from None
        out: dict[str, float | int] = {}
        for sig in msg.signals:
            v = vals[sig.name]
            if sig.scale == 1 and sig.offset == 0:
                out[sig.name] = int(v)
            else:
                # snap to the resolution so 1.234 decodes as 1.234, not 1.2340000000000002
                digits = max(0, -math.floor(math.log10(abs(sig.scale))))
                out[sig.name] = round(float(v), digits)
        return msg.name, out

    def offsets_from(self, name: str, signals: dict[str, float | int]) -> dict[int, float]:
        """Knife index to offset (um) of a decoded PIEZO_OFFSETS message."""
        if name not in OFFSETS:
            raise ValueError(f"{name} is not a PIEZO_OFFSETS message")
        return {int(k.rsplit("_", 1)[1]): float(v) for k, v in signals.items()}
