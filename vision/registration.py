"""Registration of the two images of a pair: encoder shift (seed Eq. 5-6), refined from the images.

The encoder gives the shift ``d = px_per_count * (counts_b - counts_a)`` (counter wrap handled by a
signed modular difference).  Belt slip or a bad count can make it wrong by tens of pixels, so it is
refined from the images themselves, in two stages:

1. **Texture** (coarse, unambiguous).  Correlating the raw images or their column profiles locks
   onto the shading of the nearly periodic cuttermarks, which moreover has opposite signs in A and
   B.  But the shading depends on the column only (the marks run straight across, q = 0), while
   the wood's albedo texture (fibres, pores, grain) varies along both axes and moves with the
   board.  Dividing each undistorted image by its own column profile removes the shading exactly
   and leaves ``I(u, v) / P(u) - 1``.  Band-passed along x (pixel noise and the fibre roughness,
   whose shading is mirrored between the lights, out; slow grain wander and fall-off out), the
   two textures are cross-correlated over the lags ``d_enc +- (search_px + margin_px)``, with one
   fixed stretch of A sliding over B so that image edges never enter the sums (otherwise texture
   that is nearly constant along x, like grain stripes, pulls the peak toward lag 0).  Normalised
   correlation, parabolic sub-pixel peak; confidence = peak correlation x uniqueness (one minus
   the best other local maximum over the peak).  Too low, or a peak on the window's edge, is a
   :class:`~planer.errors.RegistrationError`, never a guess.
2. **Shading** (fine).  The sharp intensity steps at the cusps pin the shift to a small fraction of
   a pixel: the log column profiles, high-passed, are *anti*-correlated (the two lights see
   mirrored shading) within ``+-fine_px`` of the texture's shift, again with a parabolic peak.  A
   pair without marks keeps the texture's shift; strong shading that does not line up within the
   window is an error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
import scipy.fft

from planer.checks import check_finite, check_int, check_positive, check_range
from planer.errors import RegistrationError


@dataclass(frozen=True)
class Registration:
    """Result of registering a pair.

    Attributes
    ----------
    shift_px : float
        Shift used: a point at undistorted column ``u`` of A is at ``u + shift_px`` in B.
    confidence : float
        In [0, 1]: the normalised texture correlation at the peak times its uniqueness,
        ``1 - second_peak / peak`` (second peak: the best local maximum outside the main lobe).
    encoder_shift_px : float
        Shift from the encoder counts alone (seed Eq. 5-6).
    peak_ncc : float
        Normalised cross-correlation of the two textures at their best shift.
    shading_score : float
        Anti-correlation of the two profiles' shading at the chosen shift (NaN: not refined).
    texture_shift_px : float
        Shift found by the texture alone (NaN when it is ``shift_px``).
    """

    shift_px: float
    confidence: float
    encoder_shift_px: float
    peak_ncc: float = math.nan
    shading_score: float = math.nan
    texture_shift_px: float = math.nan


def encoder_shift_px(
    counts_a: int, counts_b: int, *, px_per_count: float, counter_bits: int = 32
) -> float:
    """Image shift from the encoder counts latched at the two triggers (seed Eq. 5-6).

    Parameters
    ----------
    counts_a, counts_b : int
        Counter values at the triggers of image A and image B; either raw unsigned values in
        ``[0, 2**bits)`` or two's-complement signed values in ``[-2**(bits-1), 0)``.
    px_per_count : float
        Image shift per encoder count, pixels (seed: SR x mm per count).
    counter_bits : int, optional
        Width of the hardware counter, 16 or 32.  The difference is taken modulo
        ``2**counter_bits`` and read as signed, so it is right across a wrap-around.

    Returns
    -------
    float
        Shift ``d`` in pixels (positive when the board moved toward +x).
    """
    bits = check_int("counter_bits", counter_bits)
    if bits not in (16, 32):
        raise ValueError(f"counter_bits must be 16 or 32, got {bits}")
    modulus = 1 << bits
    a = check_int("counts_a", counts_a, lo=-(modulus >> 1), hi=modulus - 1)
    b = check_int("counts_b", counts_b, lo=-(modulus >> 1), hi=modulus - 1)
    scale = check_positive("px_per_count", px_per_count)
    diff = (b - a) % modulus
    if diff >= modulus >> 1:
        diff -= modulus
    return diff * scale


def shading_free_texture(rows: np.ndarray, profile: np.ndarray) -> np.ndarray:
    """Albedo texture of an image with the column shading divided out.

    Parameters
    ----------
    rows : ndarray, shape (n_rows, width)
        Undistorted image rows (or binned rows).
    profile : ndarray, shape (width,)
        Column profile of the same image (mean over rows, same scale as ``rows``).

    Returns
    -------
    ndarray, shape (n_rows, width), float32
        ``rows / profile - 1`` with each row's mean removed.
    """
    prof = np.asarray(profile, dtype=np.float32)
    inv = np.where(prof > 0, np.float32(1.0) / np.where(prof > 0, prof, 1.0), np.float32(0.0))
    tex = np.asarray(rows, dtype=np.float32) * inv.astype(np.float32)[None, :]
    tex -= tex.mean(axis=1, keepdims=True)
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
    frac = float(np.clip(frac, -0.5, 0.5))
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


class Registrar:
    """Refines the encoder shift of a pair from its images (set up once per width).

    Two stages: the albedo texture (not periodic, so it cannot lock onto the wrong mark) finds
    the shift within ``+-(search_px + margin_px)`` of the encoder's to a pixel or two; the
    cuttermark shading of the column profiles (sharp, but periodic) then refines it within
    ``+-fine_px`` to a small fraction of a pixel.

    Parameters
    ----------
    width : int
        Number of columns of the textures and profiles.
    search_px : float, optional
        Largest expected error of the encoder shift, pixels.
    margin_px : float, optional
        Extra search range beyond ``search_px``.
    min_confidence : float, optional
        Pairs whose texture confidence is lower raise :class:`RegistrationError`.
    min_peak_ncc : float, optional
        Pairs whose texture correlation at the peak is lower raise :class:`RegistrationError`.
    min_overlap_px : int, optional
        Smallest overlap of the two images, pixels.
    fine_px : int, optional
        Half-width of the shading refinement, pixels.
    min_shading_score : float, optional
        Below this anti-correlation of the shading the refinement is not trusted and the
        texture shift is kept.
    band_px : tuple of int, optional
        ``(short, long)``: the textures are band-passed along x by the difference of running
        means of these lengths.  The short one removes pixel noise and the fine fibre roughness,
        whose shading has opposite signs in A and B; the long one the slowly wandering grain
        stripes and the illumination fall-off along y that survive the column normalisation.
    """

    def __init__(
        self,
        width: int,
        *,
        search_px: float = 20.0,
        margin_px: float = 4.0,
        min_confidence: float = 0.2,
        min_peak_ncc: float = 0.25,
        min_overlap_px: int = 32,
        fine_px: int = 4,
        min_shading_score: float = 0.5,
        band_px: tuple[int, int] = (5, 61),
    ) -> None:
        self.width = check_int("width", width, lo=16)
        self.search_px = check_positive("search_px", search_px, allow_zero=True)
        self.margin_px = check_positive("margin_px", margin_px, allow_zero=True)
        self.min_confidence = check_range("min_confidence", min_confidence, 0.0, 1.0)
        self.min_peak_ncc = check_range("min_peak_ncc", min_peak_ncc, -1.0, 1.0)
        self.min_overlap_px = check_int("min_overlap_px", min_overlap_px, lo=8)
        self.fine_px = check_int("fine_px", fine_px, lo=1)
        self.min_shading_score = check_range("min_shading_score", min_shading_score, -1.0, 1.0)
        short, long = (int(band_px[0]), int(band_px[1]))
        if not 1 <= short < long < self.width:
            raise ValueError(f"band_px must be (short, long) with 1 <= short < long < width, "
                             f"got {band_px}")
        self.band_px = (short, long)
        self.nfft = _fast_len_5(2 * self.width)

    def band_pass(self, texture: np.ndarray) -> np.ndarray:
        """Difference of running means along x (lengths ``band_px``), edges reflected."""
        t = np.asarray(texture, dtype=np.float32)
        short, long = self.band_px
        smooth = cv2.blur(t, (long, 1), borderType=cv2.BORDER_REFLECT)
        if short > 1:
            t = cv2.blur(t, (short, 1), borderType=cv2.BORDER_REFLECT)
        return t - smooth

    def coarse(
        self, texture_a: np.ndarray, texture_b: np.ndarray, *, encoder_shift_px: float
    ) -> Registration:
        """Shift from the textures alone.

        Parameters
        ----------
        texture_a, texture_b : ndarray, shape (n_rows, width)
            Shading-free textures of A and B (:func:`shading_free_texture`), same rows.
        encoder_shift_px : float
            Shift from the encoder, pixels.

        Returns
        -------
        Registration

        Raises
        ------
        RegistrationError
            The peak lies on the edge of the search window, or its confidence or correlation
            is too low.
        """
        guess = check_finite("encoder_shift_px", encoder_shift_px)
        w = self.width
        ta = np.asarray(texture_a, dtype=np.float32)
        tb = np.asarray(texture_b, dtype=np.float32)
        if ta.shape != tb.shape or ta.ndim != 2 or ta.shape[1] != w:
            raise ValueError(
                f"textures must both have shape (rows, {w}), got {ta.shape} and {tb.shape}"
            )
        reach = self.search_px + self.margin_px
        lo = max(math.floor(guess - reach), -(w - self.min_overlap_px))
        hi = min(math.ceil(guess + reach), w - self.min_overlap_px)
        # One fixed stretch U of A whose partners u + lag lie inside B for every lag searched:
        # B's edges never enter the sums, so texture that is nearly constant along x (grain
        # stripes) correlates alike at every lag instead of pulling the peak toward lag 0.
        u0, u1 = max(0, -lo), min(w, w - hi)
        if hi - lo < 2 or u1 - u0 < self.min_overlap_px:
            raise RegistrationError(
                f"encoder shift {guess:.1f} px leaves less than {self.min_overlap_px} px of "
                f"overlap in images {w} px wide"
            )
        ta = self.band_pass(ta)
        tb = self.band_pass(tb)
        a = np.zeros_like(ta)
        a[:, u0:u1] = ta[:, u0:u1]
        n = self.nfft
        fa = scipy.fft.rfft(a, n=n, axis=1)
        fb = scipy.fft.rfft(tb, n=n, axis=1)
        cc = scipy.fft.irfft(np.einsum("ij,ij->j", fa.conj(), fb), n=n)
        lags = np.arange(lo, hi + 1)
        col_b = np.einsum("ij,ij->j", tb, tb, dtype=np.float64)
        cum_b = np.concatenate(([0.0], np.cumsum(col_b)))
        energy_a = float(np.einsum("ij,ij->", a, a, dtype=np.float64))
        energy_b = cum_b[u1 + lags] - cum_b[u0 + lags]
        den = np.sqrt(np.maximum(energy_a * energy_b, 1e-300))
        if not energy_a > 0:
            raise RegistrationError("the images have no texture to register on")
        ncc = cc[lags % n] / den
        i = int(np.argmax(ncc))
        if i == 0 or i == len(ncc) - 1:
            raise RegistrationError(
                f"no texture correlation peak within {reach:.0f} px of the encoder shift "
                f"{guess:.1f} px (best at the edge, lag {int(lags[i])} px)"
            )
        frac, peak_ncc = _parabolic_peak(ncc, i)
        shift = float(lags[i]) + frac
        # Second-best peak: the highest local maximum outside the main lobe (the contiguous
        # stretch above half the peak).
        half = 0.5 * float(ncc[i])
        left = i
        while left > 0 and ncc[left - 1] > half:
            left -= 1
        right = i
        while right < len(ncc) - 1 and ncc[right + 1] > half:
            right += 1
        inner = ncc[1:-1]
        is_max = (inner >= ncc[:-2]) & (inner >= ncc[2:])
        is_max[max(0, left - 1) : right] = False
        second = float(inner[is_max].max()) if np.any(is_max) else 0.0
        confidence = 0.0
        if peak_ncc > 0:
            uniqueness = float(np.clip(1.0 - max(second, 0.0) / peak_ncc, 0.0, 1.0))
            confidence = min(peak_ncc, 1.0) * uniqueness
        if peak_ncc < self.min_peak_ncc or confidence < self.min_confidence:
            raise RegistrationError(
                f"cannot register the pair: texture correlation {peak_ncc:.3f} at {shift:.1f} px, "
                f"confidence {confidence:.2f} < {self.min_confidence:.2f} "
                f"(encoder shift {guess:.1f} px)"
            )
        return Registration(
            shift_px=shift, confidence=confidence, encoder_shift_px=guess, peak_ncc=peak_ncc
        )

    def __call__(
        self,
        texture_a: np.ndarray,
        texture_b: np.ndarray,
        *,
        encoder_shift_px: float,
        profile_a: np.ndarray | None = None,
        profile_b: np.ndarray | None = None,
    ) -> Registration:
        """Register a pair: texture, then (with the profiles) shading.

        Parameters
        ----------
        texture_a, texture_b : ndarray, shape (n_rows, width)
            As in :meth:`coarse`.
        encoder_shift_px : float
            Shift from the encoder, pixels.
        profile_a, profile_b : ndarray, shape (width,), optional
            Positive column profiles of A and B (camera frame) for the shading refinement.

        Returns
        -------
        Registration

        Raises
        ------
        RegistrationError
            As :meth:`coarse`, or the shading disagrees with the texture by more than
            ``fine_px``.
        """
        reg = self.coarse(texture_a, texture_b, encoder_shift_px=encoder_shift_px)
        if profile_a is None or profile_b is None:
            return reg
        shift, score = shading_shift(
            profile_a, profile_b, guess_px=reg.shift_px, reach_px=self.fine_px
        )
        if score < self.min_shading_score:  # no usable shading (no marks): texture only
            return replace(reg, shading_score=score)
        if not math.isfinite(shift):
            raise RegistrationError(
                f"the cuttermark shading does not line up within {self.fine_px} px of the "
                f"texture registration ({reg.shift_px:.1f} px)"
            )
        return replace(reg, shift_px=shift, shading_score=score, texture_shift_px=reg.shift_px)


def refine_shift(
    rows_a: np.ndarray,
    rows_b: np.ndarray,
    *,
    encoder_shift_px: float,
    search_px: float = 20.0,
    margin_px: float = 4.0,
    min_confidence: float = 0.2,
    band_px: tuple[int, int] = (5, 61),
) -> Registration:
    """Refine the encoder shift of a pair from the images (one-off convenience wrapper).

    Parameters
    ----------
    rows_a, rows_b : ndarray, shape (n_rows, width)
        Undistorted images (or binned rows) A and B.
    encoder_shift_px : float
        Shift from :func:`encoder_shift_px`.
    search_px, margin_px, min_confidence : float
        As in :class:`Registrar`.
    band_px : tuple of int
        As in :class:`Registrar`.

    Returns
    -------
    Registration
    """
    a = np.asarray(rows_a, dtype=np.float32)
    b = np.asarray(rows_b, dtype=np.float32)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"rows_a and rows_b must be 2-D of one shape, got {a.shape} and {b.shape}")
    prof_a = a.mean(axis=0, dtype=np.float64)
    prof_b = b.mean(axis=0, dtype=np.float64)
    tex_a = shading_free_texture(a, prof_a)
    tex_b = shading_free_texture(b, prof_b)
    reg = Registrar(a.shape[1], search_px=search_px, margin_px=margin_px,
                    min_confidence=min_confidence, band_px=band_px)
    return reg(tex_a, tex_b, encoder_shift_px=encoder_shift_px, profile_a=prof_a,
               profile_b=prof_b)
