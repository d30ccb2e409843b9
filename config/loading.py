"""Reading TOML files and typed, checked values out of them (errors name the key)."""

from __future__ import annotations

import contextlib
import json
import math
import re
from collections.abc import Iterator, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

from core.errors import ConfigError

_MISSING = object()
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def default_path(name: str) -> Path:
    """Path of a configuration file shipped in the ``config`` package (e.g. ``"sim.toml"``)."""
    return Path(str(resources.files("config").joinpath(name)))


def load_toml(path: str | Path) -> dict[str, Any]:
    """Load a TOML file; a missing or malformed file raises ``ConfigError`` naming it."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    except IsADirectoryError:
        raise ConfigError(f"config path is a directory, not a file: {p}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # TOML is UTF-8 text
        raise ConfigError(
            f"{p}: not valid TOML: not UTF-8 text (byte {exc.start}: {exc.reason})"
        ) from None
    except OSError as exc:
        raise ConfigError(f"cannot read config file {p}: {exc.strerror}") from None


@contextlib.contextmanager
def naming_file(path: str | Path | None) -> Iterator[None]:
    """Prefix every ``ConfigError`` raised inside the block with the file it came from.

    Parameters
    ----------
    path : str, Path or None
        The configuration file; ``None`` (built in code, no file) leaves errors as they are.
        A message that already starts with the file name is not prefixed twice.

    Examples
    --------
    >>> with naming_file(cfg.source):  # doctest: +SKIP
    ...     FeedLoopConfig.from_mapping(cfg.feed_loop)  # "x.toml: unknown key feed_loop.gian"
    """
    try:
        yield
    except ConfigError as exc:
        text = str(exc)
        if path is None or text.startswith(f"{path}:"):
            raise
        raise ConfigError(f"{path}: {text}") from None


class Section:
    """Typed access to one table of a TOML document; every error names ``prefix.key``.

    Parameters
    ----------
    data : mapping
        The table's contents.
    prefix : str
        Dotted name of the table, used in error messages (``"camera"``).
    """

    def __init__(self, data: Mapping[str, Any] | None, prefix: str) -> None:
        if data is not None and not isinstance(data, Mapping):
            raise ConfigError(f"[{prefix}] must be a table, got {type(data).__name__}")
        self._data = dict(data or {})
        self._prefix = prefix
        self._used: set[str] = set()

    @property
    def prefix(self) -> str:
        """Dotted name of this table (``"camera"``, ``"heads[2]"``; ``""`` for the document)."""
        return self._prefix

    def key(self, name: str) -> str:
        """Dotted name of ``name`` in this section (quoted as TOML does when not a bare key)."""
        text = name if _BARE_KEY.fullmatch(str(name)) else json.dumps(str(name))
        return f"{self._prefix}.{text}" if self._prefix else text

    def has(self, name: str) -> bool:
        """Whether the key is present."""
        return name in self._data

    def raw(self, name: str, default: Any = _MISSING) -> Any:
        """The raw value; missing without default raises ``ConfigError``."""
        self._used.add(name)
        if name not in self._data:
            if default is _MISSING:
                raise ConfigError(f"missing key {self.key(name)}")
            return default
        return self._data[name]

    def section(self, name: str, *, required: bool = True) -> Section:
        """A sub-table as a ``Section``."""
        val = self.raw(name, None if not required else _MISSING)
        return Section(val, self.key(name))

    def number(
        self,
        name: str,
        default: Any = _MISSING,
        *,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
    ) -> float:
        """A finite float within ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``)."""
        val = self.raw(name, default)
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise ConfigError(f"{self.key(name)} must be a number, got {val!r}")
        v = float(val)
        if not math.isfinite(v):
            raise ConfigError(f"{self.key(name)} must be finite, got {val!r}")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            op = ">" if lo_open else ">="
            raise ConfigError(f"{self.key(name)} must be {op} {lo}, got {val!r}")
        if hi is not None and v > hi:
            raise ConfigError(f"{self.key(name)} must be <= {hi}, got {val!r}")
        return v

    def integer(
        self, name: str, default: Any = _MISSING, *, lo: int | None = None, hi: int | None = None
    ) -> int:
        """An integer within ``[lo, hi]``."""
        val = self.raw(name, default)
        if isinstance(val, bool) or not isinstance(val, int):
            raise ConfigError(f"{self.key(name)} must be an integer, got {val!r}")
        if lo is not None and val < lo:
            raise ConfigError(f"{self.key(name)} must be >= {lo}, got {val!r}")
        if hi is not None and val > hi:
            raise ConfigError(f"{self.key(name)} must be <= {hi}, got {val!r}")
        return val

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        """A boolean."""
        val = self.raw(name, default)
        if not isinstance(val, bool):
            raise ConfigError(f"{self.key(name)} must be true or false, got {val!r}")
        return val

    def string(self, name: str, default: Any = _MISSING, *, choices: tuple[str, ...] = ()) -> str:
        """A string, optionally one of ``choices``."""
        val = self.raw(name, default)
        if not isinstance(val, str):
            raise ConfigError(f"{self.key(name)} must be a string, got {val!r}")
        if choices and val not in choices:
            raise ConfigError(f"{self.key(name)} must be one of {', '.join(choices)}; got {val!r}")
        return val

    def numbers(
        self, name: str, default: Any = _MISSING, *, length: int | None = None
    ) -> tuple[float, ...]:
        """A list of finite numbers, optionally of a fixed length."""
        val = self.raw(name, default)
        if not isinstance(val, (list, tuple)):
            raise ConfigError(f"{self.key(name)} must be a list of numbers, got {val!r}")
        out = []
        for i, x in enumerate(val):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise ConfigError(f"{self.key(name)}[{i}] must be a finite number, got {x!r}")
            out.append(float(x))
        if length is not None and len(out) != length:
            raise ConfigError(f"{self.key(name)} must have {length} values, got {len(out)}")
        return tuple(out)

    def reject_unknown(self) -> None:
        """Raise ``ConfigError`` for keys that were never read (typos)."""
        unknown = sorted(set(self._data) - self._used)
        if unknown:
            raise ConfigError(f"unknown key {self.key(unknown[0])}")


# ------------------------------------------------------------------ tables shared by the configs
LOOPBACK_HOST = "127.0.0.1"
"""Default Modbus host: the simulator's PLC listens here and the service connects here."""
MODBUS_PORT = 5020
"""Default Modbus TCP port of the simulator's PLC and of the service's client (502 needs root)."""
SPOOL_DIR = "runs/spool"
"""Default frame spool folder: the simulator's camera writes it, the service reads it."""

