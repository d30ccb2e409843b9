"""The ``planer`` command: one sub-command per module in :mod:`planer.commands`.

Each command module defines ``configure(parser)`` and ``run(args) -> int``; its one-line help is
in :data:`COMMANDS`. Only the chosen command's module is imported (``planer --help`` imports
none), so command modules import what they use at their top.

Every error a user can cause ends in ONE line on stderr, ``planer <cmd>: error: <message>``,
and a non-zero exit code, never in a traceback:

=====================================================  =========
what                                                   exit code
=====================================================  =========
bad command line (unknown option, not a number, ...)   2
``ValueError`` / ``OSError`` (so every ``PlanerError``)  2
Ctrl-C (``KeyboardInterrupt``)                          130
stdout closed by its reader (``planer X | head``)      0, quietly
any other exception (a bug): ``internal error``        3
=====================================================  =========

Set ``PLANER_TRACEBACK=1`` to get the full traceback of an error instead (for developers).

Ctrl-C (SIGINT) stops every command, also one started with SIGINT ignored (a background command
of a script: ``planer hil --http ... &``, which Python would otherwise leave deaf to it), and
``kill -USR1 PID`` writes the stack of every thread to stderr without stopping the command (for
a command that seems stuck).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import select
import signal
import sys
import threading
from collections.abc import Sequence
from typing import NoReturn

COMMANDS = {
    "measure": "measure the profile and cuttermarks of an image pair (prints one JSON object)",
    "calibrate": ("calibrate the camera from checkerboard images and write the rig file's [camera] "
                  "table"),
    "calibrate-rig": ("estimate camera roll and light slants from a reference run and write them "
                      "into rig.toml"),
    "bench": "benchmarks: vision pairs/s, simulator real-time factor, service latency",
    "sim": "run the simulated planer alone (Modbus server, CAN node, frame spool) until stopped",
    "serve": "run the service beside the PLC (measure, control, log) until stopped",
    "hil": "hardware-in-the-loop run: simulator + service, scenario, summary and quality log",
    "report": "summarise a quality log: text or JSON summary, PNG figures, CSV export",
    "acquire": "grab image pairs from a GenICam camera (Aravis) into a spool directory",
    "sweep": "run a grid of HIL scenarios on Dask distributed: results.csv and plots",
}
"""Every sub-command and its one-line help; ``planer.commands.<name>`` defines ``configure(parser)``
and ``run(args) -> int`` (a dash in the name is an underscore in the module's)."""

EXIT_USAGE = 2
EXIT_ERROR = 2
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130
TRACEBACK_ENV = "PLANER_TRACEBACK"


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (plus where to find help)."""

    def error(self, message: str) -> NoReturn:  # noqa: D102 - argparse's own contract
        first = message.splitlines()[0] if message else "bad command line"
        self.exit(EXIT_USAGE, f"{self.prog}: error: {first} (see {self.prog} --help)\n")


def build_parser(commands: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered.

    Parameters
    ----------
    commands : sequence of str, optional
        The commands whose modules are imported and whose options are configured (default:
        all); the others are listed with their help only.
    """
    parser = _Parser(
        prog="planer",
        description="Cuttermark measurement and closed-loop control of a planing machine.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, text in COMMANDS.items():
        p = sub.add_parser(name, help=text, description=text)
        if commands is None or name in commands:
            mod = importlib.import_module(f"planer.commands.{name.replace('-', '_')}")
            mod.configure(p)
            p.set_defaults(_run=mod.run)
    return parser


def chosen_command(argv: Sequence[str]) -> list[str]:
    """The sub-command named on a command line (``[]``: none, e.g. ``planer --help``)."""
    return [a for a in argv if a in COMMANDS][:1]


def error_line(exc: BaseException) -> str:
    """The one-line message for an error raised on purpose.

    ``OSError`` from the operating system (``[Errno 2] No such file or directory: 'x'``) is
    rewritten as ``x: No such file or directory``; every other message is cut to its first line.
    """
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror}"
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def output_file(option: str, path: str | os.PathLike[str]) -> str:
    """Check early that a file a command will write can be written; create its folder.

    Parameters
    ----------
    option : str
        The option that named the file (``--log``), for the error message.
    path : str or path-like
        The file to be written (it may exist).

    Returns
    -------
    str
        ``path`` as given.

    Raises
    ------
    ValueError
        The path is a folder, or its folder cannot be created or written; the message names
        ``option`` and the path.
    """
    p = os.fspath(path)
    if not p:
        raise ValueError(f"{option} must not be empty")
    if os.path.isdir(p):
        raise ValueError(f"{option} {p}: is a folder, expected a file name")
    folder = os.path.dirname(os.path.abspath(p))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise ValueError(
            f"{option} {p}: cannot create its folder {folder}: {exc.strerror or exc}"
        ) from None
    writable_folder(option, folder, what=p)
    if os.path.exists(p) and not os.access(p, os.W_OK):
        raise ValueError(f"{option} {p}: file is not writable")
    return p


def output_folder(option: str, path: str | os.PathLike[str]) -> str:
    """Check early that files can be written in folder ``path`` (created if missing).

    Raises
    ------
    ValueError
        ``path`` is a file, or cannot be created or written; the message names ``option``.
    """
    p = os.fspath(path)
    if os.path.exists(p) and not os.path.isdir(p):
        raise ValueError(f"{option} {p}: is a file, expected a folder")
    try:
        os.makedirs(p, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{option} {p}: cannot create the folder: {exc.strerror or exc}") from None
    writable_folder(option, p)
    return p


def writable_folder(option: str, folder: str | os.PathLike[str], *, what: str = "") -> None:
    """Raise ``ValueError`` naming ``option`` unless a file can be created in ``folder``.

    Tries it (a temporary file, removed at once): permission bits do not tell for root or for
    read-only file systems.
    """
    import tempfile

    label = f"{option} {what or os.fspath(folder)}"
    try:
        fd, tmp = tempfile.mkstemp(prefix=".planer-probe-", dir=folder)
    except OSError as exc:
        raise ValueError(
            f"{label}: cannot write in folder {os.fspath(folder)}: {exc.strerror or exc}"
        ) from None
    os.close(fd)
    os.unlink(tmp)


def _quiet_teardown() -> None:
    """After an error was reported, keep library teardown chatter off the terminal.

    python-can warns "Bus was not properly shut down" from ``__del__`` when a command stops on an
    error before closing its bus; the error line already says what happened.
    """
    logging.getLogger("can").setLevel(logging.CRITICAL)


def _reader_gone(stream: object) -> bool:
    """Whether ``stream`` is a pipe (or socket) whose reader has closed it.

    ``poll`` reports ``POLLERR`` on the write end of a pipe without readers (Linux, BSD); a
    stream without a file descriptor (replaced by a test, closed) counts as not gone.
    """
    try:
        fd = stream.fileno()  # type: ignore[attr-defined]
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        events = poller.poll(0)
    except (AttributeError, ValueError, OSError):
        return False
    return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in events)


def _broken_pipe(exc: BaseException) -> bool:
    """Whether ``exc`` (or an exception it came from) is a write to a closed stdout/stderr."""
    seen = 0
    e: BaseException | None = exc
    while e is not None and seen < 20:
        if isinstance(e, BrokenPipeError):
            return _reader_gone(sys.stdout) or _reader_gone(sys.stderr)
        e = e.__cause__ or e.__context__
        seen += 1
    return False


def _silence_closed_streams() -> None:
    """Point a closed stdout/stderr at /dev/null so the exit flush does not fail again.

    Python flushes ``sys.stdout`` at exit; with its reader gone that flush would print
    "Exception ignored ... BrokenPipeError" and turn the exit code into 120.
    """
    for stream in (sys.stdout, sys.stderr):
        if _reader_gone(stream):
            devnull = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(devnull, stream.fileno())
            finally:
                os.close(devnull)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``planer`` command; returns the process exit code.

    A command whose stdout is closed by its reader (``planer report ... | head``) stops
    quietly with exit code 0, like other command-line tools in a pipe.
    """
    try:
        code = _main(argv)
        sys.stdout.flush()  # now, not at interpreter exit where a closed pipe cannot be handled
        return code
    except BrokenPipeError as exc:  # --help, a usage message or the last flush into a closed pipe
        if not _broken_pipe(exc):
            raise
        return _closed_pipe_exit()


def _printable_units() -> None:
    r"""Let stdout and stderr print the unit µm whatever their encoding.

    A terminal or pipe set to ASCII (``PYTHONIOENCODING=ascii``) cannot encode ``µ``: there it
    is written as ``\xb5`` instead of stopping the command with ``UnicodeEncodeError``.
    """
    for stream in (sys.stdout, sys.stderr):
        try:
            "µ".encode(stream.encoding or "ascii")
        except (UnicodeEncodeError, LookupError):
            reconfigure = getattr(stream, "reconfigure", None)
            if reconfigure is not None:
                reconfigure(errors="backslashreplace")
        except AttributeError:  # a stream without an encoding (replaced by a test)
            continue


def _signals() -> None:
    """Ctrl-C stops the command whatever it inherited; SIGUSR1 dumps every thread's stack.

    A shell without job control (a script, ``sh -c``) starts a background command with SIGINT
    ignored, and Python keeps an ignored SIGINT ignored: such a ``planer hil --http`` or
    ``planer sweep`` would go on after ``kill -INT``/Ctrl-C. The command's own contract is that
    Ctrl-C stops it (exit code 130), so SIGINT raises ``KeyboardInterrupt`` again. Only from the
    main thread of a process whose command line this is (``main()`` without ``argv``: the
    ``planer`` script, ``python -m planer.cli``); ``main(argv)`` called by another program (a
    test) leaves that program's signals alone.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        import faulthandler

        faulthandler.register(signal.SIGUSR1, file=sys.__stderr__, all_threads=True, chain=False)
    except (AttributeError, ValueError, OSError, RuntimeError):  # no usable stderr descriptor
        pass


def _main(argv: Sequence[str] | None) -> int:
    if argv is None:
        _signals()
    argv = list(sys.argv[1:] if argv is None else argv)
    _printable_units()
    parser = build_parser(chosen_command(argv))
    args = parser.parse_args(argv)
    name = f"planer {args.command}"
    debug = os.environ.get(TRACEBACK_ENV, "") not in ("", "0")
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        _quiet_teardown()
        print(f"{name}: interrupted", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as exc:  # PlanerError subclasses are among these
        if _broken_pipe(exc):
            return _closed_pipe_exit()
        if debug:
            raise
        _quiet_teardown()
        print(f"{name}: error: {error_line(exc)}", file=sys.stderr, flush=True)
        return EXIT_ERROR
    # One of the project's three bare ``except Exception`` handlers: the process's
    # outermost boundary. Whatever a command let escape is a bug; the user still gets one line
    # and exit code 3 instead of a traceback, and PLANER_TRACEBACK=1 gives the traceback.
    # Nothing runs after it, so swallowing cannot leave a half-working process behind.
    except Exception as exc:
        if _broken_pipe(exc):
            return _closed_pipe_exit()
        if debug:
            raise
        _quiet_teardown()
        print(
            f"{name}: internal error: {type(exc).__name__}: {error_line(exc)} "
            f"(a bug; {TRACEBACK_ENV}=1 shows the traceback)",
            file=sys.stderr,
            flush=True,
        )
        return EXIT_INTERNAL


def _closed_pipe_exit() -> int:
    """The reader of stdout has what it wanted: no message, success."""
    _quiet_teardown()
    _silence_closed_streams()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
