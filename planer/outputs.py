"""Files a command writes: never one it reads, of a kind it can write, errors naming the path.

Checked before any work (:func:`not_an_input`, :func:`figure_file`), and written with
:func:`writing` so that a full disk or a lost folder says which file it was.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")
"""What a figure may be written as (matplotlib's formats the commands document)."""


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether two paths name one file: the same path after symlinks, or the same inode.

    Hard links and bind mounts differ in path but not in inode; a file not yet there is the
    same as another only by its resolved path.
    """
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


def not_an_input(option: str, out: str | os.PathLike[str],
                 inputs: Mapping[str, str | os.PathLike[str] | None]) -> None:
    """Refuse an output path that is one of the command's inputs.

    Parameters
    ----------
    option : str
        The option naming the output (``--csv``), for the message.
    out : path
        The file the command would write.
    inputs : mapping
        What it reads, by the name a user knows it by (``{"LOG": path}``); ``None`` values
        (e.g. a database URL) are skipped.

    Raises
    ------
    ValueError
        ``out`` is one of ``inputs`` (after symlinks, or by inode); the message names both.
    """
    for name, path in inputs.items():
        if path is not None and same_file(out, path):
            raise ValueError(f"{option} {os.fspath(out)}: is {name} {os.fspath(path)}, which "
                             "this command reads; refusing to overwrite it (give another file)")


def figure_file(option: str, path: str | os.PathLike[str]) -> str:
    """Check a figure's file name before the work: a file (not a folder) of a known format.

    Raises
    ------
    ValueError
        A folder, or a name not ending in ``.png``, ``.pdf`` or ``.svg``; names ``option``.
    """
    p = os.fspath(path)
    if os.path.isdir(p) or p.endswith(os.sep):
        raise ValueError(f"{option} {p}: is a folder, expected a figure file such as "
                         f"{os.path.join(p, 'profile.png')}")
    suffix = os.path.splitext(p)[1].lower()
    if suffix not in FIGURE_SUFFIXES:
        raise ValueError(f"{option} {p}: a figure file must end in "
                         f"{', '.join(FIGURE_SUFFIXES)}; got {suffix or 'no suffix'!r}")
    return p


@contextlib.contextmanager
def writing(option: str, path: str | os.PathLike[str]) -> Iterator[None]:
    """Errors of writing ``path`` inside the block name it: ``--csv out.csv: cannot write: ...``.

    ``OSError`` (a full disk, a folder removed, no permission) becomes an ``OSError`` whose
    message names ``option`` and ``path``.
    """
    try:
        yield
    except OSError as exc:
        raise OSError(f"{option} {os.fspath(path)}: cannot write: "
                      f"{exc.strerror or exc}") from None