CAN_INTERFACES = ("virtual", "udp_multicast", "remote", "socketcan")
"""python-can interfaces the project uses (in-process, namespace multicast, remote, the machine)."""


def can_bus_keys(s: Section, *, interface: str, channel: str) -> tuple[str, str, dict[str, Any]]:
    """The python-can bus of a ``[can]`` table: ``interface``, ``channel``, ``[can.options]``.

    Parameters
    ----------
    s : Section
        The ``[can]`` table (other keys are left to the caller).
    interface, channel : str
        Defaults.

    Returns
    -------
    (interface, channel, options)
        ``options`` are extra keyword arguments for ``can.Bus``.
    """
    iface = s.string("interface", interface, choices=CAN_INTERFACES)
    chan = s.string("channel", channel)
    if not chan:
        raise ConfigError(f"{s.key('channel')} must not be empty")
    options = s.raw("options", {})
    if not isinstance(options, Mapping):
        raise ConfigError(f"{s.key('options')} must be a table, got {options!r}")
    return iface, chan, dict(options)


def modbus_endpoint(
    s: Section, *, host: str, port: int, unit_id: int, port_lo: int = 1, unit_hi: int = 255
) -> tuple[str, int, int]:
    """``host``, ``port`` and ``unit_id`` of a Modbus TCP table (errors name the key).

    ``port_lo = 0`` lets a server pick a free port; ``unit_hi`` bounds the unit id.
    """
    h = s.string("host", host)
    if not h.strip():
        raise ConfigError(f"{s.key('host')} must not be empty")
    return (
        h,
        s.integer("port", port, lo=port_lo, hi=65535),
        s.integer("unit_id", unit_id, lo=0, hi=unit_hi),
    )


