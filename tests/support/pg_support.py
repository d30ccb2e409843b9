"""A throw-away PostgreSQL server for tests (PostgreSQL 15's ``initdb`` / ``pg_ctl``).

``pg_server`` (session fixture) initialises a cluster in a temporary folder, listens on
127.0.0.1 and a unix socket in that folder only, and is stopped and removed at the end. As root
the server runs as the ``postgres`` user (``runuser``). Tests that use it skip with the reason
when the binaries, psycopg or a usable user are missing. ``fresh_db`` gives each test its own
empty database.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

_BIN_DIRS = ("/usr/lib/postgresql/15/bin", "/usr/lib/postgresql/16/bin")
_names = itertools.count()


def _binary(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    for d in _BIN_DIRS:
        p = Path(d) / name
        if p.is_file():
            return str(p)
    return None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class PgServer:
    """One PostgreSQL cluster in ``root`` (trust authentication, loopback only)."""

    def __init__(self, root: Path, *, run_as: str | None) -> None:
        self.root = root
        self.data = root / "data"
        self.log = root / "server.log"
        self.port = _free_port()
        self._run_as = run_as
        self._pg_ctl = _binary("pg_ctl")
        initdb = _binary("initdb")
        self._cmd([initdb, "-D", str(self.data), "-U", "postgres", "--auth=trust",
                   "--no-sync", "-E", "UTF8", "--locale=C"])

    def _cmd(self, argv: list, *, check: bool = True) -> subprocess.CompletedProcess:
        if self._run_as:
            argv = ["runuser", "-u", self._run_as, "--", *argv]
        out = subprocess.run([str(a) for a in argv], capture_output=True, text=True,
                             timeout=120)
        if check and out.returncode != 0:
            raise RuntimeError(f"{argv[-3:]} failed: {out.stderr.strip() or out.stdout.strip()}")
        return out

    def start(self) -> None:
        """Start the server and wait until it accepts connections (``pg_ctl -w``)."""
        opts = (f"-k {self.root} -h 127.0.0.1 -p {self.port} -c fsync=off "
                "-c full_page_writes=off -c max_connections=40")
        self._cmd([self._pg_ctl, "-D", self.data, "-o", opts, "-l", self.log, "-w", "start"])

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (``immediate``: like a crash, open transactions are lost)."""
        self._cmd([self._pg_ctl, "-D", self.data, "-m", mode, "-w", "stop"], check=False)

    def port_open(self) -> bool:
        """Whether the server accepts TCP connections now."""
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port),
                                                                    timeout=1.0):
            return True
        return False

    def url(self, db: str = "postgres") -> str:
        """The connection URL of database ``db`` (TCP, 127.0.0.1)."""
        return f"postgresql://postgres@127.0.0.1:{self.port}/{db}"

    def create_db(self) -> str:
        """A new empty database; its URL."""
        import psycopg

        name = f"t{os.getpid()}_{next(_names)}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)


def _skip_reason() -> str | None:
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "psycopg (psycopg[binary]) is not installed"
    if not (_binary("initdb") and _binary("pg_ctl")):
        return "PostgreSQL binaries (initdb, pg_ctl) not found"
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root and there is no postgres user to run the server"
        if not shutil.which("runuser"):
            return "running as root and runuser is missing"
    return None


@pytest.fixture(scope="session")
def pg_server() -> Iterator[PgServer]:
    """A running PostgreSQL server for the whole session (skips with the reason)."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    root = Path(tempfile.mkdtemp(prefix="planer-pg-"))
    run_as = None
    if os.geteuid() == 0:
        run_as = "postgres"
        pw = pwd.getpwnam("postgres")
        os.chown(root, pw.pw_uid, pw.pw_gid)
    os.chmod(root, 0o700)
    server = None
    try:
        server = PgServer(root, run_as=run_as)
        server.start()
        yield server
    finally:
        if server is not None:
            server.stop("immediate")
        with contextlib.suppress(OSError):
            shutil.rmtree(root)


@pytest.fixture
def fresh_db(pg_server: PgServer) -> str:
    """URL of a new empty database on the session's server."""
    return pg_server.create_db()


def wait_until(predicate, *, timeout_s: float = 30.0, what: str = "condition") -> None:
    """Poll ``predicate()`` until it is true (the world's pace, not a fixed sleep)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)
