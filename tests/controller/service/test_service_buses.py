"""One owner per bus, no coupling: a PLC that does not answer never holds up the CAN heartbeat.

``Service.run`` (real time) drives the PLC and the amplifier from separate tasks, each with its
own period. Here the PLC's connect or its requests hang for ever (a switch that swallows the
packets); the amplifier must still get a command (RPDO3) with a new alive counter every cycle
(its setpoint timeout is 100 ms). The test counts frames, it does not time them: it stops as soon
as enough commands arrived, the wall-clock limit is a backstop for a loaded machine.
"""

from __future__ import annotations

import asyncio
import itertools
from dataclasses import replace

import can
import pytest

from config.machine import load_machine, rig_path
from config.rig import load_rig
from controller.fieldbus.piezo_client import PiezoClient
from controller.fieldbus.plc_client import PlcClient
from controller.frames.source import QueueFrameSource
from controller.service.service import Service
from protocol.registers import RegisterMap
from tests.support import canopen_frames

N_COMMANDS = 15
_chan = itertools.count()


class HangingBus:
    """A Modbus transport whose connect (``where="connect"``) or requests never answer."""

    def __init__(self, where: str) -> None:
        self.where = where
        self._open = False
        self.entered = 0
        self.returned = 0
        self._never = asyncio.Event()

    @property
    def connected(self) -> bool:
        return self._open

    async def _hang(self) -> None:
        self.entered += 1
        await self._never.wait()  # cancelled when the service stops
        self.returned += 1

    async def connect(self) -> None:
        if self.where == "connect":
            await self._hang()
        self._open = True

    async def read(self, address, count):
        await self._hang()
        return [0] * count

    async def write(self, address, words):
        await self._hang()

    def close(self) -> None:
        self._open = False


@pytest.mark.parametrize("where", ["connect", "request"])
def test_plc_that_never_answers_does_not_delay_the_can_heartbeat(tmp_path, where):
    async def main():
        cfg = load_machine()
        cfg = cfg.with_changes(log=replace(cfg.log, path=tmp_path / "q.sqlite"))
        regmap = RegisterMap.load()
        plc_bus = HangingBus(where)
        channel = f"planer-buses-{next(_chan)}"
        piezo = PiezoClient(can.Bus(interface="virtual", channel=channel), knives=4,
                            command_period_s=cfg.can.command_period_s)
        amp = can.Bus(interface="virtual", channel=channel)
        svc = Service(cfg, plc=PlcClient(plc_bus, regmap), piezo=piezo,
                      measurer_factory=lambda shape: None, rig=load_rig(rig_path(cfg)))
        stop = asyncio.Event()
        alive: list[int] = []

        async def amplifier() -> None:
            while len(alive) < N_COMMANDS:
                while (msg := amp.recv(timeout=0.0)) is not None:
                    if msg.arbitration_id == canopen_frames.command(True, 4, 0)[0]:
                        alive.append(msg.data[2])  # RPDO3: enable, knives, alive counter
                await asyncio.sleep(0.005)
            stop.set()

        listener = asyncio.create_task(amplifier())
        try:
            await asyncio.wait_for(svc.run(QueueFrameSource(), stop=stop), 30.0)  # backstop
        finally:
            listener.cancel()
            await asyncio.gather(listener, return_exceptions=True)
            svc.close()
            amp.shutdown()
        assert plc_bus.entered >= 1 and plc_bus.returned == 0  # the PLC never answered
        assert len(alive) >= N_COMMANDS
        # every command carried a new alive counter (the amplifier's setpoint timeout restarts)
        assert all(b == (a + 1) % 256 for a, b in zip(alive[:-1], alive[1:], strict=True))
        assert svc.state.value == "safe" and "plc" in svc.status().missing

    asyncio.run(main())


@pytest.mark.parametrize("gaps_s", [(0.02,) * 30, (0.02, 0.001, 0.004, 0.02, 0.0, 0.013) * 5,
                                    (0.005,) * 40, (0.05, 0.001) * 15])
def test_every_command_carries_the_next_alive_counter_however_the_cycles_fall(gaps_s):
    """Cycles closer than half a command period send nothing: the counter waits for a send.

    A loaded host runs late cycles back to back; the amplifier must still see each counter
    value in turn (before, the counter moved on every cycle and skipped values).
    """
    from controller.service.actuators import Actuators
    from controller.service.events import EventLog
    from controller.service.supervisor import AmplifierMonitor

    cfg = load_machine()
    channel = f"planer-buses-{next(_chan)}"
    piezo = PiezoClient(can.Bus(interface="virtual", channel=channel), knives=4,
                        command_period_s=cfg.can.command_period_s)
    amp = can.Bus(interface="virtual", channel=channel)
    try:
        out = Actuators(None, piezo, EventLog(), AmplifierMonitor(), stroke_um=20.0)
        rpdo3 = canopen_frames.command(True, 4, 0)[0]
        t, alive = 0.0, []
        for gap in gaps_s:
            t += gap
            out.command(t)
            while (msg := amp.recv(timeout=0.0)) is not None:
                if msg.arbitration_id == rpdo3:
                    alive.append(msg.data[2])
        assert len(alive) >= 10
        assert all(b == (a + 1) % 256 for a, b in zip(alive[:-1], alive[1:], strict=True))
        assert out.alive == alive[-1]  # the counter in force is the last one sent
    finally:
        piezo.close()
        amp.shutdown()
