"""HIL scenarios: what to run (``config/hil.toml``) and the simulator/service configs for it."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from config.faults import Fault, parse_faults
from config.loading import Section, default_path, load_over_shipped, load_toml, naming_file
from config.machine import MachineConfig, load_machine
from core.errors import ConfigError

FINAL_MEASUREMENTS = 5
"""The ``final`` true values average the last this-many measurements."""
UNIFORMITY_MAX_CV = 0.05
PITCH_TOL = 0.02
CONVERGE_WITHIN_MM = 3000.0

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------------- scenario
FaultEvent = Fault
"""One injected fault of a scenario: ``FaultEvent(kind, at_s, params)`` (a ``Fault``)."""


@dataclass(frozen=True)
class Scenario:
    """A HIL scenario (``config/hil.toml``).

    Attributes
    ----------
    name : str
        Scenario name.
    distance_m : float
        Board travel to run, m.
    seed : int
        Simulator seed.
    runout_um : tuple of float or None
        Knife runouts (override the simulator's), um.
    initial_feed_mm_s : float or None
        Feed the simulated machine starts with, mm/s.
    target_pitch_mm : float or None
        Target pitch (overrides the quality class of ``machine.toml``), mm.
    sim_config, machine_config : Path or None
        Simulator and service configuration files (``None``: the shipped ones).
    max_sim_s : float
        Time limit, machine seconds.
    time_scale : float
        Cross-process runs: simulated seconds per wall second.
    faults : tuple of FaultEvent
        Faults to inject.
    amp_stroke_um : float or None
        Stroke of the simulated piezo amplifier (overrides ``sim.toml``'s ``[piezo]
        stroke_um``; the amplifier reports it over CAN), um.
    stroke_um : float or None
        The service's stroke (overrides ``machine.toml``'s ``[piezo] stroke_um``), um; with
        ``amp_stroke_um`` different, the two disagree (the stroke-mismatch scenario).
    final_cv_max : float
        The true CV the run must end at or below (and settle to) to pass: the default
        :data:`UNIFORMITY_MAX_CV`; larger for a plant whose best reachable CV is above it (a
        stroke too small for its runout: ``planer/sweep/optimum.py`` computes that CV).
    defects : bool or None
        The service looks for planing defects on every pair (overrides ``machine.toml``'s
        ``[quality] defects``).
    """

    name: str = "default"
    distance_m: float = 5.0
    seed: int = 0
    runout_um: tuple[float, ...] | None = None
    initial_feed_mm_s: float | None = None
    target_pitch_mm: float | None = None
    sim_config: Path | None = None
    machine_config: Path | None = None
    max_sim_s: float = 60.0
    time_scale: float = 1.0
    faults: tuple[FaultEvent, ...] = ()
    amp_stroke_um: float | None = None
    stroke_um: float | None = None
    final_cv_max: float = UNIFORMITY_MAX_CV
    defects: bool | None = None


def _fault_list(raw: Any, key: str) -> tuple[FaultEvent, ...]:
    """A scenario's ``faults`` (``at_s`` defaults to 0: the start of the run)."""
    return parse_faults(raw, key, default_at_s=0.0)


def _config_file(key: str, value: str, base_dir: Path | None) -> Path:
    """The configuration file ``value`` names (relative to ``base_dir``); it must exist."""
    given = Path(value).expanduser()
    folder = None if given.is_absolute() else (base_dir if base_dir is not None else Path.cwd())
    path = given if folder is None else folder / given
    if not path.is_file():
        where = ("" if folder is None else
                 f" (relative paths are resolved from the scenario file's folder {folder})"
                 if base_dir is not None else
                 f" (relative paths are resolved from the working folder {folder})")
        what = "is a folder, not a file" if path.is_dir() else "no such file"
        raise ConfigError(f"{key} = {value!r}: {what}: {path}{where}")
    return path


def scenario_from_table(
    name: str, table: Mapping[str, Any], base: Scenario, *, base_dir: Path | None = None
) -> Scenario:
    """A scenario from one TOML table, starting from ``base`` (errors name ``name.key``).

    ``sim_config`` and ``machine_config`` given relative are resolved from ``base_dir`` (the
    scenario file's folder; default the working folder) and must exist.
    """
    s = Section(table, name)
    s.raw("base", None)
    kw: dict[str, Any] = {"name": name}
    if s.has("distance_m"):
        kw["distance_m"] = s.number("distance_m", lo=0.0, lo_open=True, hi=1000.0)
    if s.has("seed"):
        kw["seed"] = s.integer("seed", lo=0)
    if s.has("runout_um"):
        kw["runout_um"] = s.numbers("runout_um")
    if s.has("initial_feed_mm_s"):
        kw["initial_feed_mm_s"] = s.number("initial_feed_mm_s", lo=0.0, lo_open=True)
    if s.has("target_pitch_mm"):
        kw["target_pitch_mm"] = s.number("target_pitch_mm", lo=0.0, lo_open=True)
    for key in ("sim_config", "machine_config"):
        if s.has(key):
            v = s.string(key)
            kw[key] = _config_file(s.key(key), v, base_dir) if v else None
    if s.has("max_sim_s"):
        kw["max_sim_s"] = s.number("max_sim_s", lo=0.0, lo_open=True)
    if s.has("time_scale"):
        kw["time_scale"] = s.number("time_scale", lo=0.0, lo_open=True, hi=100.0)
    if s.has("faults"):
        kw["faults"] = _fault_list(s.raw("faults"), f"{name}.faults")
    if s.has("amp_stroke_um"):
        kw["amp_stroke_um"] = s.number("amp_stroke_um", lo=0.0, lo_open=True, hi=1000.0)
    if s.has("stroke_um"):  # machine.toml's bound: what the DBC's offset signals carry
        kw["stroke_um"] = s.number("stroke_um", lo=0.0, lo_open=True, hi=32.767)
    if s.has("final_cv_max"):
        kw["final_cv_max"] = s.number("final_cv_max", lo=0.0, lo_open=True, hi=1.0)
    if s.has("defects"):
        kw["defects"] = s.boolean("defects")
    s.reject_unknown()
    return replace(base, **kw)


