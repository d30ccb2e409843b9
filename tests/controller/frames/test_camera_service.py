"""The service takes its pairs from the fake camera (``[frames] source = "camera"``).

No PLC listens here (port 1): the service logs each camera pair as a failed record naming the
missing PLC data, which shows the pairs reached it, one record per pair, in ``seq`` order.
"""

from __future__ import annotations

import asyncio

import pytest

from controller.frames.camera.device import aravis_unavailable

WHY = aravis_unavailable()
pytestmark = pytest.mark.skipif(WHY is not None, reason=f"camera tests need Aravis: {WHY}")


def test_service_logs_one_record_per_camera_pair(tmp_path):
    from config.machine import machine_from_dict
    from controller.frames.source import open_frame_source
    from controller.quality.log import QualityLog
    from controller.service.service import open_service

    cfg = machine_from_dict({
        "plc": {"host": "127.0.0.1", "port": 1, "timeout_s": 0.05},
        "can": {"interface": "virtual", "channel": "camera-test"},
        "frames": {"source": "camera", "camera_id": "Fake_1", "trigger_source": "Software",
                   "image_width": 659, "image_height": 493, "pairs_per_s": 50.0},
    })

    async def main():
        service = open_service(cfg, log_path=tmp_path / "q.sqlite")
        source = open_frame_source(cfg.frames)
        try:
            await asyncio.wait_for(service.run(source, stop=asyncio.Event(), max_frames=4), 30)
        finally:
            service.close()
            source.close()
        return service.counters

    counters = asyncio.run(main())
    assert counters["frames"] == 4
    records = list(QualityLog(tmp_path / "q.sqlite", create=False).records())
    assert len(records) == 4
    seqs = [r.seq for r in records]
    assert seqs == list(range(seqs[0], seqs[0] + 4))
    assert all(not r.ok and "PLC" in r.error for r in records)
