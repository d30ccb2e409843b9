"""Atomic file writing: a reader sees the old file or the whole new one, never a torn one.

The data goes to a temporary file in the destination's folder, is flushed (and with
``durable=True`` fsync'ed), then renamed over the destination with ``os.replace``; with
``durable=True`` the folder is fsync'ed after the rename too, so the new file survives a power
cut once the call returns. On any error the temporary file is removed and the destination is
left as it was.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_writer", "atomic_write_bytes", "atomic_write_text", "fsync_dir"]


def fsync_dir(folder: str | Path) -> None:
    """Make renames inside ``folder`` durable with an fsync (best effort, never raises)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - file systems that refuse it
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_writer(
    path: str | Path,
    *,
    binary: bool = False,
    encoding: str = "utf-8",
    newline: str | None = None,
    durable: bool = True,
    tmp_prefix: str = ".",
) -> Iterator[IO[Any]]:
    """Open a temporary file that replaces ``path`` when the ``with`` block ends without error.

    Parameters
    ----------
    path : str or Path
        The destination (its folder must exist).
    binary : bool
        Yield a binary file (``"wb"``) instead of a text file (``"w"``).
    encoding, newline : str
        Text mode only, as for :func:`open`.
    durable : bool
        fsync the file before the rename and the folder after it.
    tmp_prefix : str
        Start of the temporary file's name (``<tmp_prefix><name>.<random>.tmp``); a dot keeps it
        out of directory listings that skip hidden files.

    Yields
    ------
    file object
        Write the content to it; do not close it.
    """
    dest = Path(path)
    folder = dest.parent if str(dest.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f"{tmp_prefix}{dest.name}.", suffix=".tmp", dir=folder)
    try:
        if binary:
            fh = os.fdopen(fd, "wb")
        else:
            fh = os.fdopen(fd, "w", encoding=encoding, newline=newline)
        with fh:
            yield fh
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if durable:
        fsync_dir(folder)


def atomic_write_bytes(
    path: str | Path, data: bytes, *, durable: bool = True, tmp_prefix: str = "."
) -> None:
    """Replace ``path`` by ``data`` atomically (see :func:`atomic_writer`)."""
    with atomic_writer(path, binary=True, durable=durable, tmp_prefix=tmp_prefix) as fh:
        fh.write(data)


def atomic_write_text(
    path: str | Path,
    text: str,
    *,
    encoding: str = "utf-8",
    durable: bool = True,
    tmp_prefix: str = ".",
) -> None:
    """Replace ``path`` by ``text`` atomically (see :func:`atomic_writer`)."""
    with atomic_writer(
        path, encoding=encoding, durable=durable, tmp_prefix=tmp_prefix
    ) as fh:
        fh.write(text)
