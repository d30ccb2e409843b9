"""systemd's notification protocol (:mod:`controller.sd_notify`) against a real socket.

A ``SOCK_DGRAM`` Unix socket bound in a temporary folder plays systemd: ``NOTIFY_SOCKET`` names
it, ``WATCHDOG_USEC`` asks for the watchdog.
"""

from __future__ import annotations

import asyncio
import os
import socket

import pytest

from controller.sd_notify import Notifier, under_journald


@pytest.fixture
def systemd(tmp_path, monkeypatch):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify"))
    monkeypatch.setenv("WATCHDOG_USEC", "40000")  # pings every 20 ms
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()


def _drain(sock) -> list[str]:
    out = []
    sock.setblocking(False)
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except BlockingIOError:
        return out
    finally:
        sock.setblocking(True)


def test_ready_status_and_stopping_reach_the_socket(systemd):
    n = Notifier()
    assert n.enabled and n.watchdog_s == pytest.approx(0.04)
    n.ready("serving")
    n.status("waiting in the safe state: PLC 127.0.0.1:5020 not answering")
    n.status("waiting in the safe state: PLC 127.0.0.1:5020 not answering")  # not repeated
    n.status("two\nlines")
    n.stopping()
    assert _drain(systemd) == [
        "READY=1\nSTATUS=serving",
        "STATUS=waiting in the safe state: PLC 127.0.0.1:5020 not answering",
        "STATUS=two lines",
        "STOPPING=1",
    ]


def test_the_watchdog_pings_from_the_loop_and_stops_when_the_loop_is_stuck(systemd):
    n = Notifier()
    period = n.watchdog_s / 2

    async def main():
        task = asyncio.create_task(n.watchdog())
        got = []
        while len(got) < 3:  # pings while the loop runs
            await asyncio.sleep(period)
            got += _drain(systemd)
        assert set(got) == {"WATCHDOG=1"}
        # the loop stuck for six periods: blocked in a recv on this thread, no task runs
        _drain(systemd)
        systemd.settimeout(6 * period)
        with pytest.raises(TimeoutError):
            systemd.recv(4096)
        systemd.settimeout(None)
        # the loop free again: the pings resume
        again = []
        while not again:
            await asyncio.sleep(period)
            again += _drain(systemd)
        task.cancel()
        return again

    assert set(asyncio.run(main())) == {"WATCHDOG=1"}


def test_outside_systemd_nothing_is_sent_and_the_watchdog_returns(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.setenv("WATCHDOG_USEC", "40000")
    n = Notifier()
    assert not n.enabled
    n.ready("x")
    asyncio.run(asyncio.wait_for(n.watchdog(), 5))  # returns at once


def test_a_watchdog_for_another_process_is_not_ours(systemd, monkeypatch):
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert Notifier().watchdog_s is None
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert Notifier().watchdog_s == pytest.approx(0.04)


@pytest.mark.parametrize("env, words", [
    ({"WATCHDOG_USEC": "soon"}, "WATCHDOG_USEC"),
    ({"WATCHDOG_USEC": "0"}, "WATCHDOG_USEC"),
    ({"NOTIFY_SOCKET": "relative/notify"}, "NOTIFY_SOCKET"),
])
def test_bad_environment_is_refused_naming_the_variable(systemd, monkeypatch, env, words):
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(ValueError, match=words):
        Notifier()


def test_a_socket_nobody_listens_on_is_named(tmp_path, monkeypatch):
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone"))
    with pytest.raises(OSError, match="NOTIFY_SOCKET"):
        Notifier()


@pytest.mark.parametrize("env, journal", [
    ({}, False), ({"JOURNAL_STREAM": "8:12345"}, True), ({"INVOCATION_ID": "ab12"}, True),
])
def test_the_journal_is_recognised(env, journal):
    assert under_journald(env) is journal
