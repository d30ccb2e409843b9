"""The moulder in the loop: every head's service and the one feed around the simulated moulder.

In one process on simulated time, as :mod:`planer.hil.in_process` runs one head: the simulated
moulder (:class:`plant_sim.machine.moulder.Moulder`: one feed, a machine per head), every head's
amplifier a CANopen node (its node id) on ONE virtual CAN bus, the PLC through its register bus
(each head's service over its head's view of the register map, the coordinator over the common
registers), and :class:`controller.moulder.service.MoulderService` stepped every control cycle.

The summary (``planer hil --scenario moulder --json``) holds the machine's feed and a ``heads``
list: per head its name, face, knives, speed, target pitch and the true finish it ended with
(``final_true_cv``, ``final_true_pitch_mm``), where the CV settled (``cv_settled_after_mm``,
from the head's loop closing), its safe-state entries and its own checks.
"""

from __future__ import annotations

import itertools
import os
import time
from pathlib import Path
from typing import Any

from config.heads import HeadConfig
from config.machine import MachineConfig, head_config
from planer.hil.scenario import Progress, Scenario, machine_config_for, sim_config_for
from planer.hil.summary import check_log, summarize

MOULDER_CV_MAX = 0.03
"""Each head's true CV must end at or below this (and settle to it)."""
MOULDER_SETTLE_MM = 2000.0
"""... within this much board after its loop closed (its camera's delay is before that)."""
FEED_OPTIMUM_TOL = 0.01
"""The final feed within this of the fastest feed that meets every head's target."""

_channels = itertools.count()


