"""``planer`` processes for the Ctrl-C tests: how they inherit SIGINT, and their stacks on a hang.

A process inherits what its parent did with SIGINT. A test runner started as a background
command of a script (``nohup python -m pytest &``, ``cmd &`` in ``sh``) has SIGINT ignored, and
so, unless told otherwise, would every ``planer`` it starts: such a test would say nothing about
a terminal's Ctrl-C. :func:`planer_argv` states the inheritance instead (the ``planer`` command
must stop on SIGINT either way). :func:`ended_or_stacks` waits generously for a stopped process
and, if it is still there, fails with the stack of each of its threads (``kill -USR1``: the
``planer`` command dumps them, see ``planer/cli.py``) instead of a bare timeout.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable

STOP_TIMEOUT_S = 120.0
"""How long a process told to stop may take. Measured on the shared 2-core VM at load average
20-24: a sweep on a local Dask cluster 5.0-6.4 s from Ctrl-C to its exit (7 runs), ``planer hil
--http`` mid-run 1.9-3.1 s (5 runs); a 5x slower machine stays well inside, a lost signal fails
(with the stacks) after this long."""

DUMP_GRACE_S = 5.0
"""How long a hung process is given to write its stacks before it is killed."""

_LAUNCH = (
    "import os, signal, sys\n"
    "signal.signal(signal.SIGINT, signal.SIG_IGN if sys.argv[1] == 'ignored' "
    "else signal.SIG_DFL)\n"
    "os.execv(sys.executable, [sys.executable, *sys.argv[2:]])\n"
)


def planer_argv(*args: str, sigint: str = "default") -> list[str]:
    """The command line of ``python -m planer.cli ARGS`` started with SIGINT ``sigint``.

    Parameters
    ----------
    *args : str
        The ``planer`` command and its options.
    sigint : {"default", "ignored"}
        What the process inherits: ``default`` as from an interactive shell, ``ignored`` as a
        background command of a script. A small launcher sets it and ``exec``s the command (the
        process id stays the command's).
    """
    if sigint not in ("default", "ignored"):
        raise ValueError(f"sigint must be 'default' or 'ignored', got {sigint!r}")
    return [sys.executable, "-c", _LAUNCH, sigint, "-m", "planer.cli", *args]


def ended_or_stacks(proc: subprocess.Popen, what: str, *, timeout_s: float = STOP_TIMEOUT_S,
                    stderr: Callable[[], str] | None = None) -> tuple[str, str]:
    """Wait for ``proc`` (told to stop) to end; return its remaining ``(stdout, stderr)``.

    Parameters
    ----------
    proc : subprocess.Popen
        A ``planer`` process just sent SIGINT (its pipes, if any, are read here unless
        ``stderr`` is given).
    what : str
        Said in the failure message (``"planer sweep after SIGINT"``).
    timeout_s : float
        How long it may take.
    stderr : callable, optional
        Where the process's stderr is read meanwhile (a reader thread's text, all of it once
        the process has ended); then only ``proc.wait`` is used.

    Raises
    ------
    AssertionError
        The process is still running after ``timeout_s``: it is asked for its threads' stacks
        (SIGUSR1), then killed; the message holds its stderr with those stacks.
    """
    try:
        if stderr is not None:
            proc.wait(timeout_s)
            return "", stderr()
        out, err = proc.communicate(timeout=timeout_s)
        return out or "", err or ""
    except subprocess.TimeoutExpired:
        pass
    # a diagnosis, not a wait for the world: SIGUSR1 makes it write its stacks and go on, so
    # give it a few seconds to write them, then kill it and read what it wrote
    os.kill(proc.pid, signal.SIGUSR1)
    err = ""
    try:
        if stderr is not None:
            proc.wait(DUMP_GRACE_S)
        else:
            err = proc.communicate(timeout=DUMP_GRACE_S)[1] or ""
    except subprocess.TimeoutExpired:
        proc.kill()
        err = (proc.communicate()[1] or "") if stderr is None else ""
    proc.wait()
    text = stderr() if stderr is not None else err
    raise AssertionError(f"{what}: still running after {timeout_s:g} s; its stderr, with the "
                         f"stack of each thread at that moment:\n{text}")
