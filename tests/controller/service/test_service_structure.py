"""The shape of ``controller/service/``: the service is wired from parts, one module each.

The class-size rule and the rule on handlers that catch everything hold for the whole project
(``tests/test_architecture.py``).
"""

from __future__ import annotations

from pathlib import Path

import controller.service as service_room

ROOM = Path(service_room.__file__).parent
PARTS = ("intake", "measurement", "attribution", "loops", "actuators", "safe_state",
         "bus_cycles", "records", "pipeline")


def test_the_service_is_wired_from_parts():
    """The composition root holds the parts; each part lives in a module of its own."""
    from controller.service import service

    src = Path(service.__file__).read_text()
    for part in PARTS:
        assert (ROOM / f"{part}.py").is_file(), part
        assert f"controller.service.{part}" in src, part