class MoulderPlant:
    """The simulated moulder and the moulder service wired in one process (simulated time).

    Parameters
    ----------
    cfg : MachineConfig
        The service's configuration with its ``heads``.
    sim_cfg : SimConfig
        The simulator's configuration with its ``heads`` (same names).
    seed : int
        Simulator seed.
    log_path : Path
        The quality log (every head's records, each with its ``head``).
    measurer_factory : callable, optional
        ``factory(head_cfg) -> factory(shape)``; default the vision of each head's rig.
    render_images : bool
        Render the cameras' images.
    """

    def __init__(self, cfg: MachineConfig, sim_cfg: Any, *, seed: int = 0, log_path: Path,
                 measurer_factory: Any = None, render_images: bool = True) -> None:
        import can

        from config.machine import eds_path, registers_path, rig_path
        from config.rig import load_rig
        from controller.fieldbus.piezo_client import PiezoClient
        from controller.fieldbus.plc_client import PlcClient
        from controller.fieldbus.plc_protocol import Backoff
        from controller.laws.moulder_feed import MoulderFeedConfig, MoulderFeedLaw
        from controller.moulder.feed import MoulderFeed
        from controller.moulder.service import MoulderService
        from controller.quality.log import open_quality_log
        from controller.service.measurement import VisionMeasurers
        from controller.service.service import Service
        from plant_sim.interfaces.amp_node import AmpNode, AmpNodeCore
        from plant_sim.interfaces.register_bus import MachineRegisterBus
        from plant_sim.machine.moulder import Moulder
        from protocol.registers import RegisterMap

        sim_names = [h.name for h in sim_cfg.heads]
        names = [h.name for h in cfg.heads]
        if names != sim_names:
            raise ValueError(f"machine heads {names} and simulator heads {sim_names} differ: "
                             "a moulder's two configurations must name the same heads in order")
        self.cfg = cfg
        self.sim_cfg = sim_cfg
        self.moulder = Moulder(sim_cfg, seed=seed, render_images=render_images)
        self.regmap = RegisterMap.load(registers_path(cfg))
        backoff = Backoff(cfg.plc.backoff_initial_s, cfg.plc.backoff_max_s)
        self._buses: list[Any] = []
        self._logs: list[Any] = []
        self.amps: dict[str, Any] = {}
        heads: dict[str, Any] = {}
        channel = f"planer-moulder-{os.getpid()}-{next(_channels)}"
        try:
            self.start_id = 0
            for i, hc in enumerate(cfg.heads):
                machine = self.moulder.heads[hc.name]
                hsim = machine.cfg
                amp_bus = can.Bus(interface="virtual", channel=channel)
                self._buses.append(amp_bus)
                self.amps[hc.name] = AmpNode(
                    amp_bus, AmpNodeCore(machine, knives=hsim.cutterhead.knives,
                                         node_id=hsim.can.node_id, eds=hsim.can.eds,
                                         seed=seed + i),
                    own_bus=True)
                hcfg = head_config(cfg, hc.name)
                view = self.regmap.for_head(i)
                plc = PlcClient(MachineRegisterBus(self.moulder, view), view,
                                backoff=backoff, clock=self.clock)
                svc_bus = can.Bus(interface="virtual", channel=channel)
                self._buses.append(svc_bus)
                piezo = PiezoClient(
                    svc_bus, knives=hsim.cutterhead.knives, node_id=hcfg.can.node_id,
                    eds=eds_path(hcfg), command_period_s=hcfg.can.command_period_s,
                    offsets_period_s=hcfg.can.offsets_period_s, stroke_um=hcfg.stroke_um)
                log = open_quality_log(Path(log_path), machine_id=cfg.log.machine_id or None)
                self._logs.append(log)
                if i == 0:
                    self.start_id = log.last_id
                rig = load_rig(rig_path(hcfg))
                factory = (measurer_factory(hc) if measurer_factory is not None
                           else VisionMeasurers(rig, defects=hcfg.quality.defects))
                svc = Service(hcfg, plc=plc, piezo=piezo, rig=rig, log=log, clock=self.clock,
                              threaded=False, measurer_factory=factory,
                              pairs_per_s=hsim.camera.pairs_per_s, owns_feed=False)
                svc.keep_results = True
                log.set_quality_class(svc.quality_class, head=hc.name)
                heads[hc.name] = svc
            common = PlcClient(MachineRegisterBus(self.moulder, self.regmap), self.regmap,
                               backoff=backoff, clock=self.clock)
            feed = MoulderFeed(heads, cfg.heads, plc=common,
                               law=MoulderFeedLaw(MoulderFeedConfig()))
            self.service = MoulderService(heads, cfg.heads, feed=feed)
        except BaseException:
            self._close_parts(heads)
            raise
        self.start_mm = self.moulder.feed_position_mm

    def clock(self) -> float:
        """Machine time, s."""
        return float(self.moulder.t_s)

    @property
    def travelled_mm(self) -> float:
        """Table travel since the plant was made, mm."""
        return self.moulder.feed_position_mm - self.start_mm

    def inject(self, fault: Any) -> None:
        """Play one interface fault now (``can_silence``/``can_drop`` on its head's node)."""
        from config.faults import FaultKind
        from plant_sim.interfaces.amp_node import CAN_FAULTS

        kind = FaultKind.parse(fault.kind.value if hasattr(fault.kind, "value") else fault.kind)
        params = kind.check(dict(fault.params))
        head = getattr(fault, "head", None) or self.cfg.heads[0].name
        if kind.value not in CAN_FAULTS:
            raise ValueError(f"{kind.value}: not an interface fault of a moulder's head")
        self.amps[head].core.play(kind.value, params, start_s=self.clock())

    async def step(self) -> list[tuple[str, Any]]:
        """One control cycle: amplifiers receive, the moulder advances, the service acts."""
        t = self.clock()
        for amp in self.amps.values():
            amp.receive(t)
        frames = self.moulder.advance(self.cfg.safety.cycle_s)
        t = self.clock()
        for amp in self.amps.values():
            amp.transmit(t)
        await self.service.tick(t)
        out = []
        for name, fr in frames:
            out.append((name, await self.service.handle_frame(name, fr, now_s=t)))
        return out

    def _close_parts(self, heads: dict[str, Any]) -> None:
        """A failed start: every part opened so far closed (the last error propagates)."""
        from core.closing import close_all

        close_all([svc.close for svc in heads.values()]
                  + [log.close for log in self._logs[len(heads):]]  # no service to close it
                  + [amp.close for amp in self.amps.values()]
                  + [bus.shutdown for bus in self._buses])

    async def close(self) -> None:
        """Close every head's service, the coordinator's connection and the nodes."""
        try:
            self.service.close()
        finally:
            for amp in self.amps.values():
                amp.close()


