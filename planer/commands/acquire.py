"""``planer acquire``: grab image pairs from a GenICam camera into a spool (commissioning).

Opens the camera through Aravis (``--camera``: ``Fake_1``, a GigE address, a serial), sets it up
for the rig's image size (Mono8, exposure, gain, trigger, packet size from ``[frames]`` of the
machine file), grabs ``--pairs`` pairs and writes each good one into ``--spool`` in the spool
format (``docs/frames.md``), with a progress bar on stderr. With ``--plc HOST:PORT`` each pair
carries the PLC's trigger latches; without it the counts are 0 and ``acquire.json`` in the spool
says ``"counts": "not latched"``. Failed pairs (dropped, incomplete, no latch) are counted and
not written. Every written pair's images are checked (:mod:`controller.frames.camera.image_check`):
dark, flat or saturated images are warned about on stderr as they come and counted in the last
line and in ``acquire.json`` (``image_problems``). Aravis' fake cameras get ``[frames]
fake_exposure_us`` (the shipped 10 ms) unless ``exposure_us`` is set. See ``docs/camera.md``.
"""

from __future__ import annotations

import argparse


def configure(parser: argparse.ArgumentParser) -> None:
    """Add this command's arguments."""
    parser.add_argument("--camera", required=True, metavar="ID",
                        help="Aravis device id: Fake_1, a GigE Vision address, a serial")
    parser.add_argument("--pairs", type=int, default=10, metavar="N",
                        help="good pairs to write (default 10)")
    parser.add_argument("--plc", default=None, metavar="HOST:PORT",
                        help="PLC Modbus TCP server for the trigger latches (default: none)")
    parser.add_argument("--spool", required=True, metavar="DIR", help="spool directory to fill")
    parser.add_argument("--image-format", choices=("png", "npy"), default="png",
                        help="spool image files: png (compact, the default) or npy (raw: "
                             "about 0.5 ms less per pair for the service to read)")
    parser.add_argument("--config", default=None,
                        help="machine file for [frames] camera settings (default: shipped)")
    parser.add_argument("--rig", default=None, help="rig file (default: the machine file's)")
    parser.add_argument("--trigger", default=None, metavar="SOURCE",
                        help="trigger source: Software or Line0..Line4 (default: [frames] "
                        "trigger_source; Software for the Fake cameras)")
    parser.add_argument("--timeout", type=float, default=10.0, metavar="S",
                        help="give up after S seconds without a good pair (default 10)")


HINTS = {
    "dark": "too little light or exposure: raise [frames] exposure_us or gain_db, check the "
            "lights and the trigger",
    "flat": "one grey, no texture: check the lights, the focus, the lens cap and that a "
            "board is under the camera",
    "saturated": "too much light or exposure: lower [frames] exposure_us or gain_db",
}
"""What to do about each image problem (:class:`~controller.frames.camera.image_check.
ImageProblem` by value)."""


class ImageTally:
    """The written pairs' image problems: warns once per kind, counts pairs per kind."""

    def __init__(self, exposure: str) -> None:
        self.exposure = exposure
        self.pairs: dict[str, int] = {}
        self.first: dict[str, str] = {}

    def check(self, frame: object) -> list[str]:
        """Check a written pair; the warning lines for kinds not seen before."""
        from controller.frames.camera.image_check import image_problems

        found: dict[str, str] = {}
        for name in ("a", "b"):
            problems, levels = image_problems(getattr(frame, f"image_{name}"))
            for p in problems:
                found.setdefault(p.value, f"image {name.upper()}: {levels.describe()}")
        lines = []
        for kind, where in found.items():
            self.pairs[kind] = self.pairs.get(kind, 0) + 1
            if kind not in self.first:
                self.first[kind] = where
                lines.append(f"planer acquire: warning: pair {getattr(frame, 'seq', '?')} is "
                             f"{kind} ({where}; exposure {self.exposure}): {HINTS[kind]}")
        return lines

    def summary(self, written: int) -> str:
        """``""`` when every pair was usable, else e.g. ``; warning: 3 of 3 pairs dark``."""
        if not self.pairs:
            return ""
        said = ", ".join(f"{n} of {written} pairs {kind}" for kind, n in self.pairs.items())
        return f"; warning: {said} (see the warnings above)"


