"""Camera acquisition on the machine: GenICam cameras through Aravis (``docs/camera.md``).

* :mod:`controller.camera.pairing` — pure: images A/B + the PLC's trigger latches -> pairs.
* :mod:`controller.camera.device` — Aravis set-up, read-back check, buffers (optional extra).
* :mod:`controller.camera.latches` — the PLC's latch registers over Modbus TCP.
* :mod:`controller.camera.source` — the acquisition thread: the service's frame source.
"""