def _head_faults(scenario: Scenario, head: str, first: str) -> tuple[Any, ...]:
    """The scenario's faults that act on ``head`` (a fault naming no head: the first head)."""
    return tuple(f for f in scenario.faults if (getattr(f, "head", None) or first) == head)


def head_summary(hc: HeadConfig, svc: Any, scenario: Scenario, *, first_head: str,
                 counts_per_mm: float, feed_limits: tuple[float, float]) -> dict[str, Any]:
    """One head's part of the summary (the contract's keys first, then its own checks)."""
    faults = _head_faults(scenario, hc.name, first_head)
    s = summarize(svc.results, target_pitch_mm=hc.target_pitch_mm, counts_per_mm=counts_per_mm,
                  feed_limits_mm_s=feed_limits, stroke_um=svc.cfg.stroke_um,
                  faults=faults, events=svc.events, safety=svc.cfg.safety,
                  piezo_limits=svc.out.limits(), final_cv_max=MOULDER_CV_MAX)
    conv = s["converged"]
    snap = svc.plc.last
    settled = conv.get("uniformity_settled_after_mm")
    done = dict(s["done"])
    done.pop("settled_within_3m", None)  # a moulder's head: 2 m, the CV alone (pitch below)
    done[f"cv_settled_within_{MOULDER_SETTLE_MM / 1000:g}m"] = (
        settled is not None and settled <= MOULDER_SETTLE_MM)
    return {
        "name": hc.name,
        "face": hc.face,
        "knives": int(snap.knives) if snap is not None else hc.knives,
        "rpm": round(float(snap.spindle_rpm), 1) if snap is not None else hc.rpm,
        "target_pitch_mm": hc.target_pitch_mm,
        "final_true_cv": s["final"].get("uniformity_cv"),
        "final_true_pitch_mm": s["final"].get("pitch_mm"),
        "cv_settled_after_mm": settled,
        "safe_entries": s["safe_entries"]["count"],
        "safe_entries_unexplained": s["safe_entries"]["unexplained"],
        "safe_reasons": [e["reason"] for e in s["safe_entries"]["entries"]],
        "pitch_settled_after_mm": conv.get("pitch_settled_after_mm"),
        "loop_closed_at_mm": conv.get("loop_closed_at_mm"),
        "initial_true_cv": s["initial"].get("uniformity_cv"),
        "counts": s["counts"],
        "faults": s["faults"],
        "service": dict(svc.counters),
        "done": done,
        "passed": all(done.values()),
    }


def fastest_feed_mm_s(heads: list[dict[str, Any]], rpm_max: dict[str, float], *,
                      feed_mm_s: float, feed_max_mm_s: float) -> float | None:
    """The fastest feed at which every head's true pitch meets its target (mm/s), from truth.

    At the run's final feed ``feed_mm_s`` each head cut its final true pitch; the pitch scales
    with the feed over the speed, so a fixed head allows ``feed * target / pitch`` and a variable
    head (its speed free up to ``rpm_max``) that times ``rpm_max / rpm``. The machine's
    ``feed_max`` caps it. ``None`` without every head's final pitch.
    """
    best = float(feed_max_mm_s)
    for h in heads:
        p, rpm = h["final_true_pitch_mm"], h["rpm"]
        if p is None or not p > 0 or not rpm:
            return None
        allow = feed_mm_s * h["target_pitch_mm"] / p
        if h["name"] in rpm_max:
            allow *= rpm_max[h["name"]] / rpm
        best = min(best, allow)
    return best


