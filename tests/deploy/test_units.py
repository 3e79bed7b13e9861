"""deploy/systemd/: every unit and drop-in passes `systemd-analyze verify`, and the units
start the processes deploy/compose/robot.yml starts.

`systemd-analyze verify` loads each unit as systemd would (the template's instances with
their drop-in, the target with what it wants) and reports unknown keys, bad values and
missing executables; it exits 0 on warnings, so its output must be empty too. The only
rewrite is the executable's path (/opt/telerobot/.venv/bin/telerobot, an installed host's,
→ this checkout's), which verify wants to exist.

The comparison reads the units' keys and the compose file's YAML: the same services (the
target's, the compose file's and robot.toml's [up]), the same command line per service
(`telerobot NAME --config /etc/telerobot/robot.toml`; the router: zenohd there reading the
JSON5 that [router] of robot.toml names, our router here reading that table), no
capability but the force service's SYS_NICE, its real-time priority limit (the
SCHED_FIFO priority the force service asks for), the same user and groups, the hardware
the profile names, SIGTERM with a 10 s grace to stop.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest
import yaml

from services.control.force.priority import FIFO_RT_PRIORITY
from tests.deploy.cell import DEPLOY, REPO

SYSTEMD = DEPLOY / "systemd"
INSTALLED_BIN = "/opt/telerobot/.venv/bin/telerobot"
CONFIG = ["--config", "/etc/telerobot/robot.toml"]


# settings that accumulate over assignments (an empty one resets them); the others: the
# last assignment wins
LISTS = {
    "Wants", "After", "Requires", "WantedBy", "CapabilityBoundingSet", "AmbientCapabilities",
    "SupplementaryGroups", "RestrictAddressFamilies", "Environment",
}  # fmt: skip


def unit_keys(*paths: Path) -> dict[str, list[str]]:
    """`Key=value` lines of unit files read in order, each key's values as systemd reads
    them: lists accumulate (an empty assignment resets them), others are replaced."""
    keys: dict[str, list[str]] = {}
    for path in paths:
        for raw in path.read_text().splitlines():
            line = raw.strip()
            if not line or line[0] in "#;[":
                continue
            key, _, value = line.partition("=")
            if value == "" or key not in LISTS:
                keys[key] = []
            if value:
                keys.setdefault(key, []).extend([value] if key == "ExecStart" else value.split())
    return keys


def instance(name: str) -> dict[str, list[str]]:
    """The keys of telerobot@NAME.service: the template, then its drop-ins."""
    drop = sorted((SYSTEMD / f"telerobot@{name}.service.d").glob("*.conf"))
    return unit_keys(SYSTEMD / "telerobot@.service", *drop)


def exec_argv(keys: dict[str, list[str]], name: str) -> list[str]:
    (line,) = keys["ExecStart"]
    argv = line.replace("%i", name).split()
    assert argv[0] == INSTALLED_BIN, argv
    return argv[1:]


def compose() -> dict[str, Any]:
    doc = yaml.safe_load((DEPLOY / "compose" / "robot.yml").read_text())
    return dict(doc["services"])


def profile() -> dict[str, Any]:
    return tomllib.loads((DEPLOY / "robot.toml").read_text())


def wanted() -> set[str]:
    """The target's services: telerobot-router → router, telerobot@X → X."""
    names = set()
    for unit in unit_keys(SYSTEMD / "telerobot-robot.target")["Wants"]:
        m = re.fullmatch(r"telerobot(?:-(router)|@(\w+))\.service", unit)
        assert m, unit
        names.add(m.group(1) or m.group(2))
    return names


