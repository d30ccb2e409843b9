"""The measurement rig: camera intrinsics and scale, the two grazing lights, the feed encoder.

Contract (other tools rely on these keys; add freely, never rename):

- ``[camera]`` ``fx``, ``fy``, ``cx``, ``cy`` (pixels), ``dist = [k1, k2, p1, p2, k3]`` (OpenCV
  order), ``px_per_mm`` (of the undistorted image, along the feed), ``exposure_ms`` (optional)
- ``[lights]`` ``slant_deg``, ``azimuth_a_deg`` (light of image A, default 0),
  ``azimuth_b_deg`` (default 180)
- ``[encoder]`` ``px_per_count``
- optional (``planer calibrate-rig`` writes them): ``[camera]`` ``roll_deg`` (angle of the feed
  from the image x axis, toward +v; default 0), ``width``, ``height`` (image size the camera was
  calibrated at: images of another size are refused); ``[lights]`` ``slant_a_deg``,
  ``slant_b_deg`` (each light's own slant; default ``slant_deg``)

Conventions: image x = columns; the board moves toward +x; image B is taken after image A, so a
point at undistorted column u in A is at u + d in B. The light at azimuth 0 deg stands on the +x
side. Height z points to the camera; p = dz/dx.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from config.loading import Section, load_toml, over_shipped
from core.errors import ConfigError


@dataclass(frozen=True)
class Camera:
    """Pinhole camera with OpenCV's 5-coefficient distortion model.

    Attributes
    ----------
    fx, fy, cx, cy : float
        Focal lengths and principal point, pixels.
    dist : tuple of 5 float
        ``(k1, k2, p1, p2, k3)`` in OpenCV order. The seed's model (Eq. 7) is ``(k1, 0, 0, 0, 0)``.
    px_per_mm : float
        Scale of the undistorted image along the feed, pixels per millimetre.
    exposure_ms : float or None
        Exposure time, milliseconds; ``None`` when unknown (no motion deblurring).
    roll_deg : float
        Camera roll: angle of the feed direction from the image x axis (toward +v), degrees.
    width, height : int or None
        Image size the intrinsics belong to, pixels (``None``: not recorded).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    px_per_mm: float = 12.5
    exposure_ms: float | None = None
    roll_deg: float = 0.0
    width: int | None = None
    height: int | None = None


@dataclass(frozen=True)
class Lights:
    """Two grazing lights; slant from the camera axis, azimuth from +x (degrees).

    ``slant_a_deg`` / ``slant_b_deg`` are each light's own slant when calibrated (``None``:
    ``slant_deg``); see :attr:`slants_deg`.
    """

    slant_deg: float
    azimuth_a_deg: float = 0.0
    azimuth_b_deg: float = 180.0
    slant_a_deg: float | None = None
    slant_b_deg: float | None = None

    @property
    def slants_deg(self) -> tuple[float, float]:
        """``(slant of light A, slant of light B)``, degrees."""
        a = self.slant_deg if self.slant_a_deg is None else self.slant_a_deg
        b = self.slant_deg if self.slant_b_deg is None else self.slant_b_deg
        return a, b


@dataclass(frozen=True)
class Encoder:
    """Feed encoder: image shift per count and counter width (16 or 32 bits)."""

    px_per_count: float
    counter_bits: int = 32


@dataclass(frozen=True)
class Rig:
    """A whole rig file."""

    camera: Camera
    lights: Lights
    encoder: Encoder