class MoulderHil:
    """A moulder scenario on :class:`MoulderPlant` (simulator and service in one process).

    Parameters
    ----------
    scenario : Scenario
        What to run (its ``machine_config`` and ``sim_config`` describe several heads).
    log_path : Path
        Quality log (created or continued).
    progress : callable, optional
        Receives progress lines.
    progress_every : int
        Pairs (all heads) between progress lines.
    """

    def __init__(self, scenario: Scenario, *, log_path: Path, progress: Progress | None = None,
                 progress_every: int = 40) -> None:
        self.scenario = scenario
        self.log_path = Path(log_path)
        self.progress = progress
        self.progress_every = int(progress_every)
        self.cfg = machine_config_for(scenario, log_path=self.log_path)
        self.sim_cfg = sim_config_for(scenario)
        self.service: Any = None

    def _say(self, line: str) -> None:
        if self.progress is not None:
            self.progress(line)

    async def run(self) -> dict[str, Any]:
        """Run the scenario; the summary (``heads`` one object per head)."""
        sc, cfg = self.scenario, self.cfg
        plant = MoulderPlant(cfg, self.sim_cfg, seed=sc.seed, log_path=self.log_path)
        self.service = plant.service
        for name, svc in plant.service.heads.items():
            svc.on_event = (lambda e, n=name: self._say(f"t={e.t_s:7.3f} s  [{n}] {e.text}"))
        pending = sorted((f for f in sc.faults if f.kind.interface), key=lambda f: f.at_s)
        heads = ", ".join(f"{h.name} ({h.face}, target {h.target_pitch_mm:g} mm)"
                          for h in cfg.heads)
        self._say(f"hil moulder (in-process, simulated time): scenario {sc.name}, "
                  f"{sc.distance_m:g} m of board; heads {heads}")
        n_pairs = n_last = 0
        wall0 = time.perf_counter()
        try:
            while plant.travelled_mm < sc.distance_m * 1000.0 and plant.clock() < sc.max_sim_s:
                t = plant.clock()
                while pending and pending[0].at_s <= t + 1e-9:
                    f = pending.pop(0)
                    self._say(f"t={t:7.3f} s  fault: {f.kind.value} on "
                              f"{getattr(f, 'head', None) or cfg.heads[0].name} for "
                              f"{f.duration_s:g} s")
                    plant.inject(f)
                n_pairs += len(await plant.step())
                if n_pairs >= n_last + self.progress_every:
                    n_last = n_pairs
                    self._say(self._progress_line(plant))
            wall = time.perf_counter() - wall0
        finally:
            await plant.close()
        return self._summary(plant, wall)

    def _progress_line(self, plant: MoulderPlant) -> str:
        d = plant.service.feed.last
        feed = "-" if d is None or d.feed_mm_s is None else f"{d.feed_mm_s:6.1f}"
        parts = []
        for name, svc in plant.service.heads.items():
            r = svc.results[-1] if svc.results else None
            cv = r.truth.get("uniformity_cv") if r is not None and r.truth else None
            parts.append(f"{name} cv {cv:.3f}" if isinstance(cv, float) else f"{name} -")
        return (f"{plant.travelled_mm / 1000:6.2f} m  feed {feed} mm/s  " + "  ".join(parts))

    def _summary(self, plant: MoulderPlant, wall: float) -> dict[str, Any]:
        sc, cfg = self.scenario, self.cfg
        common = plant.service.feed.plc.last
        lim = ((common.feed_min_mm_s, common.feed_max_mm_s) if common is not None
               else (float("nan"), float("nan")))
        cpm = common.counts_per_mm if common is not None else self.sim_cfg.encoder.counts_per_mm
        first = cfg.heads[0].name
        heads = [head_summary(hc, plant.service.heads[hc.name], sc, first_head=first,
                              counts_per_mm=cpm, feed_limits=lim) for hc in cfg.heads]
        feed = plant.service.feed.describe()
        final_feed = common.feed_actual_mm_s if common is not None else None
        rpm_max = {hc.name: float(hc.rpm_max) for hc in cfg.heads
                   if hc.rpm_max is not None and hc.rpm_min is not None
                   and hc.rpm_min < hc.rpm_max}
        fastest = (None if final_feed is None else
                   fastest_feed_mm_s(heads, rpm_max, feed_mm_s=final_feed,
                                     feed_max_mm_s=lim[1]))
        # a faulted head does not count against the run: the others must stay controlled
        faulted = {getattr(f, "head", None) or first for f in sc.faults}
        total = sum(len(svc.results) for svc in plant.service.heads.values())
        log_check = check_log(self.log_path, total, after_id=plant.start_id)
        done = {
            "every_head_passed": all(h["passed"] for h in heads if h["name"] not in faulted),
            "faulted_heads_reported": all(
                h["safe_entries"] > 0 and h["safe_entries_unexplained"] == 0
                for h in heads if h["name"] in faulted),
            "feed_fastest_within_1pct": fastest is not None and final_feed is not None
            and abs(final_feed / fastest - 1.0) <= FEED_OPTIMUM_TOL,
            "no_unexplained_safe_state": all(h["safe_entries_unexplained"] == 0 for h in heads),
            "quality_log_intact": bool(log_check["ok"]),
        }
        return {
            "mode": "in-process",
            "scenario": sc.name,
            "machine": "moulder",
            "heads": heads,
            "feed": {**feed, "final_actual_mm_s": final_feed, "fastest_mm_s": fastest,
                     "limits_mm_s": list(lim)},
            "sim_time_s": round(plant.clock(), 3),
            "wall_time_s": round(wall, 3),
            "board_travel_m": round(plant.travelled_mm / 1000, 3),
            "quality_log": log_check,
            "done": done,
            "passed": all(done.values()),
        }


