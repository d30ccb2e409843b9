"""The shift estimators the registration composes.

They serve :class:`vision.registration.registrar.Registrar`.

Each works on one representation of the pair and gives a normalised score curve or a fitted
delay (the method: :mod:`vision.registration.registrar`):

- the **texture** stage's correlation (:func:`shading_free_texture`, :class:`TextureCorrelator`:
  the shading divided out, band-passed rows of A slid over B);
- the **column profiles'** robust correlation of their first differences
  (:func:`robust_correlation`, :func:`window_peak`) and the mark period they show
  (:func:`mark_period_px`);
- the **shading alone** when the wood shows no albedo (:func:`shading_shift`);
- the **fine** sign-free cross-spectrum delay fit (:class:`FineShiftFit`);

with the peak helpers they share (:func:`_parabolic_peak`, :func:`_second_peak`,
:func:`_confidence`). Array in, array out; the set-up (FFT sizes, phasors, kernels) is made
once per width in the two classes.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from core.errors import RegistrationError
from vision import ffts, kernels


def shading_free_texture(rows: np.ndarray, profile: np.ndarray, *,
                         centre: bool = True) -> np.ndarray:
    """Albedo texture of an image with the column shading divided out.

    Parameters
    ----------
    rows : ndarray, shape (n_rows, width)
        Undistorted image rows (or binned rows).
    profile : ndarray, shape (width,)
        Column profile of the same image (mean over rows, same scale as ``rows``).
    centre : bool, optional
        Remove each row's mean (default).  The registrar's band-pass removes any constant
        per row by itself, so the measurement skips this pass.

    Returns
    -------
    ndarray, shape (n_rows, width), float32
        ``rows / profile - 1``, with each row's mean removed when ``centre``.
    """
    prof = np.asarray(profile, dtype=np.float32)
    safe = np.where(prof > 0, prof, np.float32(1.0))
    inv = np.where(prof > 0, np.float32(1.0) / safe, np.float32(0.0)).astype(np.float32)
    tex = np.multiply(rows, inv[None, :], dtype=np.float32)
    if centre:
        tex -= tex.mean(axis=1, keepdims=True)
    else:
        tex -= np.float32(1.0)
    return tex


def _fast_len_5(n: int) -> int:
    """Smallest 5-smooth integer >= n (fast for every FFT library)."""
    best = 1 << max(0, math.ceil(math.log2(max(n, 1))))
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def _parabolic_peak(values: np.ndarray, i: int) -> tuple[float, float]:
    """Sub-sample offset and height of the parabola through ``values[i-1:i+2]``."""
    y0, y1, y2 = float(values[i - 1]), float(values[i]), float(values[i + 1])
    curv = y0 - 2.0 * y1 + y2
    frac = 0.5 * (y0 - y2) / curv if curv < 0 else 0.0
    frac = min(0.5, max(-0.5, frac))
    return frac, y1 - 0.25 * (y0 - y2) * frac


def _highpassed_log(profile: np.ndarray, highpass_px: int) -> np.ndarray:
    lp = np.log(np.maximum(np.asarray(profile, dtype=np.float64), 1e-12))[None, :]
    return (lp - cv2.blur(lp, (highpass_px, 1), borderType=cv2.BORDER_REFLECT))[0]


def shading_shift(
    profile_a: np.ndarray,
    profile_b: np.ndarray,
    *,
    guess_px: float,
    reach_px: int = 4,
    highpass_px: int = 41,
) -> tuple[float, float]:
    """Fine shift from the cuttermark shading of the two column profiles.

    The shading of the two lights has opposite signs (``log I_A ~ -p tan(sigma)``,
    ``log I_B ~ +p tan(sigma)``), and the sharp intensity steps at the cusps pin it to a small
    fraction of a pixel.  It is periodic, though, so only a shift already known to better than
    half a mark (from the texture) can be refined: the best *anti*-correlation of the high-passed
    log-profiles within ``guess_px +- reach_px``.

    Parameters
    ----------
    profile_a, profile_b : ndarray, shape (width,)
        Positive column profiles of A and B in the camera frame.
    guess_px : float
        Coarse shift, pixels.
    reach_px : int, optional
        Half-width of the search, pixels.
    highpass_px : int, optional
        Length of the running mean removed from the log-profiles (illumination, figure).

    Returns
    -------
    shift_px : float
        Refined shift; NaN when the best anti-correlation lies on the edge of the window.
    score : float
        Best anti-correlation found (1: the shading is exactly mirrored).

    Raises
    ------
    RegistrationError
        The overlap is too small.
    """
    la = _highpassed_log(profile_a, highpass_px)
    lb = _highpassed_log(profile_b, highpass_px)
    w = la.size
    centre = int(round(guess_px))
    r = int(reach_px) + 1
    # A common stretch of A whose partners lie inside B for every lag in the window.
    a0 = max(0, -(centre - r))
    a1 = min(w, w - (centre + r))
    if a1 - a0 < 16:
        raise RegistrationError(f"shift {guess_px:.1f} px leaves too little overlap to refine")
    a = la[a0:a1]
    length = a1 - a0
    lags = np.arange(centre - r, centre + r + 1)
    windows = np.lib.stride_tricks.sliding_window_view(lb, length)[a0 + lags]
    dots = windows @ a
    c2 = np.concatenate(([0.0], np.cumsum(lb * lb)))
    energy_b = c2[a0 + lags + length] - c2[a0 + lags]
    den = np.sqrt(np.maximum(energy_b * float(np.dot(a, a)), 1e-300))
    scores = -dots / den
    i = int(np.argmax(scores))
    if i == 0 or i == scores.size - 1:
        return math.nan, float(scores[i])
    frac, peak = _parabolic_peak(scores, i)
    return float(lags[i]) + frac, peak


def log_difference(profile: np.ndarray) -> np.ndarray:
    """First difference of the log of a positive profile, float64, shape (n - 1,)."""
    p = np.asarray(profile, dtype=np.float64)
    logs = np.log(np.maximum(p, 1e-12))
    return logs[1:] - logs[:-1]  # np.diff's subtraction, without its overhead


def robust_standardise(values: np.ndarray) -> np.ndarray:
    """``(values - median) / (1.4826 MAD)``; zeros when the MAD vanishes."""
    med = float(np.median(values))
    dev = values - med
    scale = 1.4826 * float(np.median(np.abs(dev)))
    if not scale > 0:
        return np.zeros_like(dev)
    return dev / scale


def _second_peak(values: np.ndarray, i: int) -> float:
    """Best local maximum of ``values`` outside the main lobe (contiguous stretch > half peak)."""
    half = 0.5 * float(values[i])
    v = values.tolist()  # the lobe's walk on Python floats, not numpy scalars
    left = i
    while left > 0 and v[left - 1] > half:
        left -= 1
    right = i
    while right < len(v) - 1 and v[right + 1] > half:
        right += 1
    inner = values[1:-1]
    is_max = (inner >= values[:-2]) & (inner >= values[2:])
    is_max[max(0, left - 1) : right] = False
    return float(inner[is_max].max()) if np.any(is_max) else 0.0


def _confidence(peak: float, second: float) -> float:
    """Peak correlation times its uniqueness ``1 - second / peak``, in [0, 1]."""
    if not peak > 0:
        return 0.0
    uniqueness = min(1.0, max(0.0, 1.0 - max(second, 0.0) / peak))
    return min(peak, 1.0) * uniqueness


def mark_period_px(profile: np.ndarray) -> float:
    """Spacing of the cuttermarks from a column profile (NaN when there is no clear one).

    The first difference of the log-profile is, inside every mark, a constant (the slope grows
    as 1/R) and, at every cusp, a spike; its self-correlation peaks at the mark spacing.

    Parameters
    ----------
    profile : ndarray, shape (width,)
        Positive column profile.

    Returns
    -------
    float
        The first local maximum (>= 0.2 of lag 0) after the first negative value of the
        self-correlation, sub-pixel, pixels; NaN when there is none below ``width / 3``.
    """
    g = log_difference(profile)
    g = g - g.mean()
    n = g.size
    nf = _fast_len_5(2 * n)
    spec = ffts.rfft(g, nf)
    ac = ffts.irfft(spec.real**2 + spec.imag**2, nf)[: n // 3]
    if ac.size < 4 or not ac[0] > 0:
        return math.nan
    ac = ac / ac[0]
    neg = np.flatnonzero(ac < 0)
    if neg.size == 0:
        return math.nan
    for k in range(int(neg[0]), ac.size - 1):
        if ac[k] >= 0.2 and ac[k] >= ac[k - 1] and ac[k] >= ac[k + 1]:
            frac, _ = _parabolic_peak(ac, k)
            return k + frac
    return math.nan


def robust_correlation(a: np.ndarray, b: np.ndarray, starts: np.ndarray, trim: float
                        ) -> np.ndarray:
    """Gnanadesikan-Kettenring correlation of ``a`` with ``b[k:k + len(a)]`` for each start.

    ``(S(a + b) - S(b - a)) / (S(a + b) + S(b - a))``, ``S`` the sum of the smallest ``trim``
    fraction of the squares (module docstring); shape ``(len(starts),)``.
    """
    n = a.size
    keep = max(1, int(trim * n))
    windows = np.lib.stride_tricks.sliding_window_view(b, n)[starts]
    squares = np.empty((2, *windows.shape), dtype=np.float32)  # (a + b)^2, (b - a)^2
    np.add(windows, a, out=squares[0])
    np.subtract(windows, a, out=squares[1])
    squares *= squares
    squares.partition(keep - 1, axis=2)
    s_both, s_diff = squares[:, :, :keep].sum(axis=2, dtype=np.float64)
    return (s_both - s_diff) / np.maximum(s_both + s_diff, 1e-300)


def window_peak(
    scores: np.ndarray, lags: np.ndarray, what: str, guess: float, reach: float
) -> tuple[float, float, float]:
    """Sub-pixel shift, peak score and confidence of a correlation over a window of lags.

    A peak on the window's edge means the true shift lies outside the search window: an error.
    """
    i = int(np.argmax(scores))
    if i == 0 or i == len(scores) - 1:
        raise RegistrationError(
            f"no {what} correlation peak within {reach:.0f} px of the encoder shift "
            f"{guess:.1f} px (best at the edge, lag {int(lags[i])} px)"
        )
    frac, peak = _parabolic_peak(scores, i)
    return float(lags[i]) + frac, peak, _confidence(peak, _second_peak(scores, i))


class FineShiftFit:
    """The fine stage: the sign-free cross-spectrum delay fit (set up once per width).

    Parameters
    ----------
    width : int
        Length of the column profiles, pixels.
    fine_px : int
        Half-width of the window of delays searched around the coarse shift, pixels.
    max_frequency : float
        Highest frequency used, cycles per pixel.
    min_overlap_px : int
        Smallest overlap of the two profiles, pixels.
    """

    _FINE_STEP_PX = 0.1  # grid of the fine fit before its parabolic peak

    def __init__(self, width: int, *, fine_px: int, max_frequency: float,
                 min_overlap_px: int) -> None:
        self.fine_px = int(fine_px)
        self.min_overlap_px = int(min_overlap_px)
        self.nfft = _fast_len_5(2 * int(width))
        # Frequencies used, the grid of delays, and their doubled-phase phasors.
        self._kmax = int(max_frequency * self.nfft) + 1
        freq = np.arange(self._kmax) / self.nfft
        steps = int(round(self.fine_px / self._FINE_STEP_PX))
        self._fine_grid = np.arange(-steps, steps + 1) * self._FINE_STEP_PX
        phasor = np.exp(4j * np.pi * self._fine_grid[:, None] * freq[None, :])
        # float32: half the memory a pair streams through (the sums hold ~1e-6 relative)
        self._fine_real = np.ascontiguousarray(
            np.concatenate([phasor.real, -phasor.imag], axis=1), dtype=np.float32)
        self._tapers: dict[int, np.ndarray] = {}

    def _taper(self, n: int) -> np.ndarray:
        taper = self._tapers.get(n)
        if taper is None:
            if len(self._tapers) > 64:
                self._tapers.clear()
            taper = self._tapers[n] = np.hanning(n)
        return taper

    def __call__(self, la: np.ndarray, lb: np.ndarray, guess: float) -> tuple[float, float]:
        """Fine shift within ``+-fine_px`` of ``round(guess)`` (:meth:`Registrar.fine`).

        Parameters
        ----------
        la, lb : ndarray, shape (width - 1,)
            First differences of the log column profiles of A and B.
        guess : float
            Coarse shift, pixels.

        Returns
        -------
        shift_px, score : float
            As :meth:`Registrar.fine`.
        """
        w = la.size
        i0 = int(round(guess))
        m = self.fine_px + 2
        u0 = max(0, -i0) + m
        u1 = min(w, w - i0) - m
        n = u1 - u0
        if n < self.min_overlap_px:
            raise RegistrationError(f"shift {guess:.1f} px leaves too little overlap to refine")
        taper = self._taper(n)
        both = np.empty((2, n))
        both[0] = la[u0:u1]
        both[1] = lb[u0 + i0 : u1 + i0]
        for row in both:  # both.mean(axis=1)'s pairwise row sums over n, without its overhead
            row -= row.sum() / n
        both *= taper
        k = self._kmax
        spec = ffts.rfft(both, self.nfft, axis=1)[:, :k]
        # |X| e^(2i arg X): the phase doubled, so frequencies where the mirrored shading
        # dominates (X < 0 at the true delay) vote with the albedo's (X > 0); Re(P @ D) as
        # one real product -- all in one compiled loop (no BLAS threads, no temporaries).
        score = np.empty(self._fine_real.shape[0])
        total = kernels.delay_scores(spec[0], spec[1], self._fine_real, score)
        if not total > 0:
            return math.nan, 0.0
        j = int(np.argmax(score))
        if j == 0 or j == score.size - 1:
            return math.nan, float(score[j]) / total
        frac, peak = _parabolic_peak(score, j)
        return i0 + float(self._fine_grid[j]) + frac * self._FINE_STEP_PX, peak / total


class TextureCorrelator:
    """The texture stage's correlation: band-pass and normalised cross-correlation of the rows.

    Parameters
    ----------
    width : int
        Number of columns of the textures.
    band_px : tuple of int
        Default ``(short, long)`` band-pass lengths (:class:`Registrar`).
    """

    def __init__(self, width: int, *, band_px: tuple[int, int]) -> None:
        self.width = int(width)
        self.band_px = band_px
        self._boxes: dict[int, np.ndarray] = {}
        # A fixed stretch of A slides over B without ever leaving it, so a circular
        # correlation of length >= width is exact (no zero-padding to 2 x width);
        # a multiple of 16 with small factors suits OpenCV's DFT best.
        self.nfft = 16 * cv2.getOptimalDFTSize((self.width + 15) // 16)

    def band_pass(self, texture: np.ndarray, band_px: tuple[int, int] | None = None
                  ) -> np.ndarray:
        """Difference of running means along x (lengths ``band_px``), edges reflected.

        The short mean goes through ``cv2.filter2D`` (a 1 x short kernel, vectorised), which
        on this OpenCV runs several times faster than ``cv2.blur`` for short boxes.
        """
        t = np.asarray(texture, dtype=np.float32)
        short, long = self.band_px if band_px is None else band_px
        smooth = cv2.blur(t, (long, 1), borderType=cv2.BORDER_REFLECT)
        if short <= 1:
            return t - smooth
        kernel = self._boxes.get(short)
        if kernel is None:
            kernel = self._boxes[short] = np.full((1, short), 1.0 / short, dtype=np.float32)
        out = cv2.filter2D(t, -1, kernel, borderType=cv2.BORDER_REFLECT)
        return cv2.subtract(out, smooth, dst=out)

    def __call__(self, ta: np.ndarray, tb: np.ndarray, lags: np.ndarray, u0: int, u1: int,
                 band: tuple[int, int]) -> np.ndarray:
        """Normalised correlation of the band-passed textures at ``lags``, shape (len(lags),).

        ``ta``, ``tb`` (float32, shape (n_rows, width)); the stretch ``u0:u1`` of A slides
        over B.  Raises :class:`~core.errors.RegistrationError` when A has no texture.
        """
        w = self.width
        r = ta.shape[0]
        # A's rows over B's: every step below works row by row, so one call does both.
        both = self.band_pass(np.concatenate((ta, tb)), band)
        ta, tb = both[:r], both[r:]
        n = self.nfft
        # cc[m] = sum_rows sum_i a[i] b[i + m]: lag L sits at m = u0 + L, and i + m never
        # passes the end of B (u1 + hi <= width <= n), so the circular correlation is exact.
        # OpenCV's row DFTs (packed real spectra) run ~3x faster than scipy's here.
        pad = np.zeros((2 * r, n), dtype=np.float32)
        pad[:r, : u1 - u0] = ta[:, u0:u1]
        pad[r:, :w] = tb
        spec = cv2.dft(pad, flags=cv2.DFT_ROWS)
        pad_a = pad[:r]
        cross = cv2.mulSpectrums(spec[r:], spec[:r], cv2.DFT_ROWS, conjB=True)
        total = cv2.reduce(cross, 0, cv2.REDUCE_SUM, dtype=cv2.CV_64F)
        cc = cv2.idft(total, flags=cv2.DFT_SCALE | cv2.DFT_REAL_OUTPUT).ravel()
        col_b = cv2.reduce(cv2.multiply(tb, tb), 0, cv2.REDUCE_SUM, dtype=cv2.CV_64F).ravel()
        cum_b = np.empty(col_b.size + 1)
        cum_b[0] = 0.0
        np.cumsum(col_b, out=cum_b[1:])
        energy_a = float(cv2.reduce(cv2.multiply(pad_a, pad_a), 0, cv2.REDUCE_SUM,
                                    dtype=cv2.CV_64F).sum())
        energy_b = cum_b[u1 + lags] - cum_b[u0 + lags]
        den = np.sqrt(np.maximum(energy_a * energy_b, 1e-300))
        if not energy_a > 0:
            raise RegistrationError("the images have no texture to register on")
        return cc[u0 + lags] / den
