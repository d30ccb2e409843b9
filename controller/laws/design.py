"""Design checks of the control laws with python-control: discrete models, margins, steps.

Feed loop (log domain, sample time ``Ts`` = the measurement interval)::

    u = x = log of the correction factor           (controller output)
    y = log(p_meas / p*) = P(z) u + log(k)         (k: model error, an output disturbance)
    P(z) = G_drive(z) * z^-(d-1) * H_m(z)          (drive lag, transport delay, window average)
    M(z) = z^-d * H_m(z)                           (internal model: the drive as one ZOH sample)
    x+ = x + g * (-(y - M u) - x)   =>   u = -C(z) y,   C = g / (z - 1 + g - g M)
    L(z) = C(z) P(z),   g = ki * Ts / (T_delay + Ts)

with ``d = ceil(L / (V Ts)) + latency`` samples and ``H_m`` the mean of ``m = W / (V Ts)``
samples (the measured window of board was cut over ``W / V`` seconds).

Uniformity loop, per circulant Fourier mode ``m`` of the knives, in the same samples (one image
pair): the loop learns on every pair against its prediction (Smith form), so per mode it is the
feed loop's structure around the actuator-and-width plant::

    P(z) = alpha * z^-d * H_m(z)                   (alpha: true / modelled mode gain)
    M(z) = z^-d * H_m(z)                           (the table history: the delay is known)
    C(z) = g / (z - 1 + g - g M(z)),  g = ki * Ts / (T_delay + Ts)

with ``d = ceil((settle + L / V) / Ts) + latency``. ``alpha`` is complex when the identified
actuator gain is off in phase (a slow piezo lags into the next knife).

Margins are computed by :func:`control.stability_margins` on a dense frequency-response grid
(``control.frd``): with transport delays of tens of samples the polynomial method of
python-control is numerically unreliable.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import control as ct
import numpy as np

from controller.laws.feed_loop import FeedLoopConfig, integral_gain
from controller.laws.uniformity_loop import UniformityLoopConfig, second_difference
from core.checks import check_int, check_positive

#: Feeds (mm/s) at which the margins are computed and documented.
DESIGN_FEEDS_MM_S = (50.0, 100.0, 300.0, 600.0, 1000.0)

#: Required margins.
MIN_GAIN_MARGIN_DB = 6.0
MIN_PHASE_MARGIN_DEG = 45.0


@dataclass(frozen=True)
class FeedPlant:
    """The feed loop's plant beyond the controller's configuration.

    Attributes
    ----------
    drive_bandwidth_hz : float
        -3 dB bandwidth of the feed drive's velocity loop, Hz.
    drive_order : int
        1: first-order lag; 2: second-order lag with damping 0.7.
    latency_samples : int
        Samples between the image pair and the setpoint it produces (measurement interval and
        processing), >= 0.
    """

    drive_bandwidth_hz: float = 5.0
    drive_order: int = 1
    latency_samples: int = 1

    def __post_init__(self) -> None:
        check_positive("drive_bandwidth_hz", self.drive_bandwidth_hz)
        check_int("drive_order", self.drive_order, lo=1, hi=2)
        check_int("latency_samples", self.latency_samples, lo=0)


@dataclass(frozen=True)
class Margins:
    """Stability margins of one loop transfer function.

    Attributes
    ----------
    gain_margin_db : float
        Gain margin, dB (``inf`` when the phase never crosses -180 deg).
    phase_margin_deg : float
        Phase margin, degrees.
    stability_margin : float
        Smallest distance of the Nyquist curve from -1.
    phase_crossover_rad_s, gain_crossover_rad_s : float
        Frequencies of the gain and phase margins, rad/s (rad/iteration for iteration loops).
    delay_margin_s : float
        Extra delay the loop tolerates, ``PM / w_gc`` (seconds, or iterations).
    """

    gain_margin_db: float
    phase_margin_deg: float
    stability_margin: float
    phase_crossover_rad_s: float
    gain_crossover_rad_s: float
    delay_margin_s: float


@dataclass(frozen=True)
class FeedLoopModel:
    """Discrete-time blocks of the feed loop at one feed (all ``dt = sample_time_s``).

    Attributes
    ----------
    feed_mm_s : float
        Feed at which the loop is linearised, mm/s.
    delay_samples, window_samples : int
        ``d`` and ``m`` of the module docstring.
    gain : float
        Per-sample integral gain ``g``.
    plant, model, filter : control.TransferFunction
        ``P(z)``, ``M(z)`` and ``K0(z) = g / (z - 1 + g)``; ``C = K0 / (1 - K0 M)``.
    """

    feed_mm_s: float
    delay_samples: int
    window_samples: int
    gain: float
    plant: ct.TransferFunction
    model: ct.TransferFunction
    filter: ct.TransferFunction


def _delay(samples: int, dt: float) -> ct.TransferFunction:
    den = np.zeros(samples + 1)
    den[0] = 1.0
    return ct.tf([1.0], den, dt)


def _window(samples: int, dt: float) -> ct.TransferFunction:
    # (1 + z^-1 + ... + z^-(m-1)) / m  =  (z^(m-1) + ... + 1) / (m z^(m-1))
    den = np.zeros(samples)
    den[0] = float(samples)
    return ct.tf(np.ones(samples), den, dt)


def _drive(plant: FeedPlant, dt: float) -> ct.TransferFunction:
    wb = 2.0 * math.pi * plant.drive_bandwidth_hz
    if plant.drive_order == 1:
        cont = ct.tf([wb], [1.0, wb])
    else:  # second order, damping 0.7: its -3 dB bandwidth is about its natural frequency
        cont = ct.tf([wb * wb], [1.0, 1.4 * wb, wb * wb])
    return ct.sample_system(cont, dt, method="zoh")


def feed_delay_samples(
    feed_mm_s: float, cfg: FeedLoopConfig, plant: FeedPlant = FeedPlant()
) -> tuple[int, int]:
    """Transport delay ``d`` and window length ``m`` in samples at ``feed_mm_s``.

    Returns
    -------
    (int, int)
        ``d = ceil(L / (V Ts)) + latency`` and ``m = max(1, round(W / (V Ts)))``.
    """
    v = check_positive("feed_mm_s", feed_mm_s)
    ts = cfg.sample_time_s
    d = math.ceil(cfg.cutter_to_camera_mm / (v * ts) - 1e-9) + plant.latency_samples
    m = max(1, round(cfg.window_mm / (v * ts)))
    return d, m


def feed_loop_model(
    cfg: FeedLoopConfig,
    feed_mm_s: float,
    *,
    plant: FeedPlant = FeedPlant(),
    model_delay_error_samples: int = 0,
    gain_scale: float = 1.0,
) -> FeedLoopModel:
    """The feed loop's blocks at one feed.

    Parameters
    ----------
    cfg : FeedLoopConfig
        The controller's configuration (gain, geometry, sample time).
    feed_mm_s : float
        Operating feed, mm/s.
    plant : FeedPlant
        Drive and latency of the true plant.
    model_delay_error_samples : int
        Error of the controller's delay model (``M`` uses ``d + error``), samples.
    gain_scale : float
        Factor on the scheduled gain (robustness checks).

    Returns
    -------
    FeedLoopModel
    """
    ts = cfg.sample_time_s
    d, m = feed_delay_samples(feed_mm_s, cfg, plant)
    window = _window(m, ts)
    p = _drive(plant, ts) * _delay(d - 1, ts) * window  # the ZOH drive adds the d-th sample
    dm = max(0, d + int(model_delay_error_samples))
    model = _delay(dm, ts) * window
    g = gain_scale * integral_gain(cfg.ki, ts, (d + 0.5 * (m - 1)) * ts)
    k0 = ct.tf([g], [1.0, g - 1.0], ts)
    return FeedLoopModel(float(feed_mm_s), d, m, g, p, model, k0)


def frequency_grid(dt: float, *, n_log: int = 400, n_lin: int = 2000) -> np.ndarray:
    """Grid up to the Nyquist frequency: log-spaced low end plus a linear part, rad/s.

    A delay of ``d`` samples turns the phase by ``d * dt`` rad per rad/s, so ``n_lin`` should be
    at least about ``10 d`` to keep the phase step below 0.3 rad (see :func:`feed_loop_frd`).
    """
    w_n = math.pi / dt
    lo = np.logspace(math.log10(w_n) - 5.0, math.log10(w_n) - 1.0, n_log, endpoint=False)
    lin = np.linspace(w_n * 0.1, w_n * (1.0 - 1e-6), n_lin)
    return np.concatenate([lo, lin])


def feed_loop_frd(
    model: FeedLoopModel, omega: np.ndarray | None = None
) -> ct.FrequencyResponseData:
    """Loop transfer function ``L = C P`` (break at the plant input) as frequency-response data."""
    dt = model.plant.dt
    if omega is None:
        n_lin = 20 * (model.delay_samples + model.window_samples) + 400
        w = frequency_grid(dt, n_lin=n_lin)
    else:
        w = np.asarray(omega, dtype=float)
    z = np.exp(1j * w * dt)
    k0 = model.filter(z)
    c = k0 / (1.0 - k0 * model.model(z))
    return ct.frd(c * model.plant(z), w, dt)


def _nyquist_value(loop: ct.LTI) -> float | None:
    """Real value of a discrete loop at z = -1 (None: continuous, or FRD not reaching it)."""
    if not loop.isdtime(strict=True):
        return None
    w_n = math.pi / loop.dt
    if isinstance(loop, ct.FRD):
        if loop.omega[-1] < w_n * (1.0 - 1e-4):
            return None
        val = complex(loop.frdata[0, 0, -1])
        return val.real if abs(val.imag) <= 1e-3 * abs(val) else None
    return float(np.real(np.squeeze(loop(-1.0))))


def margins(loop: ct.LTI) -> Margins:
    """Gain, phase and stability margins of a loop transfer function (negative feedback).

    Parameters
    ----------
    loop : control.TransferFunction or control.FrequencyResponseData
        ``L``; an FRD must cover the frequencies up to Nyquist densely.

    Returns
    -------
    Margins
    """
    with warnings.catch_warnings():  # |L| = inf at the integrator's z = 1 is expected
        warnings.simplefilter("ignore", RuntimeWarning)
        gm, pm, sm, wpc, wgc, _ = ct.stability_margins(loop)
    l_n = _nyquist_value(loop)
    if l_n is not None and l_n < 0 and 1.0 / abs(l_n) < gm:
        # a real discrete loop is real at z = -1; python-control misses a crossover there
        gm, wpc = 1.0 / abs(l_n), math.pi / loop.dt
    gm_db = math.inf if not np.isfinite(gm) else 20.0 * math.log10(gm)
    delay = math.inf if not (np.isfinite(wgc) and wgc > 0) else math.radians(pm) / wgc
    return Margins(float(gm_db), float(pm), float(sm), float(wpc), float(wgc), float(delay))


@dataclass(frozen=True)
class FeedMarginsRow:
    """One row of the feed loop's margins table."""

    feed_mm_s: float
    delay_samples: int
    window_samples: int
    gain: float
    margins: Margins


