"""Every pair the spool holds becomes a record or a named skip, the run's last one included.

A real service (virtual CAN bus, no PLC) reads a spool folder with a file that is not a pair,
a gap in the camera's sequence and, last, another bad file: each bad file is one
``SPOOL_SKIPPED`` event naming it, the gap one ``PAIRS_MISSED`` event with its numbers, every
good pair a record in the quality log.
"""

from __future__ import annotations

import asyncio
from dataclasses import replace

import can

from config.machine import load_machine
from controller.frames.source import SpoolFrameSource
from controller.quality.log import QualityLog
from controller.runtime import RuntimeOptions, ServiceRuntime
from controller.service.events import EventKind
from protocol.frames import Frame
from protocol.spool import SpoolReader, SpoolWriter


def _frame(seq: int) -> Frame:
    return Frame(image_a=None, image_b=None, seq=seq, t_s=0.1 * seq, counts_a=20 * seq,
                 counts_b=20 * seq + 16, speed_mm_s=800.0, board_id=1,
                 board_position_mm=10.0 + seq)


def test_bad_files_are_named_gaps_are_gaps_and_every_good_pair_is_a_record(tmp_path):
    spool = tmp_path / "spool"
    w = SpoolWriter(spool, keep=100, fsync=False)
    for seq in (0, 1, 2, 3):
        w.write(_frame(seq))
    bad = w.write(_frame(4))
    bad.write_text("{ not json")  # slot 4: not a pair any more
    w.write(_frame(45490))  # slot 5: the camera's seq jumped
    last_bad = w.write(_frame(45491))
    last_bad.write_text("[]")  # the run's last file: not a pair's metadata
    good = 5

    bus = can.Bus(interface="virtual", channel=f"skips-{id(tmp_path)}")
    cfg = load_machine()
    cfg = cfg.with_changes(plc=replace(cfg.plc, host="127.0.0.1", port=9, timeout_s=0.05))
    events = []

    async def main():
        async with ServiceRuntime(cfg, log_path=tmp_path / "q.sqlite", can_bus=bus,
                                  options=RuntimeOptions(workers=0, tune=False)) as rt:
            reader = SpoolReader(spool, start="all")
            source = rt.attach(SpoolFrameSource(reader, watch=False))
            rt.service.on_event = events.append
            stop = asyncio.Event()

            async def until_all_handled():
                while reader.read + reader.skipped < 7 or rt.service.counters["frames"] < good:
                    await asyncio.sleep(0.01)
                stop.set()

            watcher = asyncio.create_task(until_all_handled())
            await asyncio.wait_for(rt.run(stop=stop), 120)  # a backstop for a broken run
            await watcher
            return source

    asyncio.run(main())
    skipped = [e.text for e in events if e.kind is EventKind.SPOOL_SKIPPED]
    assert len(skipped) == 2
    assert skipped[0].startswith(f"spool: skipped {bad.name}: ") and "JSON" in skipped[0]
    assert skipped[1].startswith(f"spool: skipped {last_bad.name}: ")
    gaps = [e.text for e in events if e.kind is EventKind.PAIRS_MISSED]
    assert gaps == ["45486 sequence number(s) without a pair: the camera's seq jumped from 3 "
                    "to 45490"]  # seq 4 is the bad file named above
    assert not any("never reached" in e.text for e in events)
    with QualityLog(tmp_path / "q.sqlite", create=False) as log:
        seqs = [r.seq for r in log.records()]
    assert seqs == [0, 1, 2, 3, 45490]
