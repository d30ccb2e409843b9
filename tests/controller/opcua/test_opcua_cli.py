"""``--opcua`` of ``planer serve`` / ``planer hil``: bad input is one line and exit code 2,
before anything starts."""

from __future__ import annotations

import socket

import pytest

pytest.importorskip("asyncua")

from planer.cli import main  # noqa: E402


@pytest.mark.parametrize(("argv", "needle"), [
    (["serve", "--opcua", "http://127.0.0.1:4840"], "opcua endpoint must look like"),
    (["serve", "--opcua", "opc.tcp://10.1.2.3:4840"], "non-loopback"),
    (["hil", "--in-process", "--opcua", "opc.tcp://127.0.0.1"], "opcua endpoint must look like"),
    (["hil", "--in-process", "--opcua", "opc.tcp://0.0.0.0:4840"], "non-loopback"),
])
def test_bad_opcua_is_one_line(argv, needle, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    if argv[0] == "hil":
        argv = [*argv, "--log", str(tmp_path / "q.sqlite")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and err[0].startswith(f"planer {argv[0]}: error:")
    assert not (tmp_path / "q.sqlite").exists()


def test_busy_port_stops_serve_before_the_service(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        code = main(["serve", "--opcua", f"opc.tcp://127.0.0.1:{port}",
                     "--log", str(tmp_path / "q.sqlite")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and f"port {port} is busy" in err[0]
    assert not (tmp_path / "q.sqlite").exists()  # the service never opened its log