def _bar(done: int, total: int, failed: int) -> str:
    width = 30
    n = width * done // total
    return f"\r[{'#' * n}{'.' * (width - n)}] {done}/{total} pairs, {failed} failed"


def run(args: argparse.Namespace) -> int:
    """Run the command."""
    import json
    import logging
    import sys
    import time
    from pathlib import Path

    from config.machine import load_machine, rig_path
    from config.rig import load_rig
    from controller.frames.camera.device import AravisCamera
    from controller.frames.camera.latches import ModbusLatchReader, parse_host_port
    from controller.frames.camera.source import (
        CameraFrameSource,
        is_fake_camera,
        settings_from_config,
    )
    from core.checks import check_int, check_positive
    from core.fileio import atomic_write_text
    from planer.cli import output_folder
    from protocol.spool import SpoolWriter

    pairs = check_int("--pairs", args.pairs, lo=1, hi=10**9)
    check_positive("--timeout", args.timeout)
    plc = parse_host_port(args.plc) if args.plc else None
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its lines are not ours: one below
    cfg = load_machine(args.config)
    rig = load_rig(args.rig or rig_path(cfg))
    settings = settings_from_config(cfg.frames, rig_camera=rig.camera, camera_id=args.camera)
    trigger = args.trigger or ("Software" if is_fake_camera(args.camera)
                               else cfg.frames.trigger_source)
    settings = settings.with_changes(trigger_source=trigger)
    spool = Path(output_folder("--spool", args.spool))
    writer = SpoolWriter(spool, keep=max(pairs, 100), image_format=args.image_format)
    camera = AravisCamera(args.camera, settings)
    reader = ModbusLatchReader(plc[0], plc[1], unit_id=cfg.plc.unit_id,
                               registers=cfg.plc.registers) if plc else None
    exposure = f"{camera.info['exposure_us']:g} µs"
    print(f"camera: {camera.info['vendor']} {camera.info['model']} {args.camera}, "
          f"{settings.width}x{settings.height} Mono8, exposure {exposure}, trigger {trigger}",
          file=sys.stderr)
    tally = ImageTally(exposure)
    source = CameraFrameSource(camera, latch_reader=reader, maxsize=4 * 1024)
    written = failed = 0
    reasons: dict[str, int] = {}
    last = time.monotonic()
    plc_said = False
    try:
        while written < pairs:
            frame = source.poll()
            if reader is not None and reader.errors and not plc_said:
                plc_said = True
                print(f"\nplaner acquire: warning: the PLC at {args.plc} does not answer: no "
                      "trigger latches, the pairs fail until it answers", file=sys.stderr,
                      flush=True)
            if time.monotonic() - last > args.timeout:
                told = [s.reason for s in source.take_skips() if s.file == "<camera>"]
                worst = (max(reasons, key=reasons.get) if reasons
                         else (told[-1] if told else "no pair at all"))
                raise OSError(f"no good pair from camera {args.camera!r} for {args.timeout:g} s "
                              f"({written} of {pairs} written, {failed} failed; most often: "
                              f"{worst})")
            if frame is None:
                time.sleep(0.002)
                continue
            if frame.error is not None:
                failed += 1
                key = frame.error.split(": ", 1)[-1]
                reasons[key] = reasons.get(key, 0) + 1
            else:
                writer.write(frame)
                written += 1
                last = time.monotonic()
                for line in tally.check(frame):  # below the progress bar once it shows
                    print(f"\n{line}" if written + failed > 1 else line, file=sys.stderr,
                          flush=True)
            print(_bar(written, pairs, failed), end="", file=sys.stderr, flush=True)
    finally:
        source.close()
        if reader is not None:
            reader.close()
        print(file=sys.stderr)
    counters = source.counters
    meta = {
        "camera": camera.info,
        "counts": f"latched by the PLC at {args.plc}" if plc else
        "not latched: no --plc, counts_a/counts_b/index_latch_counts are 0",
        "pairs_written": written,
        "pairs_failed": failed,
        "failures": reasons,
        "counters": counters,
        "image_problems": {"pairs": dict(tally.pairs), "first": dict(tally.first)},
    }
    atomic_write_text(spool / "acquire.json", json.dumps(meta, indent=2) + "\n")
    print(f"wrote {written} pairs to {spool} ({failed} failed, "
          f"{counters['dropped']} dropped){tally.summary(written)}", flush=True)
    return 0
