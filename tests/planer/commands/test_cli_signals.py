"""The ``planer`` command's signals: ``kill -USR1`` writes every thread's stack and goes on;
a SIGINT its parent ignored is heard again (``planer/cli.py``)."""

from __future__ import annotations

import signal
import subprocess

from tests.support.interrupt import ended_or_stacks, planer_argv


def _until(stream, text: str) -> list[str]:
    lines = []
    for line in stream:
        lines.append(line)
        if text in line:
            return lines
    raise AssertionError(f"never printed {text!r}: {lines}")


def test_usr1_dumps_every_threads_stack_and_the_command_goes_on(tmp_path):
    proc = subprocess.Popen(
        planer_argv("sim", "--no-images", "--port", "0", "--spool", str(tmp_path / "spool")),
        cwd=tmp_path, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _until(proc.stdout, "ready")
        proc.send_signal(signal.SIGUSR1)
        dump = _until(proc.stderr, "(most recent call first)")  # the first thread's header
        dump += _until(proc.stderr, 'File "')
        assert proc.poll() is None  # still running
        proc.send_signal(signal.SIGINT)
        out, err = ended_or_stacks(proc, "planer sim after SIGUSR1 and Ctrl-C")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, "".join(dump) + err
    assert "stopped at t=" in out
    assert "Thread 0x" in "".join(dump) or "Current thread 0x" in "".join(dump), dump


def test_a_planer_started_with_sigint_ignored_hears_it_again(tmp_path):
    """The CLI's start makes SIGINT raise KeyboardInterrupt: ``hil`` mid-run ends with 130."""
    proc = subprocess.Popen(
        planer_argv("hil", "--in-process", "--plc", "direct", "--log",
                    str(tmp_path / "h.sqlite"), sigint="ignored"),
        cwd=tmp_path, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        _until(proc.stderr, "recovered")  # the loop is closed: mid-run
        proc.send_signal(signal.SIGINT)
        _, err = ended_or_stacks(proc, "planer hil after Ctrl-C")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "planer hil: interrupted"
