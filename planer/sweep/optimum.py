"""The best uniformity a plant allows: the reference for "within 5 % of the constrained optimum".

A saturated plant (stroke 10 um, 15 um of runout) must end within 5 % of the CV
of the best zero-mean offsets within the stroke. :func:`constrained_optimum_cv` finds that CV on
the simulated plant itself, not on the loop's model: the commanded table is played by the
simulated amplifier and actuator (:class:`plant_sim.model.piezo.PiezoAmplifier`, steady state at the
knives' bottom dead centres), the knives cut the exact tip circles
(:func:`plant_sim.model.surface.envelope`, marks that vanish included), and the CV is the true CV of
the marks, averaged over where the camera's window falls. The table is limited like the loop's
(``stroke - margin``, at most half the stroke kept back). The search starts from the width
model's exact QP and refines it with Nelder-Mead.

The amplifier heats with the slew of its output (``[piezo] heating_c_per_um_s`` per um/s, first
order towards ``ambient_c + heating * slew``) and faults above ``max_temperature_c``; a table
played every revolution slews ``n sum_k |o_k - o_(k-1)|`` um/s (:func:`steady_temperature_c`).
The optimum is searched among the tables whose steady-state temperature stays within that limit:
a table beyond it is scaled down onto the limit before its CV is taken (the slew is
proportional to the table), so the search never leaves what the amplifier can play for good.

The optimum is the best table the loop is allowed to command: a knife pattern (a Fourier mode
``m`` of the table over the knives) whose gain is below the loop's "can help" threshold
(``[uniformity_loop] gain_min``, :class:`controller.laws.uniformity_loop.UniformityLoopConfig`,
the same number the identifier holds a pattern at zero with) is held at zero by the loop, so
the search holds it at zero too. A pattern's gain is the largest ``|R_m / O_m|`` the simulated
actuator shows on a table of that pattern alone, over amplitudes up to the table's bound and
the temperature limit (:func:`pattern_gains`: a hysteretic stack moves a large cycle more than a
small one, and the loop plans at the amplitudes it sees).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controller.laws.limits import project_zero_mean_box
from controller.laws.offset_qp import best_offsets_um
from controller.laws.uniformity_loop import UniformityLoopConfig, offset_limit_um, second_difference


@dataclass(frozen=True)
class Optimum:
    """The constrained optimum of one plant.

    Attributes
    ----------
    cv : float
        Its true CV of the mark widths.
    offsets_um : tuple of float
        The commanded table, um (zero mean, within ``limit_um``).
    limit_um : float
        The bound of the table, um.
    clipped_cv : float
        For comparison: the CV of the runout clipped into the bound (the earlier loop's end).
    temperature_c : float
        The amplifier's steady-state temperature while it plays ``offsets_um``, degrees C.
    temperature_limit_c : float
        The temperature the table was kept within (``inf``: not limited), degrees C.
    patterns : tuple of int
        The knife patterns (modes ``1 .. Z // 2``) the table may use: those whose gain reaches
        the threshold it was searched with; the others are zero in ``offsets_um``.
    pattern_gains : tuple of float
        Each pattern's gain (:func:`pattern_gains`), modes ``1 .. Z // 2``.
    """

    cv: float
    offsets_um: tuple[float, ...]
    limit_um: float
    clipped_cv: float
    temperature_c: float = float("nan")
    temperature_limit_c: float = float("inf")
    patterns: tuple[int, ...] = ()
    pattern_gains: tuple[float, ...] = ()


def table_slew_um_s(table_um: Sequence[float], *, spindle_rpm: float) -> float:
    """The amplifier's mean output slew while it plays ``table_um`` every revolution, um/s.

    Each knife switch steps the (unshaped) output from the previous knife's offset to the next
    one's; the amplifier's heating counts those steps (the input shaper splits a step in two
    of the same sign: the same total).
    """
    o = np.asarray(table_um, dtype=float)
    return float(np.sum(np.abs(o - np.roll(o, 1)))) * spindle_rpm / 60.0


def steady_temperature_c(piezo_cfg, table_um: Sequence[float], *, spindle_rpm: float) -> float:
    """The amplifier's steady-state temperature while it plays ``table_um``, degrees C.

    ``ambient_c + heating_c_per_um_s * slew`` (:class:`plant_sim.model.piezo.PiezoAmplifier`,
    ``cycle``), with the slew of :func:`table_slew_um_s`.
    """
    slew = table_slew_um_s(table_um, spindle_rpm=spindle_rpm)
    return float(piezo_cfg.ambient_c + piezo_cfg.heating_c_per_um_s * slew)


def within_temperature(piezo_cfg, table_um: Sequence[float], *, spindle_rpm: float,
                       limit_c: float) -> np.ndarray:
    """``table_um`` scaled down (if needed) so that its steady-state temperature is ``limit_c``.

    Raises
    ------
    ValueError
        ``limit_c`` not above the amplifier's ambient temperature (no table but zero fits).
    """
    o = np.asarray(table_um, dtype=float)
    if not limit_c > piezo_cfg.ambient_c:
        raise ValueError(
            f"limit_c must exceed the ambient {piezo_cfg.ambient_c} C, got {limit_c!r}"
        )
    rise = steady_temperature_c(piezo_cfg, o, spindle_rpm=spindle_rpm) - piezo_cfg.ambient_c
    allowed = limit_c - piezo_cfg.ambient_c
    return o if rise <= allowed else o * (allowed / rise)


def actuator_response_um(piezo_cfg, table_um: Sequence[float], *, spindle_rpm: float,
                         revolutions: int = 30) -> np.ndarray:
    """Displacement at each knife's BDC once the amplifier plays ``table_um`` in steady state."""
    from plant_sim.model.piezo import PiezoAmplifier

    z = len(table_um)
    amp = PiezoAmplifier(piezo_cfg, z, np.random.default_rng(0))
    amp.command(0.0, enable=True, alive_counter=1)
    amp.set_offsets(list(table_um))
    period = 60.0 / spindle_rpm / z
    t, row = 0.0, np.zeros(z)
    for _ in range(revolutions):
        for k in range(z):
            bdc = t + period
            switch = bdc - piezo_cfg.lead_fraction * period
            amp.advance_to(switch)
            amp.switch(k, switch)
            amp.advance_to(bdc)
            row[k] = amp.actuator.x_um
            t = bdc
        amp.last_command_s = t  # no setpoint timeout
    return row


def pattern_gains(piezo_cfg, knives: int, *, spindle_rpm: float, bound_um: float,
                  temperature_limit_c: float = math.inf, amplitudes: int = 8) -> np.ndarray:
    """Each knife pattern's gain on the simulated actuator, modes ``1 .. Z // 2``.

    The gain of mode ``m`` is ``|R_m / O_m|`` for a table of that mode alone (a cosine and a
    sine over the knives, peak ``A``), ``R`` the actuator's steady response at the knives'
    bottom dead centres; the largest over ``amplitudes`` peaks up to ``bound_um``, each table
    scaled down onto ``temperature_limit_c`` where it would heat the amplifier beyond it.

    Parameters
    ----------
    piezo_cfg : config.sim.PiezoConfig
        The simulated amplifier and actuator.
    knives : int
        Knives ``Z``.
    spindle_rpm : float
        Spindle speed, rpm.
    bound_um : float
        Largest offset of a table, um.
    temperature_limit_c : float
        Steady-state temperature the tables keep within, degrees C (``inf``: not limited).
    amplitudes : int
        Peaks tried, evenly spaced from ``bound_um / amplitudes`` to ``bound_um``.

    Returns
    -------
    numpy.ndarray, shape (Z // 2,)
        The gains of modes ``1 .. Z // 2``.
    """
    z = int(knives)
    if z < 2:
        return np.zeros(0)
    if not bound_um > 0:
        raise ValueError(f"bound_um must be > 0, got {bound_um!r}")
    k = np.arange(z)
    out = np.zeros(z // 2)
    for m in range(1, z // 2 + 1):
        shapes = [np.cos(2 * np.pi * m * k / z)]
        if 2 * m != z:
            shapes.append(np.sin(2 * np.pi * m * k / z))
        best = 0.0
        for shape in shapes:
            shape = shape / np.max(np.abs(shape))
            for peak in np.linspace(bound_um / amplitudes, bound_um, amplitudes):
                table = shape * peak
                if math.isfinite(temperature_limit_c):
                    table = within_temperature(piezo_cfg, table, spindle_rpm=spindle_rpm,
                                               limit_c=temperature_limit_c)
                cmd = np.fft.fft(table)[m]
                if abs(cmd) < 1e-9:
                    continue
                resp = actuator_response_um(piezo_cfg, table, spindle_rpm=spindle_rpm)
                best = max(best, float(abs(np.fft.fft(resp)[m] / cmd)))
        out[m - 1] = best
    return out


def pattern_basis(knives: int, patterns: Sequence[int]) -> np.ndarray:
    """An orthonormal basis of the real zero-mean tables made of ``patterns`` only, (Z, r).

    ``patterns``: modes ``1 .. Z // 2`` (mode ``m`` brings ``Z - m``, its conjugate, along).
    """
    z = int(knives)
    mask = np.zeros(z)
    for m in patterns:
        if not 1 <= int(m) <= z // 2:
            raise ValueError(f"patterns must lie in 1..{z // 2}, got {m!r}")
        mask[int(m)] = mask[z - int(m)] = 1.0
    k = np.arange(z)
    f = np.exp(-2j * np.pi * np.outer(k, k) / z) / math.sqrt(z)
    proj = (f.conj().T @ np.diag(mask) @ f).real
    w, v = np.linalg.eigh(proj)
    return v[:, w > 0.5]


WINDOW_MM = 40.0
"""The camera's field along the board (``config/rig.toml``): the marks one true CV covers, mm."""
WINDOW_PHASES = 12
"""Window positions per revolution's travel that :func:`true_cv` averages over."""


def true_cv(
    sim_cfg, table_um: Sequence[float], *, feed_mm_s: float, window_mm: float = WINDOW_MM,
    phases: int = WINDOW_PHASES,
) -> float:
    """True CV of the marks cut with ``table_um`` at a steady ``feed_mm_s`` (actuator included).

    A window of ``window_mm`` holds a whole number of marks but not of revolutions (40 mm at
    1.5 mm and 4 knives: 6.7), so the CV of one window depends on where it starts: for the
    saturated plant's optimum 0.103-0.110. The HIL's true CV is one window per pair at
    whatever position the pair falls; this is the mean over ``phases`` window starts spread
    over one revolution's travel (``phases=1``: one window).

    Parameters
    ----------
    sim_cfg : config.sim.SimConfig
        The plant.
    table_um : sequence of float, shape (Z,)
        The commanded table, um.
    feed_mm_s : float
        The steady feed, mm/s.
    window_mm : float
        Length of one window, mm.
    phases : int
        Window starts averaged over, evenly spread over ``Z`` passes of board travel.

    Returns
    -------
    float
        The mean true CV of the windows.
    """
    from plant_sim.model import surface

    ch = sim_cfg.cutterhead
    head = surface.Cutterhead(knives=ch.knives, radius_mm=ch.radius_mm,
                              runout_um=tuple(ch.runout_um), eccentricity_um=ch.eccentricity_um)
    rpm = sim_cfg.spindle.rpm
    disp = actuator_response_um(sim_cfg.piezo, table_um, spindle_rpm=rpm)
    rev_mm = feed_mm_s / (rpm / 60.0)
    span_mm = window_mm + rev_mm + 20.0
    passes = surface.passes_steady(head, spindle_rpm=rpm, feed_mm_s=feed_mm_s, x_start_mm=0.0,
                                   x_end_mm=span_mm, offsets_um=tuple(disp))
    x = np.linspace(5.0, span_mm - 5.0, int(400 * (span_mm - 10.0)) + 1)
    env = surface.envelope(x, passes)
    starts = 10.0 + rev_mm * np.arange(phases) / phases
    return float(np.mean([env.metrics(a, a + window_mm)["uniformity_cv"] for a in starts]))


def constrained_optimum_cv(sim_cfg, machine_cfg, *, feed_mm_s: float | None = None,
                           temperature_limit_c: float | None = None,
                           gain_min: float | None = None) -> Optimum:
    """The best true CV of the tables the loop may command, within its bound and the heat.

    Parameters
    ----------
    sim_cfg : config.sim.SimConfig
        The plant (knives, radius, runout and eccentricity, spindle, piezo).
    machine_cfg : config.machine.MachineConfig
        The service (``stroke_um``, ``[uniformity_loop] margin_um``, target pitch).
    feed_mm_s : float, optional
        Feed; default the target pitch times ``n Z``.
    temperature_limit_c : float, optional
        Steady-state temperature the table must keep the amplifier within, degrees C; default
        the amplifier's ``max_temperature_c`` (it faults above); ``inf``: not limited.
    gain_min : float, optional
        The knife patterns whose gain (:func:`pattern_gains`) is below this are held at zero;
        default the loop's own threshold, ``[uniformity_loop] gain_min`` of ``machine_cfg``
        (0: every pattern).

    Returns
    -------
    Optimum
    """
    from scipy.optimize import minimize

    ch = sim_cfg.cutterhead
    z = ch.knives
    ucfg = UniformityLoopConfig.from_mapping(dict(machine_cfg.uniformity_loop), knives=z,
                                             stroke_um=machine_cfg.stroke_um)
    bound = offset_limit_um(machine_cfg.stroke_um, ucfg.margin_um)
    rpm = sim_cfg.spindle.rpm
    feed = feed_mm_s or machine_cfg.quality.target_pitch_mm * rpm / 60.0 * z
    hot = sim_cfg.piezo.max_temperature_c if temperature_limit_c is None else temperature_limit_c
    threshold = ucfg.gain_min if gain_min is None else gain_min
    if not (isinstance(threshold, int | float) and math.isfinite(threshold) and threshold >= 0):
        raise ValueError(f"gain_min must be a number >= 0, got {gain_min!r}")
    gains = pattern_gains(sim_cfg.piezo, z, spindle_rpm=rpm, bound_um=bound,
                          temperature_limit_c=hot)
    patterns = tuple(m + 1 for m in range(len(gains)) if gains[m] >= threshold)
    if len(patterns) == len(gains):  # every pattern: the free entries (the earlier search's)
        basis = np.vstack([np.eye(z - 1), -np.ones((1, z - 1))])
    else:
        basis = pattern_basis(z, patterns)
    proj = basis @ np.linalg.pinv(basis)
    k = np.arange(z)
    standout = np.asarray(ch.runout_um, float) + ch.eccentricity_um * np.cos(2 * np.pi * k / z)
    # the actuator's steady response as a matrix (columns: unit tables), for the QP start
    a = np.column_stack([
        actuator_response_um(sim_cfg.piezo, np.eye(z)[j] - 1.0 / z, spindle_rpm=rpm)
        for j in range(z)
    ])
    start = best_offsets_um(standout, width_operator=second_difference(z), actuator=a,
                            bound_um=bound)
    clipped = project_zero_mean_box(standout - standout.mean(), bound=bound)

    def coords(o: np.ndarray) -> np.ndarray:
        return np.linalg.lstsq(basis, proj @ np.asarray(o, float), rcond=None)[0]

    def table(x: np.ndarray) -> np.ndarray:
        o = basis @ x
        if math.isinf(hot):
            return o
        return within_temperature(sim_cfg.piezo, o, spindle_rpm=rpm, limit_c=hot)

    def cost(x: np.ndarray) -> float:
        o = table(x)
        excess = float(np.sum(np.maximum(np.abs(o) - bound, 0.0)))
        if excess > 0:
            return 1.0 + excess
        return true_cv(sim_cfg, o, feed_mm_s=feed)

    r = basis.shape[1]
    best_x, best_cv = np.zeros(r), cost(np.zeros(r))
    # starts (within the patterns): the QP's table, the clipped runout, and the best of the
    # runout scaled up to the bound (a hysteretic stack moves a small table by a few per cent:
    # its optimum table is several times the runout, far from the small-signal QP's)
    shape = proj @ (standout - standout.mean())
    peak = float(np.max(np.abs(shape)))
    scaled = [shape * c for c in np.linspace(1.0, bound / peak, 12)] if peak > 1e-12 else []
    ranked = sorted(scaled, key=lambda o: cost(coords(o)))[:1]
    for o0 in (start, clipped, *ranked) if r else ():
        res = minimize(cost, coords(o0), method="Nelder-Mead",
                       options={"xatol": 0.01, "fatol": 1e-5, "maxiter": 200 * z})
        if res.fun < best_cv:
            best_x, best_cv = res.x, float(res.fun)
    best = table(best_x)
    return Optimum(cv=best_cv, offsets_um=tuple(float(v) for v in best), limit_um=bound,
                   clipped_cv=true_cv(sim_cfg, clipped, feed_mm_s=feed),
                   temperature_c=steady_temperature_c(sim_cfg.piezo, best, spindle_rpm=rpm),
                   temperature_limit_c=float(hot), patterns=patterns,
                   pattern_gains=tuple(float(g) for g in gains))
