"""The service unit: required settings, and `systemd-analyze verify` where available."""

import configparser
import shutil
import subprocess
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "cmnav.service"


def _unit():
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str
    parser.read(UNIT)
    return parser


def test_required_settings():
    service = _unit()["Service"]
    assert service["Type"] == "notify"
    assert service["WatchdogSec"]
    assert service["Restart"] == "on-failure"
    assert service["RestartPreventExitStatus"] == "2"  # cmnav fly: bad config or model, a restart cannot help
    assert service["User"] == "cmnav"
    assert "plugdev" in service["SupplementaryGroups"]
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp"):
        assert service[key] == "yes"
    assert service["ProtectSystem"] == "strict"
    assert service["ReadWritePaths"] == "/var/log/cmnav"
    assert "cmnav fly --config" in service["ExecStart"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify(tmp_path):
    # The executable only exists on the Jetson; point a copy at one that exists here so that
    # verify checks everything else in the unit.
    unit = tmp_path / "cmnav.service"
    unit.write_text(UNIT.read_text().replace("/opt/cmnav/venv/bin/cmnav", shutil.which("true")))
    proc = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    complaints = ("Unknown", "Invalid", "Failed to parse", "ignoring")
    problems = [line for line in (proc.stdout + proc.stderr).splitlines() if any(w in line for w in complaints)]
    assert proc.returncode == 0 and not problems, proc.stdout + proc.stderr