def feed_loop_margins(
    cfg: FeedLoopConfig,
    feeds_mm_s: tuple[float, ...] = DESIGN_FEEDS_MM_S,
    *,
    plant: FeedPlant = FeedPlant(),
    model_delay_error_samples: int = 0,
    gain_scale: float = 1.0,
) -> list[FeedMarginsRow]:
    """Margins of the feed loop at each feed (see :func:`feed_loop_model`)."""
    rows = []
    for v in feeds_mm_s:
        mdl = feed_loop_model(
            cfg,
            v,
            plant=plant,
            model_delay_error_samples=model_delay_error_samples,
            gain_scale=gain_scale,
        )
        rows.append(
            FeedMarginsRow(
                float(v),
                mdl.delay_samples,
                mdl.window_samples,
                mdl.gain,
                margins(feed_loop_frd(mdl)),
            )
        )
    return rows


def feed_disturbance_response(model: FeedLoopModel) -> ct.StateSpace:
    """Closed loop from the model error ``log k`` (output disturbance) to ``log(p_meas / p*)``.

    Built as a state-space interconnection (``S = 1 / (1 + C P)``) so that long delays stay
    numerically exact (shift registers).
    """
    p = ct.ss(model.plant)
    c = ct.feedback(ct.ss(model.filter), ct.ss(model.model), sign=+1)
    return ct.feedback(
        ct.ss(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), [[1.0]], p.dt), c * p
    )


