"""The camera as the service's frame source: an acquisition thread and the pairing.

:class:`CameraFrameSource` runs the camera
(:class:`~controller.frames.camera.device.AravisCamera`) in
its own thread: it pops buffers, polls the PLC's trigger latches through an injected
``latch_reader``, feeds both to the pure :class:`~controller.frames.camera.pairing.PairAssembler`
and
hands the frames (good and failed) to the service, which awaits :meth:`CameraFrameSource.next`
on its event loop like the spool source's. The event loop never waits on the camera.

Synchronisation: when the acquisition starts (and after every restart, which the pairing
detects from frame ids and time stamps, or :meth:`CameraFrameSource.restart`) the camera is
stopped, the PLC's ``trigger_seq`` is read and the camera armed again: its first image is
trigger A of the pair after that ``trigger_seq``; without a PLC the ``seq`` continues.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from controller.frames.camera import device
from controller.frames.camera.device import AravisCamera, CameraError, CameraSettings
from controller.frames.camera.pairing import PairAssembler, TriggerLatch
from core.checks import check_int, check_positive
from protocol.frames import Frame
from protocol.spool_files import Skip

__all__ = ["CameraFrameSource", "LatchReader", "is_fake_camera", "open_camera_source",
           "settings_from_config"]

#: Reads the PLC's latch registers now: the last pair's latch, or ``None`` (PLC unreachable).
LatchReader = Callable[[], "TriggerLatch | None"]


class CameraFrameSource:
    """Pairs from a camera, assembled in an acquisition thread; the service awaits :meth:`next`.

    Parameters
    ----------
    camera : AravisCamera
        A set-up camera (not started); the source starts, restarts and closes it.
    latch_reader : callable, keyword-only, optional
        ``latch_reader() -> TriggerLatch | None``, polled every ``latch_poll_s``; ``None``:
        no PLC, pairs carry counts 0.
    latch_poll_s : float, keyword-only
        Poll period of the latches, seconds (faster than the pair rate, or latches are lost).
    window : int, keyword-only
        Pairs an incomplete pair waits (see :class:`PairAssembler`).
    maxsize : int, keyword-only
        Frames held for the service; when full the oldest goes (counted in ``queue_dropped``).
    poll_s : float, keyword-only
        Sleep of :meth:`next` between empty looks, seconds.
    counts_per_mm, ab_tolerance_s : float, keyword-only, optional
        The A/B interval check of the pairing.
    """

    def __init__(self, camera: AravisCamera, *, latch_reader: LatchReader | None = None,
                 latch_poll_s: float = 0.002, window: int = 4, maxsize: int = 64,
                 poll_s: float = 0.002, counts_per_mm: float | None = None,
                 ab_tolerance_s: float | None = None) -> None:
        self.camera = camera
        self.latch_reader = latch_reader
        self.latch_poll_s = check_positive("latch_poll_s", latch_poll_s)
        self.poll_s = check_positive("poll_s", poll_s)
        self.maxsize = check_int("maxsize", maxsize, lo=1)
        self.assembler = PairAssembler(
            latches=latch_reader is not None, window=window,
            frame_id_bits=camera.frame_id_bits, frame_id_skips_zero=camera.frame_id_skips_zero,
            counts_per_mm=counts_per_mm, ab_tolerance_s=ab_tolerance_s)
        self.received = 0
        self.queue_dropped = 0
        self._frames: deque[Frame] = deque()
        self._skips: list[Skip] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._restart = threading.Event()
        self._failure: str | None = None
        self._first_seq = 0
        self._stats = {"completed": 0, "failures": 0, "underruns": 0}
        self._thread = threading.Thread(target=self._run, name="camera-acquisition",
                                        daemon=True)
        self._thread.start()

    # -- the acquisition thread ----------------------------------------------------------------

    def _arm(self) -> None:
        """Start the acquisition; the next image is trigger A of the PLC's next pair."""
        latch = self.latch_reader() if self.latch_reader is not None else None
        with self._lock:
            self._first_seq = (self.assembler.next_seq if latch is None
                               else int(latch.seq) + 1)
        self.camera.start()

    def _run(self) -> None:
        cam = self.camera
        software = cam.settings.trigger_source == "Software" and cam._fake is None  # noqa: SLF001
        period_s = 0.5 / cam.settings.pairs_per_s
        try:
            self._arm()
        except (OSError, ValueError, *device.ARAVIS_ERRORS) as exc:  # told; thread ends
            self._fail(f"camera start failed: {exc}")
            return
        next_trigger = next_latch = time.monotonic()
        while not self._stop.is_set():
            try:
                if self._restart.is_set():
                    self._restart.clear()
                    self._stats = self._add_stats(cam.statistics())
                    cam.stop()
                    with self._lock:
                        if self.assembler.synced:
                            self.assembler.restart("camera restarted by the service")
                    self._arm()
                now = time.monotonic()
                if software and now >= next_trigger:
                    cam.trigger()
                    next_trigger = max(next_trigger + period_s, now - 1.0)
                image = cam.pop(0.01)
                with self._lock:
                    if image is not None:
                        if not self.assembler.synced:
                            self.assembler.sync(frame_id=image.frame_id, seq=self._first_seq)
                        self.assembler.add_image(image)
                        if not self.assembler.synced:  # it saw the camera restart
                            self._restart.set()  # re-arm: stop, read the PLC, start
                    if self.latch_reader is not None and time.monotonic() >= next_latch:
                        next_latch = time.monotonic() + self.latch_poll_s
                        latch = self.latch_reader()
                        if latch is not None:
                            self.assembler.add_latch(latch)
                    self._collect()
            except (OSError, ValueError, *device.ARAVIS_ERRORS) as exc:  # restart it, go on
                self._fail(f"camera error: {type(exc).__name__}: {exc}")
                self._restart.set()
                self._stop.wait(0.1)
        self._stats = self._add_stats(cam.statistics())
        cam.stop()
        with self._lock:
            self.assembler.flush()
            self._collect()

    def _add_stats(self, more: dict[str, int]) -> dict[str, int]:
        return {k: self._stats[k] + more[k] for k in self._stats}

    def _collect(self) -> None:
        """Move the assembler's output to the hand-off (lock held)."""
        for frame in self.assembler.take():
            if len(self._frames) >= self.maxsize:
                self._frames.popleft()
                self.queue_dropped += 1
            self._frames.append(frame)
        self._skips.extend(self.assembler.take_skips())
        if len(self._skips) > 10_000:
            del self._skips[:-10_000]

    def _fail(self, text: str) -> None:
        with self._lock:
            self._failure = text

    # -- the service's side --------------------------------------------------------------------

    def poll(self) -> Frame | None:
        """The oldest frame ready, or ``None`` (never blocks on the camera)."""
        with self._lock:
            if not self._frames:
                return None
            self.received += 1
            return self._frames.popleft()

    async def next(self, timeout_s: float | None = None) -> Frame | None:
        """The next frame (``None`` after ``timeout_s`` seconds without one)."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        while True:
            frame = self.poll()
            if frame is not None:
                return frame
            if deadline is not None and loop.time() >= deadline:
                return None
            wait = self.poll_s
            if deadline is not None:
                wait = max(0.0, min(wait, deadline - loop.time()))
            await asyncio.sleep(wait)

    def take_skips(self) -> list[Skip]:
        """Images and dropped pairs that gave no frame, and camera failures (``<camera>``)."""
        with self._lock:
            out, self._skips = self._skips, []
            if self._failure is not None:
                out.append(Skip("<camera>", self._failure))
                self._failure = None
        return out

    def restart(self) -> None:
        """Stop and start the acquisition (the camera's frame ids may start again)."""
        self._restart.set()

    @property
    def counters(self) -> dict[str, int]:
        """Counts of the camera path, for the service's status.

        Images, pairs, failed, dropped pairs, skipped images, restarts, latches, frames lost
        because the service did not take them (``queue_dropped``) and Aravis' own counters.
        """
        with self._lock:
            out = dict(self.assembler.counters)
            out["queue_dropped"] = self.queue_dropped
        stats = self._stats if self.camera.stream is None else self._add_stats(
            self.camera.statistics())
        out.update({f"aravis_{k}": v for k, v in stats.items()})
        return out

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the thread and the camera (waits at most ``timeout_s``)."""
        self._stop.set()
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self.camera.close()


def is_fake_camera(camera_id: str) -> bool:
    """Whether an Aravis device id names one of Aravis' in-process fake cameras (``Fake_1``)."""
    return camera_id.startswith("Fake")


def settings_from_config(frames: Any, *, rig_camera: Any = None,
                         camera_id: str | None = None) -> CameraSettings:
    """The camera settings of a ``[frames]`` table (and the rig's ``[camera]``).

    The image size is the rig's ``width``/``height`` when recorded, else ``[frames]
    image_width``/``image_height``; the exposure ``[frames] exposure_us``, else for one of
    Aravis' fake cameras (``camera_id``, default ``[frames] camera_id``) ``[frames]
    fake_exposure_us`` (its test image is black at a real camera's strobed exposure), else the
    rig's ``exposure_ms``.
    """
    width = getattr(rig_camera, "width", None) or frames.image_width
    height = getattr(rig_camera, "height", None) or frames.image_height
    if not (width and height):
        raise ValueError("frames.image_width and frames.image_height must be set for the "
                         "camera (or the rig's camera width/height)")
    camera_id = frames.camera_id if camera_id is None else camera_id
    exposure_us = frames.exposure_us or None
    if exposure_us is None and is_fake_camera(camera_id or ""):
        exposure_us = getattr(frames, "fake_exposure_us", 0.0) or None
    if exposure_us is None and getattr(rig_camera, "exposure_ms", None):
        exposure_us = rig_camera.exposure_ms * 1000.0
    return CameraSettings(width=int(width), height=int(height), exposure_us=exposure_us,
                          gain_db=frames.gain_db, trigger_source=frames.trigger_source,
                          packet_size=frames.packet_size, pairs_per_s=frames.pairs_per_s)


def open_camera_source(frames: Any, *, rig_camera: Any = None,
                       latch_reader: LatchReader | None = None) -> CameraFrameSource:
    """Open ``[frames] camera_id``, set it up and start its acquisition thread.

    Raises
    ------
    CameraError
        No Aravis, no such camera, or one that cannot give the rig's images.
    """
    if not frames.camera_id:
        raise CameraError("frames.camera_id is empty (the Aravis device id, e.g. Fake_1)")
    camera = AravisCamera(frames.camera_id, settings_from_config(frames, rig_camera=rig_camera))
    return CameraFrameSource(camera, latch_reader=latch_reader, poll_s=frames.poll_s)
