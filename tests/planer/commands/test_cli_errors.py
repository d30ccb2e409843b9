"""Bad input to every command: one line on stderr naming the bad value, a non-zero exit.

The table drives ``planer.cli.main`` in-process; a few cases run the real ``planer`` process
(whole-interpreter behaviour: no teardown chatter after the error line, Ctrl-C handling).
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from controller.quality.log import QualityLog
from planer import cli

ROOT = Path(__file__).resolve().parents[3]


def _run(argv, capsys):
    try:
        rc = cli.main(argv)
    except SystemExit as exc:  # argparse usage errors
        rc = exc.code
    cap = capsys.readouterr()
    return rc, [ln for ln in cap.err.splitlines() if ln.strip()], cap.out


@pytest.fixture()
def files(tmp_path):
    """Bad files of every kind a user could hand over."""
    f = {}

    def write(name, text):
        p = tmp_path / name
        p.write_text(text)
        f[name] = str(p)

    write("range.toml", "[feed]\nmin_mm_s = -5\n")
    write("type.toml", '[feed]\nmin_mm_s = "fast"\n')
    write("misspelt_key.toml", "[feed]\nmni_mm_s = 5\n")
    write("not_toml.toml", "[feed\nmin_mm_s = 5\n")
    write("port.toml", "[modbus]\nport = 70000\n")
    write("safe.toml", '[safety]\nsafe_state = "stop"\n')
    write("plc_port.toml", '[plc]\nport = "x"\n')
    write("source.toml", '[frames]\nsource = "inprocess"\n')
    write("scen_type.toml", '[x]\ndistance_m = "far"\n')
    write("scen_key.toml", "[x]\ndistanse_m = 2.0\n")
    write("a_file", "not a folder\n")
    write("corrupt.sqlite", "garbage, not SQLite\n")
    write("not_image.png", "not an image")
    (tmp_path / "empty.sqlite").write_bytes(b"")
    (tmp_path / "folder").mkdir()
    f["folder"] = str(tmp_path / "folder")
    f["missing"] = str(tmp_path / "nope.toml")
    f["under_file"] = str(tmp_path / "a_file" / "x.sqlite")
    f["empty.sqlite"] = str(tmp_path / "empty.sqlite")
    f["tmp"] = str(tmp_path)
    return f


# (argv template, substring the one error line must contain); {name} -> files[name]
CASES = [
    # the command line itself
    (["nonsense"], "nonsense"),
    (["sim", "--port", "abc"], "'abc'"),
    (["sim", "--bogus"], "--bogus"),
    (["bench", "--only", "nosuch"], "nosuch"),
    (["calibrate", "{not_image.png}"], "--pattern"),
    # planer sim: config files and options
    (["sim", "--config", "{missing}"], "nope.toml"),
    (["sim", "--config", "{range.toml}"], "feed.min_mm_s"),
    (["sim", "--config", "{type.toml}"], "'fast'"),
    (["sim", "--config", "{misspelt_key.toml}"], "feed.mni_mm_s"),
    (["sim", "--config", "{not_toml.toml}"], "not_toml.toml"),
    (["sim", "--config", "{port.toml}"], "modbus.port"),
    (["sim", "--port", "70000"], "--port"),
    (["sim", "--port", "-1"], "--port"),
    (["sim", "--time-scale", "-1"], "--time-scale"),
    (["sim", "--duration", "nan"], "--duration"),
    (["sim", "--progress", "0"], "--progress"),
    (["sim", "--port", "0", "--spool", "{a_file}"], "--spool"),
    # planer serve
    (["serve", "--config", "{missing}"], "nope.toml"),
    (["serve", "--config", "{safe.toml}"], "'stop'"),
    (["serve", "--config", "{plc_port.toml}"], "plc.port"),
    (["serve", "--config", "{source.toml}"], "inprocess"),
    (["serve", "--max-frames", "0"], "--max-frames"),
    (["serve", "--status-every", "0"], "--status-every"),
    (["serve", "--log", "{under_file}"], "--log"),
    (["serve", "--log", "{folder}"], "--log"),
    # planer hil
    (["hil", "--in-process", "--scenario", "nosuch"], "nosuch"),
    (["hil", "--in-process", "--scenario", "{missing}"], "nope.toml"),
    (["hil", "--in-process", "--scenario", "{scen_type.toml}:x"], "distance_m"),
    (["hil", "--in-process", "--scenario", "{scen_key.toml}:x"], "distanse_m"),
    (["hil", "--in-process", "--distance-m", "-1"], "--distance-m"),
    (["hil", "--in-process", "--seed", "-3"], "--seed"),
    (["hil", "--in-process", "--log", "{under_file}"], "--log"),
    (["hil", "--in-process", "--log", "{folder}"], "--log"),
    # planer report
    (["report", "{missing}"], "nope.toml"),
    (["report", "{corrupt.sqlite}"], "corrupt.sqlite"),
    (["report", "{empty.sqlite}"], "empty.sqlite"),
    (["report", "{folder}"], "folder"),
    # planer calibrate
    (["calibrate", "{not_image.png}", "--pattern", "7y7", "--out", "{tmp}/r.toml"], "7y7"),
    (["calibrate", "{not_image.png}", "--pattern", "7x7", "--square-mm", "-1",
      "--out", "{tmp}/r.toml"], "--square-mm"),
    (["calibrate", "{not_image.png}", "--pattern", "7x7", "--out", "{under_file}"], "--out"),
    (["calibrate", "{not_image.png}", "--pattern", "7x7", "--out", "{tmp}/r.toml",
      "--rig", "{range.toml}"], "range.toml"),
    (["calibrate", "{not_image.png}", "--pattern", "7x7", "--out", "{tmp}/r.toml"], "usable"),
]


def _fill(arg, files):
    for key, value in files.items():
        arg = arg.replace("{" + key + "}", value)
    return arg


@pytest.mark.parametrize("argv, names", CASES, ids=[" ".join(c[0])[:60] for c in CASES])
def test_bad_input_gives_one_line_naming_the_value(argv, names, files, capsys, monkeypatch):
    monkeypatch.chdir(files["tmp"])  # nothing lands in the repository
    rc, err, _out = _run([_fill(a, files) for a in argv], capsys)
    assert rc not in (0, None)
    errors = [ln for ln in err if ": warning: " not in ln]
    assert len(errors) == 1, err
    assert ": error: " in errors[0] and "Traceback" not in errors[0]
    assert names in errors[0], errors[0]


def test_report_checks_its_output_paths_before_reading(files, capsys, monkeypatch):
    monkeypatch.chdir(files["tmp"])
    log = Path(files["tmp"]) / "run.sqlite"
    QualityLog(log).close()
    for extra, name in ((["--out", files["a_file"]], "--out"),
                        (["--csv", files["under_file"]], "--csv")):
        rc, err, _ = _run(["report", str(log), *extra], capsys)
        assert rc == 2 and len(err) == 1 and name in err[0], err
    rc, err, out = _run(["report", str(log)], capsys)  # an empty log is reported, not an error
    assert rc == 0 and "0 measurements" in out and "No figures" in out


def test_port_in_use_is_named_before_anything_starts(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        rc, err, out = _run(["sim", "--port", str(port), "--no-images"], capsys)
    assert rc == 2 and len(err) == 1 and f"{port}" in err[0] and "in use" in err[0]
    assert "ready" not in out


def test_output_file_and_folder_checks(tmp_path):
    target = tmp_path / "new" / "deeper" / "log.sqlite"
    assert cli.output_file("--log", target) == str(target)
    assert target.parent.is_dir() and not target.exists()  # folder made, file not
    assert cli.output_folder("--out", tmp_path / "figs") == str(tmp_path / "figs")
    (tmp_path / "f").write_text("x")
    for call in (lambda: cli.output_file("--log", tmp_path),
                 lambda: cli.output_file("--log", tmp_path / "f" / "x"),
                 lambda: cli.output_folder("--out", tmp_path / "f"),
                 lambda: cli.output_file("--log", "")):
        with pytest.raises(ValueError, match="--log|--out"):
            call()


def test_os_errors_read_as_path_then_reason():
    exc = FileNotFoundError(2, "No such file or directory", "/x/y")
    assert cli.error_line(exc) == "/x/y: No such file or directory"
    assert cli.error_line(ValueError("first\nsecond")) == "first"
    assert cli.error_line(ValueError("")) == "ValueError"


@pytest.mark.parametrize("exc, code, text", [
    (KeyboardInterrupt(), 130, "planer bench: interrupted"),
    (RuntimeError("boom\nmore"), 3, "planer bench: internal error: RuntimeError: boom"),
    (OSError("disk gone"), 2, "planer bench: error: disk gone"),
])
def test_every_exception_ends_in_one_line(exc, code, text, capsys, monkeypatch):
    def boom(args):
        raise exc

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda *_: parser)
    parser._subparsers._group_actions[0].choices["bench"].set_defaults(_run=boom)
    monkeypatch.delenv(cli.TRACEBACK_ENV, raising=False)
    assert cli.main(["bench"]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(text), err
    monkeypatch.setenv(cli.TRACEBACK_ENV, "1")  # developers get the traceback
    if code != 130:
        with pytest.raises(type(exc)):
            cli.main(["bench"])


def test_waiting_line_names_every_missing_source():
    from planer.commands.serve import waiting_line

    line = waiting_line(("plc", "can", "measurement"), plc="h:1", can="virtual:x",
                        frames="spool d")
    assert "h:1" in line and "virtual:x" in line and "spool d" in line
    assert "\n" not in line
    assert "confirming" in waiting_line((), plc="", can="", frames="")


# ------------------------------------------------------------------ the real process
def _planer(*argv, cwd, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop(cli.TRACEBACK_ENV, None)
    return subprocess.Popen(
        [sys.executable, "-m", "planer.cli", *argv], cwd=cwd, env=env, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL), **kw,
    )


def test_process_error_is_exactly_one_line(tmp_path):
    bad = tmp_path / "sim.toml"
    bad.write_text("[can]\ninterface = 'virtual'\n[feed]\nmin_mm_s = -5\n")
    p = _planer("sim", "--config", str(bad), cwd=tmp_path)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 2
    assert err.splitlines() == [f"planer sim: error: {bad}: feed.min_mm_s must be > 0.0, got -5"]


def _wait_for(stream, word):
    lines = []
    for line in stream:
        lines.append(line)
        if word in line:
            return lines
    raise AssertionError(f"never printed {word!r}: {lines}")


def test_ctrl_c_stops_sim_cleanly(tmp_path):
    p = _planer("sim", "--no-images", "--port", "0", "--spool", str(tmp_path / "spool"),
                cwd=tmp_path)
    try:
        _wait_for(p.stdout, "ready")
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 0, err
    assert "stopped at t=" in out and "Traceback" not in err


def test_ctrl_c_interrupts_hil_with_130_and_keeps_the_log(tmp_path):
    log = tmp_path / "hil.sqlite"
    p = _planer("hil", "--in-process", "--plc", "direct", "--log", str(log), cwd=tmp_path)
    try:
        _wait_for(p.stderr, "recovered")  # the loop is closed: mid-run
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 130, err
    assert err.strip().splitlines()[-1] == "planer hil: interrupted"
    assert "Traceback" not in err and "PASSED" not in out


def test_sim_into_a_pipe_that_closes_ends_quietly(tmp_path):
    """``planer sim | head -3``: the reader goes away; exit 0, no "Broken pipe" on stderr."""
    r, w = os.pipe()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen(
        [sys.executable, "-m", "planer.cli", "sim", "--no-images", "--port", "0", "--spool",
         str(tmp_path / "spool"), "--progress", "0.05"],
        cwd=tmp_path, env=env, stdout=w, stderr=subprocess.PIPE, text=True,
    )
    os.close(w)
    try:
        with os.fdopen(r) as head:
            lines = [head.readline() for _ in range(3)]  # what `head -3` takes, then it exits
        err = p.communicate(timeout=120)[1]
    finally:
        p.kill()
    assert lines[0].startswith("modbus: ")
    assert p.returncode == 0, err
    assert "Broken pipe" not in err and "Traceback" not in err and err.strip() == ""


_DRIVER = r"""
import json, re, signal, subprocess, sys
cmd = [sys.executable, "-m", "planer.cli"]
sim = subprocess.Popen(cmd + ["sim", "--config", "sim_udp.toml"],
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
for line in sim.stdout:
    if line.strip() == "ready":
        break
# events, not a count of pairs: a service that starts on a loaded host may measure a backlog of
# pairs before its recovery time has passed; stop it once control resumed and a progress line
# (20 measurements) came after it
serve = subprocess.Popen(cmd + ["serve"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
said, resumed = [], False
for line in serve.stdout:
    said.append(line)
    if "recovered: control resumed" in line:
        resumed = True
    elif resumed and re.search(r"#\d+ +run +ok ", line):
        break
serve.send_signal(signal.SIGINT)
rest, serve_err = serve.communicate(timeout=120)
sim.send_signal(signal.SIGINT)
sim_out = sim.communicate(timeout=120)[0]
print(json.dumps({"serve_rc": serve.returncode, "serve_out": "".join(said) + rest,
                  "serve_err": serve_err, "sim_rc": sim.returncode, "sim_out": sim_out}))
"""


def test_serve_against_sim_as_the_docs_say(tmp_path):
    """README / docs/service.md: sim with udp_multicast CAN and the shipped machine.toml.

    Real time, as a user runs it (the shipped time scale): no timing is asserted, only that
    the service closes the loop and measures every pair; the time limits are backstops for a
    loaded 2-core host (the simulator slows its clock rather than starving its interfaces).
    """
    from protocol import can_transport

    try:
        import msgpack  # noqa: F401
    except ImportError:
        pytest.skip("udp_multicast needs msgpack")
    if not can_transport.private_netns_available():
        pytest.skip("no unprivileged network namespaces here")
    (tmp_path / "sim_udp.toml").write_text(
        '[can]\ninterface = "udp_multicast"\nchannel = "239.74.163.2"\n'
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = can_transport.run_in_private_netns([sys.executable, "-c", _DRIVER], cwd=tmp_path,
                                           env=env, stdout=subprocess.PIPE, text=True)
    out, _ = p.communicate(timeout=420)
    res = json.loads(out)
    assert res["serve_rc"] == 0 and res["sim_rc"] == 0, res
    assert "recovered: control resumed" in res["serve_out"]
    stopped = re.search(r"stopped: (\d+) pairs, (\d+) measured", res["serve_err"])
    assert stopped, res["serve_err"]
    with QualityLog(tmp_path / "runs" / "quality.sqlite", create=False) as log:
        records = log.records()
    assert len(records) == int(stopped.group(1)) >= 20  # every pair logged
    errors = [(r.seq, r.error) for r in records if not r.ok]
    # every pair logged with its reason; nearly all measured (12 of 12 in each of 4 runs under
    # six CPU hogs, docs/simulator.md; one clean-clone run in the middle of the whole suite had 2
    # of 20 refused, their reasons then not shown: they are now)
    assert all(err for _, err in errors), errors
    assert len(errors) <= 0.1 * len(records), errors


def test_multicast_outside_a_namespace_says_what_to_do_in_words(tmp_path, capsys, monkeypatch):
    """The refusal names the remedy a user can follow, not Python functions."""
    from protocol import can_transport

    monkeypatch.setattr(can_transport, "network_interfaces", lambda: ["lo", "eth0"])
    monkeypatch.chdir(tmp_path)
    rc, err, _ = _run(["serve", "--max-frames", "1", "--log", str(tmp_path / "q.sqlite")],
                      capsys)
    assert rc == 2 and len(err) == 1
    line = err[0]
    assert line.startswith("planer serve: error: udp_multicast would reach the network outside "
                           "this host")
    for words in ("eth0", "private network namespace", "unshare", "nsenter", "README.md",
                  '"Simulator and service in two terminals"', "docs/service.md", "planer hil"):
        assert words in line, words
    for api in ("run_in_private_netns", "protocol", "loopback_only", "()"):
        assert api not in line, api
