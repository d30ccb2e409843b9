"""Camera acquisition on the machine: GenICam cameras through Aravis (``docs/camera.md``).

* :mod:`controller.frames.camera.pairing` — pure: images A/B + the PLC's trigger latches -> pairs.
* :mod:`controller.frames.camera.device` — Aravis set-up, read-back check, buffers (optional extra).
* :mod:`controller.frames.camera.latches` — the PLC's latch registers over Modbus TCP.
* :mod:`controller.frames.camera.source` — the acquisition thread: the service's frame source.
"""