# --- systemd-analyze verify ---------------------------------------------------------------
def verify(tmp_path: Path, *units: str, edit: tuple[str, str] | None = None) -> str:
    """`systemd-analyze verify` of copies of the units; its output (empty when clean)."""
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("no systemd-analyze (apt-get install systemd)")
    exe = REPO / ".venv" / "bin" / "telerobot"
    assert exe.exists(), "make install first"
    shutil.copytree(SYSTEMD, tmp_path / "units")
    for f in (tmp_path / "units").rglob("*"):
        if f.is_file():
            text = f.read_text().replace(INSTALLED_BIN, str(exe))
            if edit is not None and f.name == edit[0]:
                text += edit[1]
            f.write_text(text)
    argv = [analyze, "verify", *(str(tmp_path / "units" / u) for u in units)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 or edit is not None, done.stdout + done.stderr
    return (done.stdout + done.stderr).strip()


def all_units() -> list[str]:
    return [
        "telerobot-robot.target",
        "telerobot-router.service",
        *(f"telerobot@{n}.service" for n in sorted(wanted() - {"router"})),
    ]


def test_every_unit_and_drop_in_verifies_clean(tmp_path: Path) -> None:
    assert verify(tmp_path, *all_units()) == ""


def test_verify_reads_the_force_drop_in(tmp_path: Path) -> None:
    # the same run with a misspelt key in the drop-in says so: the drop-in is verified
    out = verify(tmp_path, "telerobot@force.service", edit=("realtime.conf", "LimitRTPRIOX=10\n"))
    assert "Unknown key 'LimitRTPRIOX'" in out, out


# --- units ≡ compose ------------------------------------------------------------------------
def test_the_units_compose_and_the_profile_run_the_same_services() -> None:
    assert wanted() == set(compose()) == set(profile()["up"]["services"])
    assert (SYSTEMD / "telerobot@.service").exists()
    dropins = {p.parent.name for p in SYSTEMD.glob("*.service.d/*.conf")}
    assert dropins == {"telerobot@force.service.d"}, dropins


def test_each_service_gets_the_same_command_line() -> None:
    services = compose()
    for name in sorted(wanted() - {"router"}):
        assert exec_argv(instance(name), name) == [name, *CONFIG] == services[name]["command"]
    router_unit = exec_argv(unit_keys(SYSTEMD / "telerobot-router.service"), "router")
    assert router_unit == ["router", *CONFIG]
    # zenohd in compose reads the JSON5 our router reads through robot.toml's [router]
    json5 = profile()["router"]["zenoh_config"]
    assert services["router"]["command"] == ["-c", json5]
    override = yaml.safe_load((DEPLOY / "compose" / "robot.python-router.yml").read_text())
    assert override["services"]["router"]["command"] == router_unit


def test_only_force_gets_a_capability_and_its_rt_priority_matches() -> None:
    services = compose()
    for name in sorted(wanted() - {"router"}):
        keys, svc = instance(name), services[name]
        granted = {c.removeprefix("CAP_") for c in keys.get("AmbientCapabilities", [])}
        bounding = {c.removeprefix("CAP_") for c in keys["CapabilityBoundingSet"]}
        assert granted == bounding == ({"SYS_NICE"} if name == "force" else set()), name
        assert svc["cap_drop"] == ["ALL"], name
        assert set(svc.get("cap_add", [])) == granted, (name, svc.get("cap_add"), granted)
        assert keys["NoNewPrivileges"] == ["yes"]
        assert "no-new-privileges:true" in svc["security_opt"], name
        rtprio = svc.get("ulimits", {}).get("rtprio")
        if name == "force":
            assert keys["RestrictRealtime"] == ["no"]
            assert keys["LimitRTPRIO"] == [str(FIFO_RT_PRIORITY)]
            assert rtprio == FIFO_RT_PRIORITY
        else:
            assert keys["RestrictRealtime"] == ["yes"], name
            assert "LimitRTPRIO" not in keys and rtprio is None, name
    router = unit_keys(SYSTEMD / "telerobot-router.service")
    assert router["CapabilityBoundingSet"] == [] and "AmbientCapabilities" not in router
    assert services["router"]["cap_drop"] == ["ALL"] and "cap_add" not in services["router"]


def test_the_same_user_groups_devices_and_stop() -> None:
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    m = re.search(r"useradd .*--groups (\S+)", dockerfile)
    assert m and re.search(r"^USER telerobot$", dockerfile, re.M), "the image's user"
    image_groups = set(m.group(1).split(","))
    prof, services = profile(), compose()
    hardware = {
        "arm": {prof["arm"]["port"]},
        "force": {prof["force"]["port"]},
        "vision": {f"/dev/video{i}" for i in prof["vision"]["devices"]},
    }
    for name in sorted(wanted() - {"router"}):
        keys, svc = instance(name), services[name]
        assert keys["User"] == ["telerobot"] and set(keys["SupplementaryGroups"]) == image_groups
        assert "user" not in svc, name  # the image's
        devices = {d.split(":")[1] for d in svc.get("devices", [])}
        assert devices == hardware.get(name, set()), (name, devices)
        assert "PrivateDevices" not in keys  # the units see the host's /dev
        assert keys["KillSignal"] == ["SIGTERM"] and keys["TimeoutStopSec"] == ["10"]
        # compose: SIGTERM, then 10 s, unless the file says otherwise
        assert svc.get("stop_signal", "SIGTERM") == "SIGTERM", name
        assert svc.get("stop_grace_period", "10s") == "10s", name
        assert svc["restart"] == "unless-stopped" and keys["Restart"] == ["on-failure"]