def feed_step(
    model: FeedLoopModel, *, model_error: float = 0.03, n_samples: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Relative pitch error after a step of the model error (``control.forced_response``).

    Parameters
    ----------
    model : FeedLoopModel
        The loop at one feed.
    model_error : float
        Relative model error stepped in at t = 0 (0.03 = the true pitch 3 % above the model).
    n_samples : int, optional
        Length of the simulation; default 25 loop delays.

    Returns
    -------
    t_s : ndarray, shape (n,)
        Time, seconds.
    pitch_error : ndarray, shape (n,)
        ``p_meas / p* - 1``.
    """
    dt = model.plant.dt
    n = n_samples or 25 * (model.delay_samples + model.window_samples) + 20
    t = np.arange(n) * dt
    sys = feed_disturbance_response(model)
    resp = ct.forced_response(sys, T=t, U=np.full(n, math.log1p(model_error)))
    return t, np.expm1(np.asarray(resp.outputs).reshape(-1))


def settling_time_s(t_s: np.ndarray, error: np.ndarray, *, band: float) -> float:
    """First time after which ``|error|`` stays within ``band``, seconds (inf if never)."""
    outside = np.nonzero(np.abs(np.asarray(error)) > band)[0]
    if outside.size == 0:
        return float(t_s[0])
    if outside[-1] == len(t_s) - 1:
        return math.inf
    return float(t_s[outside[-1] + 1])


# -- uniformity loop ---------------------------------------------------------------------------
#: Camera distances (cutter to image centre, mm) at which the uniformity loop is documented.
DESIGN_CAMERAS_MM = (300.0, 1000.0, 2000.0)


def mode_eigenvalues(knives: int) -> np.ndarray:
    """Eigenvalues ``-4 sin^2(pi m / Z)`` of the circulant second difference, m = 0..Z-1."""
    return np.linalg.eigvalsh(second_difference(knives))


def uniformity_delay_samples(
    feed_mm_s: float,
    cfg: UniformityLoopConfig,
    *,
    cutter_to_camera_mm: float,
    window_mm: float = 40.0,
    latency_samples: int = 1,
) -> tuple[int, int]:
    """Delay ``d`` and window ``m`` (samples) from a new table to the pair that shows it.

    Returns
    -------
    (int, int)
        ``d = ceil((settle + L / V) / Ts) + latency`` and ``m = max(1, round(W / (V Ts)))``.
    """
    v = check_positive("feed_mm_s", feed_mm_s)
    ts = cfg.sample_time_s
    travel_s = cfg.settle_s + check_positive("cutter_to_camera_mm", cutter_to_camera_mm) / v
    d = math.ceil(travel_s / ts - 1e-9) + check_int("latency_samples", latency_samples, lo=0)
    m = max(1, round(check_positive("window_mm", window_mm) / (v * ts)))
    return d, m


def uniformity_loop_model(
    cfg: UniformityLoopConfig,
    feed_mm_s: float,
    *,
    cutter_to_camera_mm: float,
    window_mm: float = 40.0,
    latency_samples: int = 1,
    mode_gain: float = 1.0,
    model_delay_error_samples: int = 0,
) -> FeedLoopModel:
    """One knife mode of the uniformity loop at one feed (the feed loop's block layout).

    Parameters
    ----------
    cfg : UniformityLoopConfig
        The loop (``ki``, ``sample_time_s``, ``settle_s``).
    feed_mm_s : float
        Operating feed, mm/s.
    cutter_to_camera_mm, window_mm : float
        ``L`` and the measured window ``W``, mm.
    latency_samples : int
        Samples from the pair to the table it produces, >= 0.
    mode_gain : float
        ``alpha``, the true over the modelled gain of the mode (real; a phase error is checked
        with :func:`uniformity_closed_loop_radius`).
    model_delay_error_samples : int
        Error of the table history's timing (the model uses ``d + error``), samples.

    Returns
    -------
    FeedLoopModel
        ``plant`` = ``alpha z^-d H_m``, ``model`` = ``z^-(d + error) H_m``, ``filter`` =
        ``g / (z - 1 + g)``.
    """
    ts = cfg.sample_time_s
    d, m = uniformity_delay_samples(
        feed_mm_s, cfg, cutter_to_camera_mm=cutter_to_camera_mm, window_mm=window_mm,
        latency_samples=latency_samples,
    )
    window = _window(m, ts)
    plant = float(mode_gain) * _delay(d, ts) * window
    model = _delay(max(0, d + int(model_delay_error_samples)), ts) * window
    g = integral_gain(cfg.ki, ts, (d + 0.5 * (m - 1)) * ts)
    return FeedLoopModel(float(feed_mm_s), d, m, g, plant, model, ct.tf([g], [1.0, g - 1.0], ts))


def uniformity_closed_loop_radius(model: FeedLoopModel, mode_gain: complex = 1.0) -> float:
    """Largest closed-loop pole magnitude of one mode for a complex true/model gain ``alpha``.

    With ``N = d + m - 1`` and ``h(z) = z^(m-1) + ... + 1`` the characteristic polynomial of
    ``1 + C alpha M = 0`` is ``m z^N (z - 1 + g) + g (alpha - 1) h(z)`` (exact; the loop is stable
    iff the result is < 1). A complex ``alpha`` is a phase error of the identified actuator
    gain (a mode pair ``m``, ``Z - m`` sees ``alpha`` and its conjugate).
    """
    d, m, g = model.delay_samples, model.window_samples, model.gain
    n = d + m - 1
    poly = np.zeros(n + 2, dtype=complex)
    poly[0] = m  # m z^(N+1)
    poly[1] = m * (g - 1.0)  # m (g - 1) z^N
    poly[-m:] += g * (complex(mode_gain) - 1.0)  # h(z): z^(m-1) ... z^0
    return float(np.max(np.abs(np.roots(poly))))


@dataclass(frozen=True)
class UniformityMarginsRow:
    """One row of the uniformity loop's margins table."""

    cutter_to_camera_mm: float
    feed_mm_s: float
    delay_samples: int
    window_samples: int
    gain: float
    margins: Margins


def uniformity_loop_margins(
    cfg: UniformityLoopConfig,
    feeds_mm_s: tuple[float, ...] = DESIGN_FEEDS_MM_S,
    cameras_mm: tuple[float, ...] = DESIGN_CAMERAS_MM,
    **kwargs: float,
) -> list[UniformityMarginsRow]:
    """Margins of one knife mode at each camera distance and feed.

    ``kwargs`` go to :func:`uniformity_loop_model` (mode gain, latency, timing error).
    """
    rows = []
    for cam in cameras_mm:
        for v in feeds_mm_s:
            mdl = uniformity_loop_model(cfg, v, cutter_to_camera_mm=cam, **kwargs)
            rows.append(UniformityMarginsRow(
                float(cam), float(v), mdl.delay_samples, mdl.window_samples, mdl.gain,
                margins(feed_loop_frd(mdl)),
            ))
    return rows


# -- the identified actuator: how far off may it be ------------------------------------------------
def robust_disc_radius(model: FeedLoopModel) -> float:
    """Largest ``r``: every true/model gain ratio with ``|alpha - 1| < r`` keeps one mode stable.

    The loop of one knife mode is ``alpha L1`` (``L1`` the nominal loop, ``alpha`` complex:
    the identified gain's error in magnitude and phase; a mode pair sees ``alpha`` and its
    conjugate). With ``alpha = 1 + delta`` the return difference is ``(1 + L1)(1 + delta T)``,
    ``T = L1 / (1 + L1)``: by the small-gain theorem stable for ``|delta| max|T| < 1``. The
    radius is ``1 / max_w |T(e^jw)|`` from the frequency response (python-control FRD of
    :func:`feed_loop_frd`); the identifier's confidence ``1 - 2 sigma / |a|`` is positive only
    when two standard errors stay inside a disc of radius 1 (``controller.laws.actuator_id``).
    """
    loop = feed_loop_frd(model)
    l1 = np.asarray(loop.frdata[0, 0, :], dtype=complex)
    ok = np.isfinite(l1) & (np.abs(l1) < 1e12)  # |L| = inf at the integrator's z = 1
    t = l1[ok] / (1.0 + l1[ok])
    peak = max(float(np.max(np.abs(t))), 1.0)  # T(1) = 1 at the integrator
    return 1.0 / peak


def identified_mode_margin(model: FeedLoopModel, alpha: complex) -> float:
    """``min_w |1 + alpha L1(e^jw)|`` over both signs of frequency (the mode and its conjugate).

    The stability margin (the distance of the Nyquist curve from -1) of one knife mode when
    the true gain is ``alpha`` times the identified one; > 0 and the closed loop stable
    (:func:`uniformity_closed_loop_radius` < 1) is the design's test.
    """
    loop = feed_loop_frd(model)
    l1 = np.asarray(loop.frdata[0, 0, :], dtype=complex)
    l1 = l1[np.isfinite(l1) & (np.abs(l1) < 1e12)]
    a = complex(alpha)
    return float(min(np.min(np.abs(1.0 + a * l1)), np.min(np.abs(1.0 + a.conjugate() * l1))))


@dataclass(frozen=True)
class IdentifiedDiscRow:
    """The loop of one mode at one operating point against the identifier's 2-sigma disc."""

    cutter_to_camera_mm: float
    feed_mm_s: float
    robust_radius: float
    worst_pole_radius: float
    worst_margin: float


def identified_disc_rows(
    cfg: UniformityLoopConfig,
    disc: float = 0.5,
    feeds_mm_s: tuple[float, ...] = DESIGN_FEEDS_MM_S,
    cameras_mm: tuple[float, ...] = DESIGN_CAMERAS_MM,
    points: int = 24,
) -> list[IdentifiedDiscRow]:
    """Worst closed-loop pole radius and stability margin over ``|alpha - 1| = disc``.

    ``disc = 0.5``: a mode at confidence 0 (two standard errors = half the gain) whose true
    gain lies two standard errors off in any direction.
    """
    rows = []
    for cam in cameras_mm:
        for v in feeds_mm_s:
            mdl = uniformity_loop_model(cfg, v, cutter_to_camera_mm=cam)
            alphas = [1.0 + disc * complex(math.cos(th), math.sin(th))
                      for th in np.linspace(0.0, 2.0 * math.pi, points, endpoint=False)]
            rows.append(IdentifiedDiscRow(
                float(cam), float(v), robust_disc_radius(mdl),
                max(uniformity_closed_loop_radius(mdl, a) for a in alphas),
                min(identified_mode_margin(mdl, a) for a in alphas),
            ))
    return rows


def identified_disc_markdown(rows: list[IdentifiedDiscRow], disc: float) -> str:
    """Markdown table of :func:`identified_disc_rows`."""
    out = [
        f"| camera mm | feed mm/s | robust disc radius | worst pole radius, abs(alpha-1) = "
        f"{disc:g} | worst min abs(1+L) |",
        "|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        out.append(f"| {r.cutter_to_camera_mm:.0f} | {r.feed_mm_s:.0f} | {r.robust_radius:.2f} "
                   f"| {r.worst_pole_radius:.3f} | {r.worst_margin:.2f} |")
    return "\n".join(out)


# -- report ------------------------------------------------------------------------------------
def _fmt(x: float, digits: int = 1) -> str:
    return "inf" if not math.isfinite(x) else f"{x:.{digits}f}"


def feed_margins_markdown(rows: list[FeedMarginsRow], ts: float) -> str:
    """Markdown table of feed-loop margins."""
    out = [
        "| feed mm/s | delay d (samples) | window m | gain g | GM dB | PM deg | min abs(1+L) "
        "| w_gc rad/s | delay margin s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        m = r.margins
        out.append(
            f"| {r.feed_mm_s:.0f} | {r.delay_samples} | {r.window_samples} | {r.gain:.4f} "
            f"| {_fmt(m.gain_margin_db)} | {_fmt(m.phase_margin_deg)} | {m.stability_margin:.2f} "
            f"| {_fmt(m.gain_crossover_rad_s, 3)} | {_fmt(m.delay_margin_s, 2)} |"
        )
    return "\n".join(out)


def uniformity_margins_markdown(rows: list[UniformityMarginsRow]) -> str:
    """Markdown table of the uniformity loop's margins."""
    out = [
        "| camera mm | feed mm/s | delay d | window m | gain g | GM dB | PM deg | min abs(1+L) "
        "| delay margin s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        m = r.margins
        out.append(
            f"| {r.cutter_to_camera_mm:.0f} | {r.feed_mm_s:.0f} | {r.delay_samples} "
            f"| {r.window_samples} | {r.gain:.4f} | {_fmt(m.gain_margin_db)} "
            f"| {_fmt(m.phase_margin_deg)} | {m.stability_margin:.2f} "
            f"| {_fmt(m.delay_margin_s, 2)} |"
        )
    return "\n".join(out)


def main() -> None:
    """Print the design tables (nominal and robustness cases) for ``docs/control_design.md``."""
    cfg = FeedLoopConfig()
    print(f"## Feed loop, nominal (ki = {cfg.ki}, Ts = {cfg.sample_time_s} s, 5 Hz drive)\n")
    print(feed_margins_markdown(feed_loop_margins(cfg), cfg.sample_time_s))
    cases = {
        "controller delay model 1 sample short": dict(model_delay_error_samples=-1),
        "controller delay model 1 sample long": dict(model_delay_error_samples=+1),
        "2nd-order drive, 2 Hz": dict(plant=FeedPlant(drive_bandwidth_hz=2.0, drive_order=2)),
        "drive 10 Hz": dict(plant=FeedPlant(drive_bandwidth_hz=10.0)),
        "latency 2 samples (modelled)": dict(plant=FeedPlant(latency_samples=2)),
        "gain 1.5x": dict(gain_scale=1.5),
    }
    for name, kw in cases.items():
        print(f"\n## Feed loop, {name}\n")
        print(feed_margins_markdown(feed_loop_margins(cfg, **kw), cfg.sample_time_s))
    print("\n## Feed loop, step of the model error (+3 %), nominal\n")
    print("| feed mm/s | final error | undershoot | settling to 5 % s | board m |")
    print("|---:|---:|---:|---:|---:|")
    for v in DESIGN_FEEDS_MM_S:
        t, e = feed_step(feed_loop_model(cfg, v), model_error=0.03)
        settle = settling_time_s(t, e, band=0.05 * 0.03)
        print(
            f"| {v:.0f} | {e[-1]:+.1e} | {min(float(e.min()), 0.0) / 0.03:.1%} | {settle:.1f} "
            f"| {settle * v / 1000:.2f} |"
        )
    ucfg = UniformityLoopConfig()
    print(f"\n## Uniformity loop, nominal (ki = {ucfg.ki})\n")
    print(uniformity_margins_markdown(uniformity_loop_margins(ucfg)))
    ucases = {
        "mode gain 0.5 (actuator weaker than identified)": dict(mode_gain=0.5),
        "mode gain 1.5 (actuator stronger than identified)": dict(mode_gain=1.5),
        "table timing 1 sample late": dict(model_delay_error_samples=1),
        "table timing 1 sample early": dict(model_delay_error_samples=-1),
        "latency 2 samples": dict(latency_samples=2),
    }
    for name, kw in ucases.items():
        rows = uniformity_loop_margins(ucfg, **kw)
        gm = min(r.margins.gain_margin_db for r in rows)
        pm = min(r.margins.phase_margin_deg for r in rows)
        print(f"\nuniformity loop, {name}: worst GM {_fmt(gm)} dB, worst PM {_fmt(pm)} deg")
    print("\nmode eigenvalues, Z = 4:", np.round(mode_eigenvalues(4), 3))
    print("\n## Uniformity loop, the identified gain two standard errors off (confidence 0)\n")
    print(identified_disc_markdown(identified_disc_rows(ucfg, 0.5), 0.5))


if __name__ == "__main__":  # pragma: no cover
    main()
