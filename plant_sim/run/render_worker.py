"""Camera images rendered in worker processes; frames written to the spool there, in order.

The machine (stepped on the runner's thread) assembles each pair's frame without images and
keeps a :class:`~plant_sim.rendering.camera.RenderJob` for it (``FrameAssembler.defer_rendering``).
:class:`RenderPool` sends frame and job to a worker process -- it builds the optics
:class:`~plant_sim.rendering.optics.Renderer` once -- which renders the images and, given a spool
writer, writes the pair there itself (PNG encoding and fsync stay out of the process that
serves the machine's interfaces); without one it hands the images back. Frames are written or
handed back in the order they were submitted: several workers render at once and take turns
to write (a shared turn counter; with more than one, the worker whose turn it is opens the
spool afresh, so numbering and pruning see every pair the others wrote). With one
worker the images are exactly those the machine would have rendered itself (same renderer,
same noise stream, same order); with more, each pair's sensor noise is seeded from the
machine's seed and the pair's ``seq``, so the images do not depend on which worker rendered
them.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

from plant_sim.rendering.camera import RenderJob, render_images
from protocol.frames import Frame

_renderer: Any = None
_writer: Any = None
_turn: Any = None  # (condition, next index to write, abort flag) shared by the workers
_seeded = False
_seed = 0
TURN_POLL_S = 0.2
"""How often a worker waiting for its turn to write checks whether the pool is closing, s."""


def build_renderer(cfg: Any, *, seed: int) -> Any:
    """The optics renderer of a ``SimConfig``'s camera, exactly as the machine builds it."""
    from plant_sim.machine.machine import Machine

    return Machine(cfg, seed=seed, render_images=True).renderer


def _init_worker(cfg: Any, seed: int, writer: Any, turn: Any, seeded: bool,
                 nice: int | None) -> None:  # pragma: no cover - worker
    import signal

    global _renderer, _writer, _turn, _seeded, _seed
    from plant_sim.interfaces.thread import lower_priority

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    _renderer = build_renderer(cfg, seed=seed)  # at the caller's priority: a prompt start
    if nice is not None:  # the heavy part yields to the interfaces and the service
        lower_priority(nice)
    _writer, _turn, _seeded, _seed = writer, turn, seeded, seed


def noise_seed(seed: int, seq: int) -> int:
    """The sensor-noise seed of pair ``seq`` when several workers render (any order)."""
    return (int(seed) * 1_000_003 + int(seq)) % (1 << 63)


def _ready() -> bool:  # pragma: no cover - runs in the worker
    return _renderer is not None


def _render(index: int, frame: Frame, job: RenderJob | None) -> Any:  # pragma: no cover
    """The images (no writer), ``True`` when written, ``None`` when dropped.

    With a writer, the frame is written when it is its turn (``index``, counted over every
    frame submitted); the turn passes on whatever happens.
    """
    result: Any = True
    try:
        if job is not None:
            seed = noise_seed(_seed, job.seq) if _seeded else None
            try:
                images = render_images(_renderer, job, rng_seed=seed)
            except ValueError:  # as the machine does: a pair that cannot be rendered is dropped
                images = None
            if images is None:
                result = None
            elif _writer is None:
                return images
            else:
                frame = dataclasses.replace(frame, image_a=images[0], image_b=images[1])
        if _writer is not None and result is True and _wait_turn(index):
            _spool().write(frame)
        return result
    finally:
        if _writer is not None:
            _pass_turn(index)


def _spool() -> Any:  # pragma: no cover - worker
    """The spool writer to write with now (several workers: opened afresh on this turn)."""
    if not _seeded:  # one worker: the only writer, its state is the spool's
        return _writer
    from protocol.spool import SpoolWriter

    return SpoolWriter(_writer.directory, keep=_writer.keep, fsync=_writer.fsync)


def _wait_turn(index: int) -> bool:  # pragma: no cover - worker
    """Wait until frame ``index`` may be written; ``False`` when the pool is closing."""
    cond, nxt, abort = _turn
    with cond:
        while nxt.value != index:
            if abort.value:
                return False
            cond.wait(TURN_POLL_S)
    return not abort.value


