"""Registration of the two images of a pair: encoder shift (seed Eq. 5-6), refined from the images.

The encoder gives the shift ``d = px_per_count * (counts_b - counts_a)`` (counter wrap handled by a
signed modular difference).  Belt slip or a bad count can make it wrong by tens of pixels, so it is
refined from the images themselves: a coarse, unambiguous estimate from the wood's albedo, then a
fine one from the column profiles.

Coarse, within ``d_enc +- (search_px + margin_px)``; two estimators of the albedo, because a board
may carry its albedo variation across the feed (2-D texture), along it (1-D), or both:

1. **Texture** (2-D).  The marks run straight across (q = 0), so their shading depends on the column
   only and dividing each undistorted image by its own column profile removes it exactly, leaving
   ``I(u, v) / P(u) - 1``.  Band-passed along x, the two textures are cross-correlated with one
   fixed stretch of A sliding over B (image edges never enter the sums, otherwise grain stripes,
   nearly constant along x, pull the peak toward lag 0).  The division also removes any albedo
   that is constant along y: a board whose albedo varies only along the feed has no texture here.
2. **Column profiles** (1-D), run when the texture is not clearly confident.  In log space
   ``log A(u) = L(u) - T(u)`` and ``log B(u + d) = L(u) + T(u)`` (albedo L, shading
   ``T ~ tan(sigma) p``).  Correlating the profiles themselves pits the albedo peak against the
   mirrored, periodic shading.  Their first differences do not: inside a mark p grows linearly
   (slope 1/R), so ``T'`` is a constant plus sparse spikes at the cusps, while ``L'`` is
   broadband.  Each first difference is centred on its median and scaled by its MAD (the constant
   goes), and the two are compared at every lag by a robust correlation (Gnanadesikan-Kettenring):
   ``rho = (S(a + b) - S(b - a)) / (S(a + b) + S(b - a))`` with ``S`` the mean of the smallest
   75 % of the squares, so the cusp spikes (opposite signs in A and B) fall in the discarded
   quarter instead of cancelling the albedo.

Each gives a normalised correlation curve; sub-pixel parabolic peak; confidence = peak x
uniqueness (one minus the best other local maximum over the peak).  The texture is taken as it is
when its confidence is at least ``strong_confidence``; otherwise the profiles are tried too, and
of the stages that pass their thresholds the more confident is used -- if both pass they must
agree within ``fine_px`` unless the more confident is itself strong.  When neither passes, the
pair is a :class:`~core.errors.RegistrationError`, never a guess -- with one exception: with
no albedo at all, the mirrored shading alone is unambiguous when the search window is narrower
than half a mark (``search_px < period / 2``), so the best anti-correlation of the shading within
``d_enc +- search_px`` is taken, with confidence ``score * (1 - 2 search_px / period)``.

Fine, within ``+-fine_px`` of the coarse shift: a delay fitted to the cross-spectrum
``X(f) = conj(F[a']) F[b']`` of the first differences of the log-profiles (tapered).  At the true
delay ``X(f) e^(2 pi i f d)`` is real, positive where the albedo dominates and negative where the
mirrored shading does; so the fit is made invariant to that sign by doubling the phase: the
delay maximises ``Re sum_f |X| e^(2 i (arg X + 2 pi f d))`` over ``f <= max_frequency``.  Albedo and
shading then both pin the delay -- the albedo's fine detail, the sharp steps at the cusps -- to a
few hundredths of a pixel.  The price is an alias at half a mark, far outside the window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from core.checks import check_finite, check_int, check_positive, check_range
from core.errors import RegistrationError
from core.units import counter_difference
from vision import kernels
from vision.registration.shift_estimators import (
    FineShiftFit,
    TextureCorrelator,
    log_difference,
    mark_period_px,
    robust_correlation,
    robust_standardise,
    shading_free_texture,
    shading_shift,
    window_peak,
)


@dataclass(frozen=True)
class Registration:
    """Result of registering a pair.

    Attributes
    ----------
    shift_px : float
        Shift used: a point at undistorted column ``u`` of A is at ``u + shift_px`` in B.
    confidence : float
        In [0, 1]: the coarse stage's normalised correlation at the peak times its uniqueness,
        ``1 - second_peak / peak`` (second peak: the best local maximum outside the main lobe);
        for ``source == "shading"``, ``score * (1 - 2 search_px / mark_period)``.
    encoder_shift_px : float
        Shift from the encoder counts alone (seed Eq. 5-6).
    peak_ncc : float
        Correlation of the coarse stage used, at its best shift.
    fine_score : float
        Sign-free coherence of the fine fit, in [-1, 1] (NaN: not refined); for
        ``source == "shading"`` the shading's anti-correlation.
    coarse_shift_px : float
        Shift found by the coarse stage (NaN when it is ``shift_px``).
    source : str
        Coarse stage used: ``"texture"`` (2-D albedo texture), ``"profile"`` (1-D column
        profiles) or ``"shading"`` (shading alone, narrow search window).
    """

    shift_px: float
    confidence: float
    encoder_shift_px: float
    peak_ncc: float = math.nan
    fine_score: float = math.nan
    coarse_shift_px: float = math.nan
    source: str = "texture"


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
    diff = counter_difference(b, a, bits=bits)
    return diff * scale


class ShiftStages:
    """The registration's stages with their thresholds, set up once per width.

    Each stage gives a :class:`Registration` or raises :class:`~core.errors.RegistrationError`
    naming why: :meth:`coarse` (the 2-D texture), :meth:`coarse_profile` (the 1-D column
    profiles), :meth:`fine` (the sign-free cross-spectrum fit); :class:`Registrar` decides
    among them. The estimators themselves are in :mod:`vision.registration.shift_estimators`.

    Parameters
    ----------
    width : int
        Number of columns of the textures and profiles.
    search_px : float, optional
        Largest expected error of the encoder shift, pixels.
    margin_px : float, optional
        Extra search range beyond ``search_px``.
    min_confidence : float, optional
        Texture registrations of lower confidence are not used.
    min_peak_ncc : float, optional
        Texture registrations of lower peak correlation are not used.
    min_overlap_px : int, optional
        Smallest overlap of the two images, pixels.
    fine_px : int, optional
        Half-width of the fine fit around the coarse shift, pixels; also how far the two coarse
        stages may disagree.  Must stay below a quarter of the mark spacing.
    min_fine_score : float, optional
        Below this coherence the fine fit is not trusted and the coarse shift is kept.
    band_px : tuple of int, optional
        ``(short, long)``: the textures are band-passed along x by the difference of running
        means of these lengths.  The short one removes pixel noise and the fine fibre roughness,
        whose shading has opposite signs in A and B; the long one the slowly wandering grain
        stripes and the illumination fall-off along y that survive the column normalisation.
    strong_confidence : float, optional
        A coarse stage at least this confident needs no second opinion.
    min_profile_confidence, min_profile_ncc : float, optional
        Thresholds of the 1-D profile registration (confidence, robust correlation at the peak).
    min_shading_score : float, optional
        Smallest anti-correlation of the shading accepted by the shading-only rule.
    max_frequency : float, optional
        Highest frequency used by the fine fit, cycles per pixel (above it pixel sampling and
        blur make the two images' fine detail differ).
    min_significance : float, optional
        Noisy images: a texture peak below ``min_peak_ncc`` is still used when it stands this
        many chance levels ``1 / sqrt(N_eff)`` above zero (``N_eff``: rows x overlap / short
        band length / 2), and its confidence is then ``0.9 uniqueness x clip((z - z_min) / 5)``
        with ``z = peak / chance level`` -- high for a strong, unique peak in many rows, falling
        with the noise.
    noisy_short_px : int, optional
        When the texture does not register with ``band_px``, it is tried once more with this
        short length (noisy images).
    quick_rows : int, optional
        The texture stage first correlates about this many evenly spread rows and stops there
        when that is already ``strong_confidence`` confident (0: always all rows).
    """

    _TRIM = 0.75  # fraction of the smallest squares kept by the robust profile correlation

    def __init__(
        self,
        width: int,
        *,
        search_px: float = 20.0,
        margin_px: float = 4.0,
        min_confidence: float = 0.2,
        min_peak_ncc: float = 0.25,
        min_overlap_px: int = 32,
        fine_px: int = 3,
        min_fine_score: float = 0.3,
        band_px: tuple[int, int] = (5, 61),
        strong_confidence: float = 0.5,
        min_profile_confidence: float = 0.25,
        min_profile_ncc: float = 0.35,
        min_shading_score: float = 0.5,
        max_frequency: float = 0.35,
        min_significance: float = 5.0,
        noisy_short_px: int = 15,
        quick_rows: int = 16,
    ) -> None:
        self.width = check_int("width", width, lo=16)
        self.search_px = check_positive("search_px", search_px, allow_zero=True)
        self.margin_px = check_positive("margin_px", margin_px, allow_zero=True)
        self.min_confidence = check_range("min_confidence", min_confidence, 0.0, 1.0)
        self.min_peak_ncc = check_range("min_peak_ncc", min_peak_ncc, -1.0, 1.0)
        self.min_overlap_px = check_int("min_overlap_px", min_overlap_px, lo=8)
        self.fine_px = check_int("fine_px", fine_px, lo=1)
        self.min_fine_score = check_range("min_fine_score", min_fine_score, -1.0, 1.0)
        self.strong_confidence = check_range("strong_confidence", strong_confidence, 0.0, 1.0)
        self.min_profile_confidence = check_range(
            "min_profile_confidence", min_profile_confidence, 0.0, 1.0
        )
        self.min_profile_ncc = check_range("min_profile_ncc", min_profile_ncc, -1.0, 1.0)
        self.min_shading_score = check_range("min_shading_score", min_shading_score, -1.0, 1.0)
        self.max_frequency = check_range("max_frequency", max_frequency, 0.05, 0.5)
        self.min_significance = check_positive("min_significance", min_significance)
        self.noisy_short_px = check_int("noisy_short_px", noisy_short_px, lo=1)
        self.quick_rows = check_int("quick_rows", quick_rows, lo=0)
        short, long = (int(band_px[0]), int(band_px[1]))
        if not 1 <= short < long < self.width:
            raise ValueError(f"band_px must be (short, long) with 1 <= short < long < width, "
                             f"got {band_px}")
        self.band_px = (short, long)
        self.fine_fit = FineShiftFit(self.width, fine_px=self.fine_px,
                                     max_frequency=self.max_frequency,
                                     min_overlap_px=self.min_overlap_px)
        self.correlator = TextureCorrelator(self.width, band_px=self.band_px)
        self._windows: dict[int, TextureCorrelator] = {}
        self.nfft = self.fine_fit.nfft
        self.coarse_nfft = self.correlator.nfft

    # -- helpers --------------------------------------------------------------------------------

    def _lag_window(self, guess: float, width: int) -> tuple[int, int, int, int]:
        """Lags ``lo..hi`` searched and the fixed stretch ``u0:u1`` of A (signals of ``width``)."""
        reach = self.search_px + self.margin_px
        lo = max(math.floor(guess - reach), -(width - self.min_overlap_px))
        hi = min(math.ceil(guess + reach), width - self.min_overlap_px)
        # One fixed stretch U of A whose partners u + lag lie inside B for every lag searched:
        # B's edges never enter the sums, so albedo that is nearly constant along x (grain
        # stripes) correlates alike at every lag instead of pulling the peak toward lag 0.
        u0, u1 = max(0, -lo), min(width, width - hi)
        if hi - lo < 2 or u1 - u0 < self.min_overlap_px:
            raise RegistrationError(
                f"encoder shift {guess:.1f} px leaves less than {self.min_overlap_px} px of "
                f"overlap in images {self.width} px wide"
            )
        return lo, hi, u0, u1

    def _profiles(self, profile_a: np.ndarray, profile_b: np.ndarray) -> tuple[np.ndarray, ...]:
        pa = np.asarray(profile_a, dtype=np.float64)
        pb = np.asarray(profile_b, dtype=np.float64)
        if pa.shape != (self.width,) or pb.shape != (self.width,):
            raise ValueError(
                f"profiles must both have shape ({self.width},), got {pa.shape} and {pb.shape}"
            )
        if not kernels.all_finite(np.ascontiguousarray(pa), np.ascontiguousarray(pb)):
            raise ValueError("profiles must be finite")
        return pa, pb

    def _window_correlator(self, width: int) -> TextureCorrelator:
        """The texture correlation of windows ``width`` columns wide (set up once)."""
        hit = self._windows.get(width)
        if hit is None:
            if len(self._windows) > 8:
                self._windows.clear()
            hit = self._windows[width] = TextureCorrelator(width, band_px=self.band_px)
        return hit

    def band_pass(self, texture: np.ndarray, band_px: tuple[int, int] | None = None
                  ) -> np.ndarray:
        """Difference of running means along x (:meth:`TextureCorrelator.band_pass`)."""
        return self.correlator.band_pass(texture, band_px)

    # -- coarse stages --------------------------------------------------------------------------

    def coarse(
        self, texture_a: np.ndarray, texture_b: np.ndarray, *, encoder_shift_px: float,
        band_px: tuple[int, int] | None = None, offset_px: int = 0,
    ) -> Registration:
        """Shift from the 2-D textures alone.

        Parameters
        ----------
        texture_a, texture_b : ndarray, shape (n_rows, width) or (n_rows, w)
            Shading-free textures of A and B (:func:`shading_free_texture`), same rows: the
            whole width, or windows of ``w <= width`` columns, B's starting ``offset_px``
            columns after A's.
        encoder_shift_px : float
            Shift from the encoder, pixels.
        band_px : tuple of int, optional
            Band-pass lengths (default ``band_px`` of the registrar).
        offset_px : int, optional
            Column of B's window minus column of A's (0 for whole-width textures); the shift
            returned is in image columns either way.

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
        off = check_int("offset_px", offset_px)
        ta = np.asarray(texture_a, dtype=np.float32)
        tb = np.asarray(texture_b, dtype=np.float32)
        w = ta.shape[1] if ta.ndim == 2 else -1
        if ta.shape != tb.shape or ta.ndim != 2 or not 16 <= w <= self.width:
            raise ValueError(
                f"textures must both have shape (rows, w), 16 <= w <= {self.width}, got "
                f"{ta.shape} and {tb.shape}"
            )
        correlator = self.correlator if w == self.width else self._window_correlator(w)
        lo, hi, u0, u1 = self._lag_window(guess - off, w)
        reach = self.search_px + self.margin_px
        band = self.band_px if band_px is None else band_px
        lags = np.arange(lo, hi + 1)
        ncc = correlator(ta, tb, lags, u0, u1, band)
        shift, peak_ncc, confidence = window_peak(ncc, lags + off, "texture", guess, reach)
        # Evidence of many rows: the chance level of the correlation falls as 1 / sqrt(N_eff).
        n_eff = ta.shape[0] * (u1 - u0) / (2.0 * band[0])
        z = peak_ncc * math.sqrt(max(n_eff, 1.0))
        if z >= self.min_significance and peak_ncc > 0:
            uniqueness = confidence / min(peak_ncc, 1.0)
            confidence = max(confidence,
                             0.9 * uniqueness * min(1.0, (z - self.min_significance) / 5))
        significant = peak_ncc >= self.min_peak_ncc or z >= self.min_significance
        if not significant or confidence < self.min_confidence:
            raise RegistrationError(
                f"cannot register the pair: texture correlation {peak_ncc:.3f} at {shift:.1f} px, "
                f"confidence {confidence:.2f} < {self.min_confidence:.2f} "
                f"(encoder shift {guess:.1f} px)"
            )
        return Registration(
            shift_px=shift, confidence=confidence, encoder_shift_px=guess, peak_ncc=peak_ncc
        )

    def coarse_profile(
        self, profile_a: np.ndarray, profile_b: np.ndarray, *, encoder_shift_px: float
    ) -> Registration:
        """Shift from the 1-D column profiles alone (albedo along the feed).

        Robust correlation of the standardised first differences of the log-profiles (module
        docstring) at every integer lag within ``+-(search_px + margin_px)`` of the encoder's
        shift, one fixed stretch of A sliding over B; parabolic sub-pixel peak.

        Parameters
        ----------
        profile_a, profile_b : ndarray, shape (width,)
            Positive column profiles of A and B (camera frame).
        encoder_shift_px : float
            Shift from the encoder, pixels.

        Returns
        -------
        Registration
            With ``source == "profile"``.

        Raises
        ------
        RegistrationError
            The peak lies on the edge of the window, or its confidence or correlation is below
            ``min_profile_confidence`` / ``min_profile_ncc``.
        """
        guess = check_finite("encoder_shift_px", encoder_shift_px)
        pa, pb = self._profiles(profile_a, profile_b)
        ga = robust_standardise(log_difference(pa)).astype(np.float32)
        gb = robust_standardise(log_difference(pb)).astype(np.float32)
        lo, hi, u0, u1 = self._lag_window(guess, ga.size)
        reach = self.search_px + self.margin_px
        lags = np.arange(lo, hi + 1)
        rho = robust_correlation(ga[u0:u1], gb, u0 + lags, self._TRIM)
        shift, peak, confidence = window_peak(rho, lags, "column-profile", guess, reach)
        if peak < self.min_profile_ncc or confidence < self.min_profile_confidence:
            raise RegistrationError(
                f"column-profile correlation {peak:.3f} at {shift:.1f} px, confidence "
                f"{confidence:.2f} < {self.min_profile_confidence:.2f}"
            )
        return Registration(
            shift_px=shift, confidence=confidence, encoder_shift_px=guess, peak_ncc=peak,
            source="profile",
        )

    # -- fine stage -----------------------------------------------------------------------------

    def fine(
        self, profile_a: np.ndarray, profile_b: np.ndarray, *, guess_px: float
    ) -> tuple[float, float]:
        """Fine shift within ``+-fine_px`` of ``round(guess_px)``: sign-free cross-spectrum fit.

        Parameters
        ----------
        profile_a, profile_b : ndarray, shape (width,)
            Positive column profiles of A and B (camera frame).
        guess_px : float
            Coarse shift, pixels.

        Returns
        -------
        shift_px : float
            Refined shift; NaN when the best delay lies on the edge of the window.
        score : float
            Coherence of the fit in [-1, 1]: ``Re sum |X| e^(2i(...))`` at the best delay over
            ``sum |X|`` (1: every frequency agrees on the delay, up to sign).

        Raises
        ------
        RegistrationError
            The overlap is too small.
        """
        guess = check_finite("guess_px", guess_px)
        pa, pb = self._profiles(profile_a, profile_b)
        return self._fine(log_difference(pa), log_difference(pb), guess)

    def _fine(self, la: np.ndarray, lb: np.ndarray, guess: float) -> tuple[float, float]:
        """:meth:`fine` from the first differences of the log-profiles."""
        return self.fine_fit(la, lb, guess)

    # -- the texture stage as the registration runs it ------------------------------------------

    def _quick_texture(self, texture_a: np.ndarray, texture_b: np.ndarray, guess: float,
                       offset_px: int = 0) -> Registration | None:
        """The texture stage on every k-th row first: kept when that alone is strong.

        A clean board's texture registers at a confidence of 0.8-0.98 on a third of the rows;
        only a weak or noisy texture needs the evidence of all of them (``None``: use all).
        """
        rows = np.shape(texture_a)[0]
        step = -(-rows // self.quick_rows) if self.quick_rows else 0
        if step < 2:
            return None
        try:
            quick = self.coarse(texture_a[::step], texture_b[::step], encoder_shift_px=guess,
                                offset_px=offset_px)
        except RegistrationError:
            return None
        return quick if quick.confidence >= self.strong_confidence else None

    def _texture_stage(self, texture_a: np.ndarray, texture_b: np.ndarray, guess: float,
                       offset_px: int, reasons: list[str]) -> Registration | None:
        """The texture registration: quick rows, all rows, a wider short band (noisy images).

        ``None`` when none passes; the reasons are appended to ``reasons``.
        """
        texture = self._quick_texture(texture_a, texture_b, guess, offset_px)
        if texture is not None:
            return texture
        try:
            return self.coarse(texture_a, texture_b, encoder_shift_px=guess, offset_px=offset_px)
        except RegistrationError as exc:
            reasons.append(str(exc).removeprefix("cannot register the pair: "))
        # Noisy images: a wider short band keeps the fibres' texture and drops the noise.
        wide = (max(self.band_px[0], self.noisy_short_px), self.band_px[1])
        if wide != self.band_px and wide[0] < wide[1]:
            try:
                return self.coarse(texture_a, texture_b, encoder_shift_px=guess, band_px=wide,
                                   offset_px=offset_px)
            except RegistrationError as exc2:
                reasons.append(str(exc2).removeprefix("cannot register the pair: "))
        return None



class Registrar(ShiftStages):
    """Refines the encoder shift of a pair from its images (set up once per width).

    Coarse (unambiguous) from the albedo -- the 2-D texture, and the 1-D column profiles when the
    texture is not clearly confident -- within ``+-(search_px + margin_px)`` of the encoder's
    shift; then fine, to a few hundredths of a pixel, from the column profiles within
    ``+-fine_px`` (see the module docstring). This class decides among the stages
    (:meth:`__call__`); the stages and every parameter are :class:`ShiftStages`'.
    """

    def _choose(
        self, texture: Registration | None, profile: Registration | None
    ) -> Registration | None:
        """The coarse registration to use of those that passed their thresholds."""
        found = [r for r in (texture, profile) if r is not None]
        if len(found) < 2:
            return found[0] if found else None
        assert texture is not None and profile is not None
        best = max(found, key=lambda r: r.confidence)
        if abs(texture.shift_px - profile.shift_px) <= self.fine_px:
            return best
        if best.confidence >= self.strong_confidence:
            return best
        raise RegistrationError(
            f"texture ({texture.shift_px:.1f} px, confidence {texture.confidence:.2f}) and "
            f"column profiles ({profile.shift_px:.1f} px, confidence {profile.confidence:.2f}) "
            f"disagree"
        )

    def __call__(
        self,
        texture_a: np.ndarray,
        texture_b: np.ndarray,
        *,
        encoder_shift_px: float,
        profile_a: np.ndarray | None = None,
        profile_b: np.ndarray | None = None,
        texture_offset_px: int = 0,
        whole_textures: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Registration:
        """Register a pair: coarse from the albedo, then (with the profiles) fine.

        Parameters
        ----------
        texture_a, texture_b : ndarray, shape (n_rows, width) or (n_rows, w)
            As in :meth:`coarse`.
        encoder_shift_px : float
            Shift from the encoder, pixels.
        profile_a, profile_b : ndarray, shape (width,), optional
            Positive column profiles of A and B (camera frame).  Without them only the texture
            registers the pair and the shift is not refined.
        texture_offset_px : int, optional
            Column of B's texture window minus A's (``offset_px`` of :meth:`coarse`).
        whole_textures : tuple of two ndarray, shape (n_rows, width), optional
            With windowed textures: the whole-width textures, registered instead when the
            windows give no strongly confident texture registration (the windows are a fast
            path for clear textures; a weak one is judged on all the evidence, as without).

        Returns
        -------
        Registration

        Raises
        ------
        RegistrationError
            The shift leaves too little overlap; no coarse stage is confident (and the
            shading-only rule does not apply); the two coarse stages disagree; or the fine fit
            is coherent but does not line up within ``fine_px`` of the coarse shift.
        """
        guess = check_finite("encoder_shift_px", encoder_shift_px)
        off = check_int("texture_offset_px", texture_offset_px)
        if profile_a is None or profile_b is None:
            return self.coarse(texture_a, texture_b, encoder_shift_px=guess, offset_px=off)
        pa, pb = self._profiles(profile_a, profile_b)
        self._lag_window(guess, self.width)  # overlap check before anything else
        reasons: list[str] = []
        texture = self._texture_stage(texture_a, texture_b, guess, off, reasons)
        if whole_textures is not None and (texture is None
                                           or texture.confidence < self.strong_confidence):
            reasons = []  # the windows were not enough: the whole width decides, as without
            texture = self._texture_stage(*whole_textures, guess, 0, reasons)
        profile: Registration | None = None
        profile_tried = False
        disagree: RegistrationError | None = None
        reg = texture
        if texture is None or texture.confidence < self.strong_confidence:
            profile = _try_profile(self, pa, pb, guess, reasons)
            profile_tried = True
            try:
                reg = self._choose(texture, profile)
            except RegistrationError as exc:
                disagree = exc
                reg = None
        if reg is None and disagree is None:
            return _shading_only(self, pa, pb, guess, reasons)
        if reg is not None:
            candidates = [reg]
        else:  # the stages disagree: the one the fine fit confirms, if any
            found = [r for r in (texture, profile) if r is not None]
            candidates = sorted(found, key=lambda r: -r.confidence)
        message = ""
        la, lb = log_difference(pa), log_difference(pb)
        while candidates:
            cand = candidates.pop(0)
            shift, score = self._fine(la, lb, cand.shift_px)
            if score < self.min_fine_score:  # featureless profiles: keep the coarse shift
                if disagree is None:
                    return replace(cand, fine_score=score)
                continue
            if not math.isfinite(shift):
                shift, score = _fine_beside(self, la, lb, cand.shift_px)
            if math.isfinite(shift):
                return replace(cand, shift_px=shift, fine_score=score,
                               coarse_shift_px=cand.shift_px)
            message = (f"the column profiles do not line up within {self.fine_px} px of the "
                       f"{cand.source} registration ({cand.shift_px:.1f} px)")
            # A texture misled (e.g. fibres tilted by a roll): the 1-D profiles may still hold.
            if not profile_tried:
                profile = _try_profile(self, pa, pb, guess, reasons)
                profile_tried = True
                if profile is not None and abs(profile.shift_px - cand.shift_px) > self.fine_px:
                    candidates.append(profile)
        if disagree is not None:
            raise disagree
        raise RegistrationError(message)


    def without_texture(self, profile_a: np.ndarray, profile_b: np.ndarray, *,
                        encoder_shift_px: float) -> Registration:
        """A second registration from the column profiles alone (coarse, then fine).

        The texture stage is what light-dependent defects fool: a pit, a ridge or a tuft of
        fibres shades differently under the two lights, so its texture in A is not its texture
        in B, and strong shading can outvote the albedo at a wrong shift.  The column profiles
        average every column along the marks, where a defect covers only a few rows, and their
        robust correlation discards the largest quarter of the squares; the fine fit is
        sign-free.  The measurement asks for this estimate when its marks check fails.

        Parameters
        ----------
        profile_a, profile_b : ndarray, shape (width,)
            Positive column profiles of A and B (camera frame).
        encoder_shift_px : float
            Shift from the encoder, pixels.

        Returns
        -------
        Registration
            With ``source == "profile"``, refined by the fine fit when it is coherent.

        Raises
        ------
        RegistrationError
            The column profiles do not register the pair, or the fine fit is coherent but
            lies on the edge of its window.
        """
        guess = check_finite("encoder_shift_px", encoder_shift_px)
        pa, pb = self._profiles(profile_a, profile_b)
        coarse = self.coarse_profile(pa, pb, encoder_shift_px=guess)
        la, lb = log_difference(pa), log_difference(pb)
        shift, score = self._fine(la, lb, coarse.shift_px)
        if score < self.min_fine_score:
            return replace(coarse, fine_score=score)
        if not math.isfinite(shift):
            shift, score = _fine_beside(self, la, lb, coarse.shift_px)
        if not math.isfinite(shift):
            raise RegistrationError(
                f"the column profiles do not line up within {self.fine_px} px of their own "
                f"coarse registration ({coarse.shift_px:.1f} px)")
        return replace(coarse, shift_px=shift, fine_score=score, coarse_shift_px=coarse.shift_px)


def _shading_only(reg: Registrar, pa: np.ndarray, pb: np.ndarray, guess: float,
                  reasons: list[str]) -> Registration:
    """The shading alone when the search window is narrower than half a mark, else an error."""
    period = mark_period_px(pa)
    reach = reg.search_px
    if math.isfinite(period) and reach < 0.5 * period:
        shift, score = shading_shift(
            pa, pb, guess_px=guess, reach_px=math.ceil(reach) + 1
        )
        confidence = score * (1.0 - 2.0 * reach / period)
        if (math.isfinite(shift) and abs(shift - guess) <= reach
                and score >= reg.min_shading_score and confidence >= reg.min_confidence):
            return Registration(
                shift_px=shift, confidence=confidence, encoder_shift_px=guess,
                fine_score=score, source="shading",
            )
        reasons.append(f"shading alone {score:.2f} within {reach:.0f} px")
    raise RegistrationError(
        f"cannot register the pair within {reg.search_px + reg.margin_px:.0f} px of the "
        f"encoder shift {guess:.1f} px: " + "; ".join(reasons)
    )


def _fine_beside(reg: Registrar, la: np.ndarray, lb: np.ndarray, coarse: float
                 ) -> tuple[float, float]:
    """Fine fit in the windows either side of a coarse shift off by a little over ``fine_px``.

    A noisy or biased coarse shift (e.g. fibres crossing the row bins of a rolled camera)
    may miss the fine window; its neighbours are tried, and a coherent interior delay
    within ``1.5 fine_px`` of the coarse shift -- short of the half-mark alias -- is taken.
    """
    best = (math.nan, -1.0)
    for side in (-1, 1):
        shift, score = reg._fine(la, lb, coarse + side * reg.fine_px)
        if (math.isfinite(shift) and score >= reg.min_fine_score
                and abs(shift - coarse) <= 1.5 * reg.fine_px and score > best[1]):
            best = (shift, score)
    return best

def _try_profile(reg: Registrar, pa: np.ndarray, pb: np.ndarray, guess: float,
                 reasons: list[str]) -> Registration | None:
    try:
        return reg.coarse_profile(pa, pb, encoder_shift_px=guess)
    except RegistrationError as exc:
        reasons.append(str(exc))
        return None


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
