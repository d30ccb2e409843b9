"""How a moulder's heads open the quality log: one connection, one pair of writer threads."""

from __future__ import annotations

import itertools

import can

from config.loading import default_path
from config.machine import load_machine
from controller.quality.journal import default_journal_path
from controller.quality.log import QualityLog, QualityRecord, utc_iso
from controller.quality.write_ahead import SharedLog, WriterGroup

_chan = itertools.count()


def _moulder(tmp_path, *, threaded: bool):
    from controller.moulder.compose import open_moulder_service

    cfg = load_machine(default_path("machine_moulder.toml"))
    bus = can.Bus(interface="virtual", channel=f"compose-log-{next(_chan)}")
    return cfg, open_moulder_service(cfg, log_path=tmp_path / "q.sqlite", can_bus=bus,
                                     threaded=threaded)


def test_every_heads_records_go_through_one_group_on_one_connection(tmp_path):
    cfg, moulder = _moulder(tmp_path, threaded=True)
    try:
        groups = [part for part in moulder.shared if isinstance(part, WriterGroup)]
        assert len(groups) == 1
        group = groups[0]
        assert isinstance(group.log, QualityLog) and group.log.path == tmp_path / "q.sqlite"
        for name, svc in moulder.heads.items():
            assert isinstance(svc.log, SharedLog) and svc.log.writer_group is group
            writer = svc.records.writer
            assert writer is not None and writer._group is group
            # each head keeps its own journal (and learned state) beside the log
            assert writer.journal_path == default_journal_path(tmp_path / "q.sqlite", head=name)
        for i, (name, svc) in enumerate(moulder.heads.items()):
            svc.records.writer._make = lambda item: item  # a record, not a pair, handed in
            svc.records.writer._on_durable = None
            svc.records.writer.put(QualityRecord(
                t_s=0.0, wall_time=utc_iso(0.0), seq=i, board_id=1, board_position_mm=0.0,
                ok=True, head=name))
        assert all(svc.records.writer.wait_logged(60.0) for svc in moulder.heads.values())
    finally:
        moulder.close()
    assert group.log._store.closed  # closed once, after every head
    with QualityLog(tmp_path / "q.sqlite", create=False) as log:
        assert sorted((r.head, r.seq) for r in log.records()) == sorted(
            (hc.name, i) for i, hc in enumerate(cfg.heads))


def test_inline_heads_share_the_connection_too(tmp_path):
    _, moulder = _moulder(tmp_path, threaded=False)
    try:
        logs = {id(svc.log.writer_group.log) for svc in moulder.heads.values()}
        assert len(logs) == 1
        assert all(svc.records.sink is not None for svc in moulder.heads.values())
    finally:
        moulder.close()
    group = moulder.heads[next(iter(moulder.heads))].log.writer_group
    assert group.log._store.closed
