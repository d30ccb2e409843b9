"""The shipped systemd unit (``deploy/planer.service``, ``docs/deploy.md``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "deploy" / "planer.service"


def _settings(text: str) -> dict[str, list[str]]:
    """``{"Section.Key": [values in order]}`` of a unit file (keys may repeat)."""
    out: dict[str, list[str]] = {}
    section = ""
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.setdefault(f"{section}.{key.strip()}", []).append(value.strip())
    return out


def test_the_unit_is_a_notify_service_with_watchdog_restart_and_hardening():
    s = _settings(UNIT.read_text())
    one = {k: v[-1] for k, v in s.items()}
    assert one["Service.Type"] == "notify"
    assert one["Service.WatchdogSec"].rstrip("s").isdigit()
    assert one["Service.Restart"] in ("on-failure", "always", "on-abnormal")
    assert one["Service.User"] == one["Service.Group"] == "planer"
    assert one["Service.ProtectSystem"] == "strict"
    assert one["Service.NoNewPrivileges"] == "yes"
    assert one["Service.ExecStart"].split()[1:3] == ["serve", "--config"]
    # writable: only the quality log's folder and the spool, the ones docs/deploy.md configures
    writable = " ".join(s["Service.ReadWritePaths"]).split()
    assert writable == ["/var/lib/planer", "/var/spool/planer"]
    docs = (ROOT / "docs" / "deploy.md").read_text()
    assert 'spool_dir = "/var/spool/planer"' in docs
    assert 'path = "/var/lib/planer/quality.sqlite"' in docs
    assert one["Service.WorkingDirectory"] in writable
    assert one["Install.WantedBy"] == "multi-user.target"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd not installed")
def test_systemd_accepts_the_unit(tmp_path):
    """``systemd-analyze verify``, the program path pointed at an existing executable."""
    text = UNIT.read_text().replace("/opt/planer/venv/bin/planer", sys.executable)
    unit = tmp_path / "planer.service"
    unit.write_text(text)
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True,
                       timeout=60)
    complaints = [ln for ln in (r.stdout + r.stderr).splitlines()
                  if "planer.service" in ln]
    assert r.returncode == 0 and complaints == [], r.stdout + r.stderr


def test_the_unit_grants_the_loop_its_priority_and_raises_nothing_itself():
    """The service raises its loop thread and lowers its servers itself: the unit grants the
    right (``CAP_SYS_NICE``, an ``RLIMIT_RTPRIO`` above the loop's), keeps a hard real-time CPU
    limit above the service's own guard, and never raises the whole process tree."""
    from core.realtime import INTERFACE_RT_PRIORITY, RT_CPU_LIMIT_S

    s = _settings(UNIT.read_text())
    one = {k: v[-1] for k, v in s.items()}
    assert "CAP_SYS_NICE" in one["Service.AmbientCapabilities"].split()
    assert "CAP_SYS_NICE" in one["Service.CapabilityBoundingSet"].split()
    assert int(one["Service.LimitRTPRIO"]) >= INTERFACE_RT_PRIORITY
    rttime = one["Service.LimitRTTIME"]
    assert rttime.endswith("s") and ":" not in rttime  # soft = hard; the service lowers soft
    assert RT_CPU_LIMIT_S < float(rttime.rstrip("s")) <= 10.0  # a net, under WatchdogSec
    for key in ("CPUSchedulingPolicy", "CPUSchedulingPriority", "Nice",
                "CPUSchedulingResetOnFork"):
        assert f"Service.{key}" not in s, key  # the pages' process would be raised too
    docs = (ROOT / "docs" / "deploy.md").read_text()
    assert "## Priority" in docs and "LimitRTTIME=2s" in docs


def _syscalls(groups: list[str], seen: set[str] | None = None) -> set[str]:
    """The system calls of ``systemd-analyze syscall-filter`` groups, nested groups expanded."""
    seen = set() if seen is None else seen
    out: set[str] = set()
    for group in groups:
        if group in seen:
            continue
        seen.add(group)
        r = subprocess.run(["systemd-analyze", "syscall-filter", group], capture_output=True,
                           text=True, timeout=60)
        for line in r.stdout.splitlines()[1:]:
            name = line.strip()
            if not name or name.startswith("#"):
                continue
            out |= _syscalls([name], seen) if name.startswith("@") else {name}
    return out


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd not installed")
def test_the_system_call_filter_lets_the_service_set_its_priorities():
    s = _settings(UNIT.read_text())
    allowed = " ".join(v for v in s["Service.SystemCallFilter"] if not v.startswith("~")).split()
    denied = " ".join(v[1:] for v in s["Service.SystemCallFilter"] if v.startswith("~")).split()
    needed = {"sched_setscheduler", "setpriority", "prlimit64", "rt_sigaction"}
    assert needed <= _syscalls(allowed)
    assert not needed & _syscalls(denied)