# ------------------------------------------------------------ partial files: over the shipped one
def merged(below: Mapping[str, Any], above: Mapping[str, Any]) -> dict[str, Any]:
    """``above`` deep-merged over ``below``: tables merge key by key, any other value replaces.

    Lists (``runout_um``, ``[[faults]]``) replace as a whole. Neither argument is changed.
    """
    out = dict(below)
    for key, value in above.items():
        under = out.get(key)
        if isinstance(value, Mapping) and isinstance(under, Mapping):
            out[key] = merged(under, value)
        else:
            out[key] = value
    return out


def over_shipped(data: Mapping[str, Any], kind: str, *, aliases: Mapping[str, str] | None = None,
                 _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """A configuration document deep-merged over the shipped file of its kind.

    The one rule for every configuration file: a file gives only what it changes and keeps
    every other value of the shipped file of its kind (``config/sim.toml``,
    ``config/machine.toml``, ``config/rig.toml``). A top-level ``base = "sim_drift.toml"``
    starts from another shipped file instead (itself over the shipped file of the kind).

    Parameters
    ----------
    data : mapping
        The parsed file.
    kind : str
        The shipped file of its kind, e.g. ``"sim.toml"``.
    aliases : mapping, optional
        Older key names: ``{"camera.optics.noise": "read_noise_dn"}``; a file giving the older
        name replaces the shipped file's newer one in the same table.

    Returns
    -------
    dict
        The merged document, without ``base``.

    Raises
    ------
    ConfigError
        ``base`` is not a file name of the shipped config folder, that file is missing or bad,
        or the bases form a circle; the message names the key.
    """
    name = data.get("base", kind)
    if not isinstance(name, str) or not name.endswith(".toml") or Path(name).name != name:
        raise ConfigError(f"base must name a file of the shipped config folder "
                          f"(e.g. \"{kind}\"), got {name!r}")
    if name in _seen:
        raise ConfigError(f"base = {name!r} is circular ({' -> '.join((*_seen, name))})")
    path = default_path(name)
    if not path.is_file():
        raise ConfigError(f"base = {name!r}: no such file in the shipped config folder "
                          f"{path.parent}")
    try:
        below = load_toml(path)
        if name != kind or "base" in below:  # the shipped file of the kind is the ground
            below = over_shipped(below, kind, aliases=aliases, _seen=(*_seen, name))
    except ConfigError as exc:
        raise ConfigError(f"base = {name!r}: {exc}") from None
    for old, new in (aliases or {}).items():
        *table, key = old.split(".")
        mine, ground = _table(data, table), _table(below, table)
        if key in mine and new not in mine and new in ground:
            below = merged(below, {})  # a copy down to the table, then without the newer name
            _table(below, table, copy=True).pop(new)
    return merged(below, {k: v for k, v in data.items() if k != "base"})


def _table(doc: Mapping[str, Any], path: list[str], *, copy: bool = False) -> Any:
    """The table at ``path`` of ``doc`` (``{}`` when missing); ``copy``: made a fresh dict."""
    node: Any = doc
    for key in path:
        child = node.get(key, {}) if isinstance(node, Mapping) else {}
        if copy:
            child = dict(child)
            node[key] = child
        node = child
    return node if isinstance(node, Mapping) else {}


def load_over_shipped(path: str | Path | None, kind: str) -> tuple[Path, dict[str, Any]]:
    """Load a configuration file over the shipped one of its kind (:func:`over_shipped`).

    Parameters
    ----------
    path : str, Path or None
        The file (``None``: the shipped file of the kind itself).
    kind : str
        The shipped file of its kind, e.g. ``"machine.toml"``.

    Returns
    -------
    (Path, dict)
        The file read and the merged document. Errors name the file.
    """
    p = default_path(kind) if path is None else Path(path)
    data = load_toml(p)
    with naming_file(p):
        return p, over_shipped(data, kind)
