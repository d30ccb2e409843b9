"""Atomic file writing: a reader sees the old file or the whole new one, never a torn one.

The data goes to a temporary file in the destination's folder, is flushed (and with
``durable=True`` fsync'ed), then renamed over the destination with ``os.replace``; with
``durable=True`` the folder is fsync'ed after the rename too, so the new file survives a power
cut once the call returns. On any error the temporary file is removed and the destination is
left as it was.

Permissions: a new file gets ``0o666 & ~umask`` (what ``open()`` would give it, e.g. 0644 with
the usual umask 022) -- not the 0600 of :func:`tempfile.mkstemp`; a file that is replaced keeps
its permission bits.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_writer", "atomic_write_bytes", "atomic_write_text", "fsync_dir", "new_file_mode"]


def _umask() -> int:
    """The process's umask, read without changing it where the system allows."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):  # not Linux, or a kernel without the field
        pass
    old = os.umask(0o022)  # the portable way sets it; put it back at once
    os.umask(old)
    return old


def new_file_mode(path: str | Path | None = None) -> int:
    """Permission bits an atomic write gives ``path``.

    Parameters
    ----------
    path : str or Path, optional
        The destination; when it exists, its own permission bits are kept.

    Returns
    -------
    int
        ``0o666 & ~umask`` for a new file (what ``open(path, "w")`` gives), else the existing
        file's mode bits.
    """
    if path is not None:
        try:
            return os.stat(path).st_mode & 0o7777
        except OSError:
            pass
    return 0o666 & ~_umask()


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
    mode = new_file_mode(dest)
    fd, tmp = tempfile.mkstemp(prefix=f"{tmp_prefix}{dest.name}.", suffix=".tmp", dir=folder)
    try:
        if binary:
            fh = os.fdopen(fd, "wb")
        else:
            fh = os.fdopen(fd, "w", encoding=encoding, newline=newline)
        with fh:
            os.fchmod(fh.fileno(), mode)  # mkstemp makes it 0600; follow the umask as open() does
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