def load_scenario(name_or_path: str | None = None) -> Scenario:
    """A scenario by name from ``config/hil.toml``, or the first table of another TOML file.

    Parameters
    ----------
    name_or_path : str, optional
        ``"default"`` (the default), another name of ``config/hil.toml``, or a path to a TOML
        file laid out the same way (``path.toml`` runs its ``default`` table or its only one;
        ``path.toml:name`` picks one).

    Raises
    ------
    ConfigError
        Unknown scenario, bad value, unknown fault kind, missing ``sim_config`` /
        ``machine_config`` file (relative to the scenario file's folder); the message names the
        file and the key (``hil.toml: default.faults[0].kind must be one of ...``).
    """
    spec = name_or_path or "default"
    path, name = default_path("hil.toml"), spec
    if spec.endswith(".toml") or ".toml:" in spec:
        p, _, nm = spec.partition(".toml")
        path = Path(p + ".toml")
        name = nm.lstrip(":") or ""
    doc = load_toml(path)
    if not name:
        name = "default" if "default" in doc else (next(iter(doc)) if len(doc) == 1 else "")
        if not doc:
            raise ConfigError(f"{path}: holds no scenario (no table)")
        if not name:
            raise ConfigError(
                f"{path}: holds several scenarios ({', '.join(sorted(doc))}) and none called "
                f"default: pick one with {path}:NAME"
            )
    if name not in doc:
        raise ConfigError(
            f"{path}: no scenario {name!r} (have: {', '.join(sorted(doc)) or 'none'})"
        )

    def build(nm: str, seen: tuple[str, ...]) -> Scenario:
        if nm in seen:
            raise ConfigError(f"{path}: scenario {nm} has a circular base")
        if nm not in doc:  # only a base can name a missing table (the name was checked)
            raise ConfigError(
                f"{path}: {seen[-1]}.base = {nm!r}: no scenario {nm!r} in this file (have: "
                f"{', '.join(sorted(doc))}); a base must be a table of the same file"
            )
        table = doc[nm]
        if not isinstance(table, Mapping):
            raise ConfigError(f"{path}: scenario {nm!r} is not a table")
        base_name = table.get("base")
        if base_name is not None and not isinstance(base_name, str):
            raise ConfigError(f"{path}: {nm}.base must be the name of a scenario, got "
                              f"{base_name!r}")
        base = build(base_name, (*seen, nm)) if base_name else Scenario()
        try:
            return scenario_from_table(nm, table, base, base_dir=path.parent)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None

    return build(name, ())


# ---------------------------------------------------------------------------------- configs
def sim_document(scenario: Scenario) -> dict[str, Any]:
    """The simulator's TOML document for a scenario (shipped ``sim.toml`` plus overrides)."""
    doc = load_over_shipped(scenario.sim_config, "sim.toml")[1]  # a partial file: over sim.toml
    if scenario.runout_um is not None:
        doc.setdefault("cutterhead", {})["runout_um"] = list(scenario.runout_um)
        doc["cutterhead"]["knives"] = len(scenario.runout_um)
    if scenario.initial_feed_mm_s is not None:
        doc.setdefault("feed", {})["initial_mm_s"] = scenario.initial_feed_mm_s
    if scenario.amp_stroke_um is not None:
        doc.setdefault("piezo", {})["stroke_um"] = scenario.amp_stroke_um
    return doc


def sim_config_for(scenario: Scenario, *, machine_faults: bool = True) -> Any:
    """The :class:`config.sim.SimConfig` of a scenario (machine faults in ``[faults]``)."""
    from config.sim import sim_from_dict

    doc = sim_document(scenario)
    if machine_faults:
        extra = [f.table() for f in scenario.faults if not f.kind.interface]
        if extra:
            doc.setdefault("faults", {}).setdefault("inject", [])
            doc["faults"]["inject"] = list(doc["faults"]["inject"]) + extra
    base = Path(scenario.sim_config).parent if scenario.sim_config else None
    with naming_file(scenario.sim_config or default_path("sim.toml")):  # errors name the file
        return sim_from_dict(doc, base_dir=base)


def machine_config_for(scenario: Scenario, *, log_path: Path | None = None) -> MachineConfig:
    """The service's configuration for a scenario (target pitch, stroke, log path applied)."""
    cfg = load_machine(scenario.machine_config)
    if scenario.stroke_um is not None:
        cfg = cfg.with_changes(stroke_um=scenario.stroke_um)
    if scenario.target_pitch_mm is not None:
        cfg = cfg.with_changes(
            quality=replace(cfg.quality, target_pitch_mm=scenario.target_pitch_mm)
        )
    if scenario.defects is not None:
        cfg = cfg.with_changes(quality=replace(cfg.quality, defects=scenario.defects))
    if log_path is not None:
        cfg = cfg.with_changes(log=replace(cfg.log, path=Path(log_path)))
    return cfg
