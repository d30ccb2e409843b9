"""Earlier forms of the measurement workers' reply packing, kept to pin the forms now used."""

from __future__ import annotations

from typing import Any

import numpy as np

from controller.workers.process import _Packed


def _blob_into_slot(packed: Any, buf: Any, offset: int, room: int) -> Any:
    """``packed`` (of ``_pack``), its float array written into the slot (``blob=None``) if it fits.

    The slot's images are no longer needed once measured: the service copies the array out
    of the slot (:meth:`controller.workers.link.WorkerLink.outcome`) instead of both
    sides pickling, writing and reading it (16 KB at 659 px a row: 15-40 us a pair over both
    processes).
    """
    if type(packed) is not _Packed or packed.blob.nbytes > room:
        return packed
    np.ndarray(packed.blob.shape, np.float64, buffer=buf, offset=offset)[:] = packed.blob
    return packed._replace(blob=None)
