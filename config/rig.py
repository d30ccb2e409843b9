"""The measurement rig: camera intrinsics and scale, the two grazing lights, the feed encoder.

Contract (other tools rely on these keys; add freely, never rename):

- ``[camera]`` ``fx``, ``fy``, ``cx``, ``cy`` (pixels), ``dist = [k1, k2, p1, p2, k3]`` (OpenCV
  order), ``px_per_mm`` (of the undistorted image, along the feed), ``exposure_ms`` (optional)
- ``[lights]`` ``slant_deg``, ``azimuth_a_deg`` (light of image A, default 0),
  ``azimuth_b_deg`` (default 180)
- ``[encoder]`` ``px_per_count``

Conventions: image x = columns; the board moves toward +x; image B is taken after image A, so a
point at undistorted column u in A is at u + d in B. The light at azimuth 0 deg stands on the +x
side. Height z points to the camera; p = dz/dx.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from config.loading import Section, load_toml
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
    """

    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    px_per_mm: float = 12.5
    exposure_ms: float | None = None


@dataclass(frozen=True)
class Lights:
    """Two grazing lights; slant from the camera axis, azimuth from +x (degrees)."""

    slant_deg: float
    azimuth_a_deg: float = 0.0
    azimuth_b_deg: float = 180.0


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
    camera = Camera(
        fx=cam.number("fx", lo=0.0, lo_open=True),
        fy=cam.number("fy", lo=0.0, lo_open=True),
        cx=cam.number("cx"),
        cy=cam.number("cy"),
        dist=dist,  # type: ignore[arg-type]
        px_per_mm=cam.number("px_per_mm", lo=0.0, lo_open=True),
        exposure_ms=None if exposure is None else cam.number("exposure_ms", lo=0.0),
    )
    lit = root.section("lights")
    lights = Lights(
        slant_deg=lit.number("slant_deg", lo=0.0, hi=89.0, lo_open=True),
        azimuth_a_deg=lit.number("azimuth_a_deg", 0.0, lo=-360.0, hi=360.0),
        azimuth_b_deg=lit.number("azimuth_b_deg", 180.0, lo=-360.0, hi=360.0),
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
    """Load and check a rig file; errors name the file and the key."""
    data = load_toml(path)
    try:
        return rig_from_dict(data)
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
    lines += [
        "",
        "[lights]",
        f"slant_deg = {li.slant_deg!r}",
        f"azimuth_a_deg = {li.azimuth_a_deg!r}",
        f"azimuth_b_deg = {li.azimuth_b_deg!r}",
        "",
        "[encoder]",
        f"px_per_count = {e.px_per_count!r}",
        f"counter_bits = {e.counter_bits!r}",
        "",
    ]
    return "\n".join(lines)