def rig_from_dict(data: Mapping[str, Any]) -> Rig:
    """Build and check a :class:`Rig` from a parsed TOML document.

    Raises
    ------
    ConfigError
        A key is missing or its value is out of range; the message names the key.
    """
    root = Section(data, "")
    cam = root.section("camera")
    dist = cam.numbers("dist", [0.0, 0.0, 0.0, 0.0, 0.0])
    if len(dist) == 1:  # the seed's one-coefficient model may be written as [k1]
        dist = (dist[0], 0.0, 0.0, 0.0, 0.0)
    if len(dist) != 5:
        raise ConfigError(f"camera.dist must have 5 values [k1, k2, p1, p2, k3], got {len(dist)}")
    exposure = cam.raw("exposure_ms", None)
    size = {}
    for key in ("width", "height"):
        if cam.raw(key, None) is not None:
            size[key] = cam.integer(key)
            if size[key] < 8:
                raise ConfigError(f"camera.{key} must be >= 8 pixels, got {size[key]}")
    camera = Camera(
        fx=cam.number("fx", lo=0.0, lo_open=True),
        fy=cam.number("fy", lo=0.0, lo_open=True),
        cx=cam.number("cx"),
        cy=cam.number("cy"),
        dist=dist,  # type: ignore[arg-type]
        px_per_mm=cam.number("px_per_mm", lo=0.0, lo_open=True),
        exposure_ms=None if exposure is None else cam.number("exposure_ms", lo=0.0),
        roll_deg=cam.number("roll_deg", 0.0, lo=-10.0, hi=10.0),
        **size,
    )
    lit = root.section("lights")
    lights = Lights(
        slant_deg=lit.number("slant_deg", lo=0.0, hi=89.0, lo_open=True),
        azimuth_a_deg=lit.number("azimuth_a_deg", 0.0, lo=-360.0, hi=360.0),
        azimuth_b_deg=lit.number("azimuth_b_deg", 180.0, lo=-360.0, hi=360.0),
        slant_a_deg=(None if lit.raw("slant_a_deg", None) is None
                     else lit.number("slant_a_deg", lo=0.0, hi=89.0, lo_open=True)),
        slant_b_deg=(None if lit.raw("slant_b_deg", None) is None
                     else lit.number("slant_b_deg", lo=0.0, hi=89.0, lo_open=True)),
    )
    enc = root.section("encoder")
    bits = enc.integer("counter_bits", 32)
    if bits not in (16, 32):
        raise ConfigError(f"encoder.counter_bits must be 16 or 32, got {bits}")
    encoder = Encoder(
        px_per_count=enc.number("px_per_count", lo=0.0, lo_open=True), counter_bits=bits
    )
    return Rig(camera=camera, lights=lights, encoder=encoder)


def load_rig(path: str | Path) -> Rig:
    """Load and check a rig file over the shipped ``config/rig.toml``; errors name file and key.

    A file gives only what it changes (:func:`config.loading.over_shipped`).
    """
    data = load_toml(path)
    try:
        return rig_from_dict(over_shipped(data, "rig.toml"))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def rig_to_toml(rig: Rig) -> str:
    """Serialise a rig as TOML text (the inverse of :func:`rig_from_dict`)."""
    c, li, e = rig.camera, rig.lights, rig.encoder
    lines = [
        "[camera]",
        f"fx = {c.fx!r}",
        f"fy = {c.fy!r}",
        f"cx = {c.cx!r}",
        f"cy = {c.cy!r}",
        "dist = [" + ", ".join(repr(float(v)) for v in c.dist) + "]",
        f"px_per_mm = {c.px_per_mm!r}",
    ]
    if c.exposure_ms is not None:
        lines.append(f"exposure_ms = {c.exposure_ms!r}")
    if c.roll_deg:
        lines.append(f"roll_deg = {c.roll_deg!r}")
    if c.width is not None:
        lines.append(f"width = {c.width!r}")
    if c.height is not None:
        lines.append(f"height = {c.height!r}")
    lines += [
        "",
        "[lights]",
        f"slant_deg = {li.slant_deg!r}",
        f"azimuth_a_deg = {li.azimuth_a_deg!r}",
        f"azimuth_b_deg = {li.azimuth_b_deg!r}",
        *([f"slant_a_deg = {li.slant_a_deg!r}"] if li.slant_a_deg is not None else []),
        *([f"slant_b_deg = {li.slant_b_deg!r}"] if li.slant_b_deg is not None else []),
        "",
        "[encoder]",
        f"px_per_count = {e.px_per_count!r}",
        f"counter_bits = {e.counter_bits!r}",
        "",
    ]
    return "\n".join(lines)