def _pass_turn(index: int) -> None:  # pragma: no cover - worker
    cond, nxt, _abort = _turn
    with cond:
        if nxt.value == index:
            nxt.value = index + 1
            cond.notify_all()


class RenderPool:
    """Worker processes rendering frames' images, results in submission order.

    Parameters
    ----------
    cfg : config.sim.SimConfig
        The simulator configuration (camera, optics, rig, species).
    seed : int
        The machine's seed (the wood texture and image noise derive from it).
    workers : int
        Worker processes (1 keeps the images identical to in-process rendering).
    writer : protocol.spool.SpoolWriter, optional
        The workers write every frame submitted to this spool, in order, taking turns; the
        caller must not write to it meanwhile.
    nice : int, optional
        Nice value of the workers (``planer sim``:
        :data:`~plant_sim.interfaces.thread.RENDER_NICE`, so they yield to the interfaces and the
        service); ``None`` leaves them as the caller runs.

    Attributes
    ----------
    dropped : int
        Frames whose images could not be rendered (dropped, as the machine drops them).
    """

    def __init__(self, cfg: Any, *, seed: int, workers: int = 1, writer: Any = None,
                 nice: int | None = None) -> None:
        if int(workers) < 1:
            raise ValueError(f"workers must be >= 1, got {workers!r}")
        self.writer = writer
        self.cfg = cfg
        self.seed = int(seed)
        self.workers = int(workers)
        self.nice = None if nice is None else int(nice)
        self._pool: ProcessPoolExecutor | None = None
        self._queue: deque[tuple[Frame, Future | None]] = deque()
        self._index = 0
        self._turn: Any = None
        self.dropped = 0

    def start(self) -> None:
        """Start the workers and wait until each has built its renderer."""
        if self._pool is not None:
            return
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with threads
        self._turn = (ctx.Condition(), ctx.Value("q", 0, lock=False), ctx.Value("b", 0,
                                                                           lock=False))
        self._pool = ProcessPoolExecutor(
            max_workers=self.workers, mp_context=ctx, initializer=_init_worker,
            initargs=(self.cfg, self.seed, self.writer, self._turn, self.workers > 1,
                      self.nice),
        )
        for f in [self._pool.submit(_ready) for _ in range(self.workers)]:
            f.result()

    @property
    def pending(self) -> int:
        """Frames submitted and not yet taken back."""
        return len(self._queue)

    @property
    def writes_spool(self) -> bool:
        """Whether the worker writes the frames (to :attr:`writer`)."""
        return self.writer is not None

    def submit(self, frame: Frame, job: RenderJob | None) -> None:
        """Queue ``frame`` to get the images ``job`` renders (``None``: as it is)."""
        if self._pool is None:
            raise RuntimeError("RenderPool.start() first")
        if job is None and self.writer is None:
            self._queue.append((frame, None))
        else:
            self._queue.append((frame, self._pool.submit(_render, self._index, frame, job)))
            self._index += 1

    def take(self, *, wait: bool = False) -> list[Frame]:
        """Frames done, in submission order (``wait``: all of them).

        With a spool writer they have been written (the frames returned carry no images);
        otherwise they carry their images. Dropped frames are counted in :attr:`dropped`.
        """
        out: list[Frame] = []
        while self._queue:
            frame, fut = self._queue[0]
            if fut is not None and not (wait or fut.done()):
                break
            self._queue.popleft()
            if fut is None:
                out.append(frame)
                continue
            result = fut.result()
            if result is None:
                self.dropped += 1
            elif result is True:
                out.append(frame)
            else:
                out.append(dataclasses.replace(frame, image_a=result[0], image_b=result[1]))
        return out

    def close(self) -> None:
        """Stop the workers (pending frames are dropped; :meth:`take` them first)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            cond, _nxt, abort = self._turn
            with cond:
                abort.value = 1  # a worker waiting for a cancelled frame's turn gives up
                cond.notify_all()
            pool.shutdown(wait=True, cancel_futures=True)
        self._queue.clear()