def human_text(summary: dict[str, Any]) -> str:
    """The moulder run's summary for people: the feed, then one line per head, then checks."""

    def f(v: object, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    feed = summary["feed"]
    lines = [
        f"planer hil: scenario {summary.get('scenario')} (moulder, {len(summary['heads'])} "
        f"heads, {summary.get('mode')}), {summary.get('board_travel_m')} m of board",
        f"  feed              {f(feed.get('final_actual_mm_s'), '.1f')} mm/s; fastest meeting "
        f"every target {f(feed.get('fastest_mm_s'), '.1f')} mm/s (limiting: "
        f"{', '.join(feed.get('limiting') or []) or '-'})",
        "  head    face    Z  rpm     target  true pitch  true CV        CV settled  safe",
    ]
    for h in summary["heads"]:
        lines.append(
            f"  {h['name']:<7} {h['face']:<7} {f(h['knives'], 'd'):<2} {f(h['rpm'], '.0f'):<7} "
            f"{h['target_pitch_mm']:.3f}   {f(h['final_true_pitch_mm'], '.3f'):<10}  "
            f"{f(h.get('initial_true_cv'), '.3f')} -> {f(h['final_true_cv'], '.3f')}  "
            f"{f(h['cv_settled_after_mm'], '.0f'):>7} mm  {h['safe_entries']}"
            + (f" ({'; '.join(h['safe_reasons'])})" if h["safe_reasons"] else "")
            + ("" if h["passed"] else "  FAILED: " + ", ".join(
                k for k, ok in h["done"].items() if not ok)))
    for k, ok in summary["done"].items():
        lines.append(f"  {'ok ' if ok else 'NOT'} {k}")
    lines.append(f"  quality log       {summary['quality_log'].get('path')} "
                 f"({summary['quality_log'].get('records')} records)")
    lines.append("PASSED" if summary["passed"] else "FAILED")
    return "\n".join(lines)
