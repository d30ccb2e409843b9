"""A GenICam camera through Aravis (PyGObject): set-up, read-back check, buffers.

The I/O edge of the camera path. :class:`AravisCamera` opens a device by its Aravis id (``Fake_1``
for the in-process fake camera, a GigE Vision address such as ``127.0.0.1``, a serial or
``Vendor-Model-Serial``), sets the GenICam features of :class:`CameraSettings` (region, pixel
format, exposure, gain, trigger source and activation, packet size), reads them back and refuses
a camera that cannot give the rig's image size or format with one :class:`CameraError` naming
both. :meth:`AravisCamera.pop` turns a buffer into a
:class:`~controller.frames.camera.pairing.CameraImage`.

PyGObject and the Aravis typelib are optional (``pip install '.[camera]'``, Debian
``gir1.2-aravis-0.8``): :func:`aravis_unavailable` says why they cannot be used.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.frames.camera.pairing import CameraImage
from core.checks import check_int, check_positive
from core.errors import PlanerError

__all__ = ["AravisCamera", "CameraError", "CameraSettings", "aravis_unavailable", "load_aravis"]

#: Trigger sources the set-up accepts: ``Software`` (tests, commissioning) or a hardware line.
TRIGGER_SOURCES = ("Software", "Line0", "Line1", "Line2", "Line3", "Line4")
TRIGGER_ACTIVATIONS = ("RisingEdge", "FallingEdge")


class CameraError(PlanerError, OSError):
    """The camera cannot be opened, set up as the rig needs, or read."""


@dataclass(frozen=True)
class CameraSettings:
    """What the camera must deliver (from the rig and ``[frames]`` of the machine file).

    Attributes
    ----------
    width, height : int
        Image size, pixels (the rig's).
    pixel_format : str
        GenICam pixel format; the measurement takes ``Mono8``.
    exposure_us : float or None
        Exposure time, microseconds (``None``: the camera's).
    gain_db : float or None
        Gain, dB (``None``: the camera's).
    trigger_source : str
        ``"Software"`` or a hardware line (``"Line1"``) wired to the PLC's trigger output.
    trigger_activation : str
        ``"RisingEdge"`` or ``"FallingEdge"`` (hardware lines only).
    packet_size : int
        GigE Vision stream packet size, bytes (0: negotiated by Aravis; up to 9000 with jumbo
        frames).
    pairs_per_s : float
        Nominal pair rate (the fake camera is told to run at twice this frame rate).
    buffers : int
        Stream buffers queued in Aravis (a burst of this many images never drops).
    """

    width: int
    height: int
    pixel_format: str = "Mono8"
    exposure_us: float | None = None
    gain_db: float | None = None
    trigger_source: str = "Software"
    trigger_activation: str = "RisingEdge"
    packet_size: int = 0
    pairs_per_s: float = 10.0
    buffers: int = 64

    def __post_init__(self) -> None:
        check_int("width", self.width, lo=1, hi=100_000)
        check_int("height", self.height, lo=1, hi=100_000)
        if self.pixel_format != "Mono8":
            raise ValueError(f"pixel_format must be Mono8, got {self.pixel_format!r}")
        if self.exposure_us is not None:
            check_positive("exposure_us", self.exposure_us)
        if self.gain_db is not None:
            check_positive("gain_db", self.gain_db, allow_zero=True)
        if self.trigger_source not in TRIGGER_SOURCES:
            raise ValueError(f"trigger_source must be one of {', '.join(TRIGGER_SOURCES)}, "
                             f"got {self.trigger_source!r}")
        if self.trigger_activation not in TRIGGER_ACTIVATIONS:
            raise ValueError(f"trigger_activation must be one of "
                             f"{', '.join(TRIGGER_ACTIVATIONS)}, got {self.trigger_activation!r}")
        check_int("packet_size", self.packet_size, lo=0, hi=16_384)
        check_positive("pairs_per_s", self.pairs_per_s)
        check_int("buffers", self.buffers, lo=4, hi=4096)

    def with_changes(self, **changes: Any) -> CameraSettings:
        """A copy with some fields replaced (checked again)."""
        return dataclasses.replace(self, **changes)


_ARAVIS: Any = None
_WHY: str | None = None
#: What Aravis calls raise: ``GLib.Error`` (set once Aravis loads) and PyGObject's type errors.
ARAVIS_ERRORS: tuple[type[BaseException], ...] = (TypeError, RuntimeError)


def aravis_unavailable() -> str | None:
    """Why the camera path cannot run here (``None``: PyGObject and Aravis 0.8 load)."""
    global _ARAVIS, _WHY, ARAVIS_ERRORS
    if _ARAVIS is not None or _WHY is not None:
        return _WHY
    try:
        import gi
    except ImportError:
        _WHY = ("PyGObject (gi) is not installed: pip install 'smart-planer[camera]' "
                "(needs Debian libgirepository1.0-dev, libcairo2-dev, pkg-config, a C compiler)")
        return _WHY
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as exc:
        _WHY = f"Aravis 0.8 typelib not found ({exc}): apt-get install gir1.2-aravis-0.8"
        return _WHY
    _ARAVIS = Aravis
    ARAVIS_ERRORS = (GLib.Error, TypeError, RuntimeError)
    return None


def load_aravis() -> Any:
    """The ``gi.repository.Aravis`` module; :class:`CameraError` with the reason if missing."""
    why = aravis_unavailable()
    if why is not None:
        raise CameraError(why)
    return _ARAVIS


def _glib_text(exc: BaseException) -> str:
    return " ".join(str(getattr(exc, "message", None) or exc).split())


class AravisCamera:
    """One GenICam camera, set up and checked for the rig.

    Parameters
    ----------
    device_id : str
        Aravis device id (``Fake_1``: the in-process fake camera), GigE address or serial.
    settings : CameraSettings
        What the camera must deliver.

    Attributes
    ----------
    info : dict
        What the camera reports after the set-up (vendor, model, size, format, exposure, gain,
        trigger, packet size).
    frame_id_bits, frame_id_skips_zero
        How the camera counts its frames (GigE Vision 1.x and the fake cameras: 16 bits, 0
        skipped; USB3 Vision: 64 bits).

    Raises
    ------
    CameraError
        Aravis missing, no such camera, or a camera that cannot give the settings (the message
        names what the camera gives and what the rig needs).
    """

    def __init__(self, device_id: str, settings: CameraSettings) -> None:
        if not isinstance(device_id, str) or not device_id.strip():
            raise ValueError(f"device_id must be a non-empty string, got {device_id!r}")
        if not isinstance(settings, CameraSettings):
            raise ValueError(f"settings must be CameraSettings, got {type(settings).__name__}")
        self.aravis = arv = load_aravis()
        self.device_id = device_id
        self.settings = settings
        if device_id.startswith("Fake"):
            arv.enable_interface("Fake")
        try:
            self.camera = arv.Camera.new(device_id)
        except ARAVIS_ERRORS as exc:
            raise CameraError(f"camera {device_id!r}: cannot open: {_glib_text(exc)}") from None
        if self.camera is None:
            raise CameraError(f"camera {device_id!r}: not found")
        self.device = self.camera.get_device()
        self.stream: Any = None
        self.acquiring = False
        self._fake = getattr(self.device, "get_fake_camera", None)
        usb = bool(getattr(self.camera, "is_uv_device", lambda: False)())
        self.frame_id_bits, self.frame_id_skips_zero = (64, False) if usb else (16, True)
        self.info = self._set_up()

    # -- set-up --------------------------------------------------------------------------------

    def _set_up(self) -> dict[str, Any]:
        cam, s = self.camera, self.settings
        need = f"{s.width}x{s.height} {s.pixel_format}"
        try:
            formats = list(cam.dup_available_pixel_formats_as_strings() or [])
        except ARAVIS_ERRORS:  # a camera without the enumeration: try to set it
            formats = []
        try:
            if formats and s.pixel_format not in formats:
                raise CameraError(self._mismatch(need, f"formats {', '.join(formats)}"))
            cam.set_pixel_format_from_string(s.pixel_format)
            wb, hb = cam.get_width_bounds(), cam.get_height_bounds()
            if not (wb.min <= s.width <= wb.max and hb.min <= s.height <= hb.max):
                raise CameraError(self._mismatch(
                    need, f"at most {wb.max}x{hb.max} (at least {wb.min}x{hb.min})"))
            cam.set_region(0, 0, s.width, s.height)
            if self._fake is not None:  # the fake camera runs at its "trigger frequency"
                self._fake().set_trigger_frequency(2.0 * s.pairs_per_s)
            if s.exposure_us is not None:
                cam.set_exposure_time(float(s.exposure_us))
            if s.gain_db is not None:
                cam.set_gain(float(s.gain_db))
            cam.set_trigger(s.trigger_source)
            if s.trigger_source != "Software":
                self.device.set_string_feature_value("TriggerActivation", s.trigger_activation)
            if cam.is_gv_device():
                if s.packet_size > 0:
                    cam.gv_set_packet_size(s.packet_size)
                else:
                    cam.gv_auto_packet_size()
        except CameraError:
            raise
        except ARAVIS_ERRORS as exc:  # name the camera and the cause
            raise CameraError(f"camera {self.device_id!r}: set-up failed: {_glib_text(exc)} "
                              f"(the rig needs {need})") from None
        return self._read_back(need)

    def _mismatch(self, need: str, gives: str) -> str:
        return (f"camera {self.device_id!r} cannot give the rig's images: it gives {gives}, "
                f"the rig needs {need}")

    def _read_back(self, need: str) -> dict[str, Any]:
        cam, s = self.camera, self.settings
        try:
            region = cam.get_region()
            fmt = cam.get_pixel_format_as_string()
            info = {
                "vendor": cam.get_vendor_name(), "model": cam.get_model_name(),
                "device_id": self.device_id, "width": int(region.width),
                "height": int(region.height), "offset_x": int(region.x),
                "offset_y": int(region.y), "pixel_format": fmt,
                "exposure_us": float(cam.get_exposure_time()),
                "gain_db": float(cam.get_gain()) if cam.is_gain_available() else None,
                "trigger_source": cam.get_trigger_source(),
                "packet_size": int(cam.gv_get_packet_size()) if cam.is_gv_device() else 0,
            }
            payload = int(cam.get_payload())
        except ARAVIS_ERRORS as exc:
            raise CameraError(f"camera {self.device_id!r}: read-back failed: "
                              f"{_glib_text(exc)}") from None
        gives = f"{info['width']}x{info['height']} {fmt}"
        if (info["width"], info["height"], fmt) != (s.width, s.height, s.pixel_format):
            raise CameraError(self._mismatch(need, gives))
        if payload < s.width * s.height:
            raise CameraError(self._mismatch(need, f"{gives} in {payload} bytes per image"))
        if info["trigger_source"] != s.trigger_source:
            raise CameraError(f"camera {self.device_id!r}: trigger source reads back "
                              f"{info['trigger_source']!r}, set {s.trigger_source!r}")
        if s.exposure_us is not None and abs(info["exposure_us"] - s.exposure_us) > max(
                1.0, 0.01 * s.exposure_us):
            raise CameraError(f"camera {self.device_id!r}: exposure reads back "
                              f"{info['exposure_us']:g} us, set {s.exposure_us:g} us")
        self.payload = payload
        return info

    # -- acquisition ---------------------------------------------------------------------------

    def start(self) -> None:
        """Create the stream, queue the buffers and start the acquisition."""
        arv = self.aravis
        try:
            self.stream = self.camera.create_stream(None, None)
            for _ in range(self.settings.buffers):
                self.stream.push_buffer(arv.Buffer.new_allocate(self.payload))
            self.camera.start_acquisition()
        except ARAVIS_ERRORS as exc:
            raise CameraError(f"camera {self.device_id!r}: cannot start the acquisition: "
                              f"{_glib_text(exc)}") from None
        self.acquiring = True

    def trigger(self) -> None:
        """One software trigger (``trigger_source = "Software"``)."""
        self.camera.software_trigger()

    def pop(self, timeout_s: float) -> CameraImage | None:
        """The next buffer as a :class:`CameraImage` (``None`` after ``timeout_s``).

        A buffer that is not complete (packet loss, timeout, wrong size) gives an image with its
        status and no pixels; the buffer goes back to the stream either way.
        """
        if self.stream is None:
            raise CameraError(f"camera {self.device_id!r}: not started")
        buf = self.stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
        if buf is None:
            return None
        try:
            status = buf.get_status()
            fid, ts = int(buf.get_frame_id()), int(buf.get_timestamp())
            s = self.settings
            if status != self.aravis.BufferStatus.SUCCESS:
                return CameraImage(fid, ts, None, status.value_nick.replace("-", " "))
            w, h = buf.get_image_width(), buf.get_image_height()
            data = buf.get_data()
            if (w, h) != (s.width, s.height) or len(data) < w * h:
                return CameraImage(fid, ts, None, f"{w}x{h} image in {len(data)} bytes, "
                                   f"expected {s.width}x{s.height}")
            image = np.frombuffer(data, np.uint8, count=w * h).reshape(h, w).copy()
            return CameraImage(fid, ts, image)
        finally:
            self.stream.push_buffer(buf)

    def statistics(self) -> dict[str, int]:
        """Aravis' stream counters: completed buffers, failures, underruns."""
        if self.stream is None:
            return {"completed": 0, "failures": 0, "underruns": 0}
        # ArvStream's counters (ArvGvStream has a get_statistics of its own: resent, missing)
        done, failures, underruns = self.aravis.Stream.get_statistics(self.stream)
        return {"completed": int(done), "failures": int(failures), "underruns": int(underruns)}

    def stop(self) -> None:
        """Stop the acquisition (the stream and its buffers go)."""
        if self.acquiring:
            try:
                self.camera.stop_acquisition()
            except ARAVIS_ERRORS:  # noqa: S110 - a camera gone: nothing left to stop
                pass
            self.acquiring = False
        self.stream = None

    def close(self) -> None:
        """Stop and release the camera."""
        self.stop()
        self.camera = None
        self.device = None
