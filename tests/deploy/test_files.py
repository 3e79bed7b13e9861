"""The deploy/ files as shipped: Zenoh accepts every JSON5, the profiles parse into every
service's configuration, the certificates script makes a chain clients accept, and the
units, compose files and Dockerfile name only things that exist.

The behaviour of these files on a running router is tested in test_security.py and
test_nat.py; this module checks what can be checked without a network.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import zenoh

from services.bus.config import NodeConfig, control_qos_rules, load_deploy, section
from services.bus.router import router_config
from services.control.arm.config import ArmConfig
from services.control.decision.config import DecisionConfig
from services.control.force.config import ForceConfig
from services.control.master.config import MasterConfig
from services.control.vision.config import VisionConfig
from services.frontends.console.config import ConsoleConfig
from services.tools.cli.launcher import UpConfig
from services.tools.cli.main import COMMANDS
from tests.deploy.cell import DEPLOY, REPO, install, make_certs

ZENOH_FILES = sorted([*DEPLOY.glob("router/*.json5"), *DEPLOY.glob("zenoh/*.json5")])
ROUTER_FILES = sorted(DEPLOY.glob("router/*.json5"))
ALL_MESSAGES = {
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
}


def zconfig(path: Path) -> dict[str, Any]:
    """The file as Zenoh 1.10 parsed it (JSON5 → its own model → JSON)."""
    cfg = zenoh.Config.from_file(str(path))
    return {
        key: json.loads(cfg.get_json(key))
        for key in ("mode", "listen", "connect", "transport", "access_control", "scouting", "qos")
    }


def users() -> dict[str, str]:
    lines = (DEPLOY / "router" / "users.txt").read_text().splitlines()
    return dict(line.split(":", 1) for line in lines if line.strip())


# --- Zenoh configuration ----------------------------------------------------------------


@pytest.mark.parametrize("path", ZENOH_FILES, ids=lambda p: p.name)
def test_zenoh_accepts_every_json5_file(path: Path) -> None:
    assert zconfig(path)


@pytest.mark.parametrize("path", ZENOH_FILES, ids=lambda p: p.name)
def test_an_unknown_key_would_be_refused(path: Path, tmp_path: Path) -> None:
    """So the test above means something: the same file with a misspelt key fails."""
    text = path.read_text()
    bad = tmp_path / path.name
    bad.write_text(text.replace("  transport: {", "  transport: {\n    no_such_key: 1,", 1))
    assert bad.read_text() != text
    with pytest.raises(zenoh.ZError, match="no_such_key"):
        zenoh.Config.from_file(str(bad))


@pytest.mark.parametrize("path", ROUTER_FILES, ids=lambda p: p.name)
def test_router_files_deny_by_default_with_consistent_rules(path: Path) -> None:
    cfg = zconfig(path)
    acl = cfg["access_control"]
    assert cfg["mode"] == "router"
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"] for s in acl["subjects"]}
    assert len(rules) == len(acl["rules"]), "rule ids are unique"
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= set(rules), policy
        assert set(policy["subjects"]) <= subjects, policy
    for rule in rules.values():
        assert rule["permission"] == "allow", "deny-by-default: every rule allows"
        assert set(rule["messages"]) <= ALL_MESSAGES
    # Only the robot host's own login, on loopback, gets robot/arm/** and the arm and
    # force methods; everyone else's rules never name them.
    robot = next(s for s in acl["subjects"] if s["id"] == "robot-host")
    assert robot["interfaces"] == ["lo"] and robot["usernames"] == ["robot"]
    for policy in acl["policies"]:
        if policy["subjects"] == ["robot-host"]:
            continue
        for rid in policy["rules"]:
            for ke in rules[rid]["key_exprs"]:
                assert ke != "**" and not ke.startswith("@"), (rid, ke)
                if "put" in rules[rid]["messages"] and "ingress" in rules[rid]["flows"]:
                    assert not ke.startswith("robot/arm"), (rid, ke)
                assert not ke.startswith(("robot/arm/rpc", "robot/force/rpc")), (rid, ke)
    assert cfg["transport"]["auth"]["usrpwd"]["dictionary_file"] == "/etc/telerobot/zenoh/users.txt"
    assert cfg["listen"]["endpoints"] == [
        "tcp/0.0.0.0:7447",
        "tls/0.0.0.0:7448",
        "quic/0.0.0.0:7449?mixed_rel=1",
    ]


@pytest.mark.parametrize("path", ROUTER_FILES, ids=lambda p: p.name)
def test_the_operator_exchanges_passivity_energies_and_watchers_see_both(path: Path) -> None:
    """TDPA (issue 18) needs the master's energies in and the slave's out; without these
    rules a station behind the router would run its passivity controller blind."""
    acl = zconfig(path)["access_control"]
    rules = {r["id"]: r for r in acl["rules"]}

    def granted(subject: str, flow: str, message: str) -> set[str]:
        keys: set[str] = set()
        for policy in acl["policies"]:
            if subject not in policy["subjects"]:
                continue
            for rid in policy["rules"]:
                rule = rules[rid]
                if flow in rule["flows"] and message in rule["messages"]:
                    keys.update(rule["key_exprs"])
        return keys

    operator = next(s["id"] for s in acl["subjects"] if "operator" in (s.get("usernames") or []))
    observer = next(s["id"] for s in acl["subjects"] if "observer" in (s.get("usernames") or []))
    assert "robot/passivity/master" in granted(operator, "ingress", "put")
    assert "robot/passivity/slave" not in granted(operator, "ingress", "put")
    for who in (operator, observer):
        assert "robot/passivity/*" in granted(who, "ingress", "declare_subscriber")
    assert "robot/passivity/*" in granted(observer, "egress", "put")
    assert "robot/passivity/master" not in granted(observer, "ingress", "put")


@pytest.mark.parametrize("path", ROUTER_FILES, ids=lambda p: p.name)
def test_router_files_drop_the_control_class_off_host_as_the_nodes_do(path: Path) -> None:
    """zenohd reads these files without our NodeConfig: they carry its two rules themselves,
    and `telerobot router --zenoh-config` on them adds no second copy."""
    ours = zenoh.Config()
    ours.insert_json5("qos/network", json.dumps(control_qos_rules(["lo"])))
    assert zconfig(path)["qos"]["network"] == json.loads(ours.get_json("qos/network"))
    cfg = NodeConfig(mode="router", zenoh_config=str(path), loopback=("lo",)).to_zenoh()
    assert json.loads(cfg.get_json("qos/network")) == zconfig(path)["qos"]["network"]


def test_mtls_variant_differs_only_in_tls_and_the_operator_subject() -> None:
    plain = zconfig(DEPLOY / "router" / "robot-router.json5")
    mtls = zconfig(DEPLOY / "router" / "robot-router-mtls.json5")
    for key in ("rules", "policies", "default_permission", "enabled"):
        assert plain["access_control"][key] == mtls["access_control"][key], key
    tls = mtls["transport"]["link"]["tls"]
    assert tls["enable_mtls"] is True and tls["root_ca_certificate"].endswith("/ca.pem")
    op = next(s for s in mtls["access_control"]["subjects"] if s["id"] == "operator")
    assert op["cert_common_names"] == ["operator"] and op["usernames"] == ["operator"]
    assert op["link_protocols"] == ["tls", "quic"]
    for cfg in (plain, mtls):
        cfg["transport"]["link"].pop("tls")
        cfg["access_control"].pop("subjects")
    assert plain == mtls


def test_logins_match_the_users_file_and_the_acl() -> None:
    table = users()
    assert set(table) == {"robot", "operator", "observer"}
    acl = zconfig(DEPLOY / "router" / "robot-router.json5")["access_control"]
    named = {u for s in acl["subjects"] for u in s.get("usernames") or []}
    assert named == set(table)
    for path in DEPLOY.glob("zenoh/*.json5"):
        login = zconfig(path)["transport"]["auth"]["usrpwd"]
        assert table[login["user"]] == login["password"], path.name


# --- profiles ---------------------------------------------------------------------------


def test_profiles_parse_into_every_service_config(tmp_path: Path) -> None:
    cell = install(tmp_path)
    robot = load_deploy(cell.profile("robot"))
    operator = load_deploy(cell.profile("operator"))
    ArmConfig.from_mapping(robot["arm"])
    section(ForceConfig, robot["force"], "force")
    section(DecisionConfig, robot.get("decision"), "decision")
    VisionConfig.from_mapping(robot["vision"])
    MasterConfig.from_mapping(operator["master"])
    section(ConsoleConfig, operator["console"], "console")
    for deploy in (robot, operator):
        node = section(NodeConfig, deploy["zenoh"], "zenoh")
        assert node.mode == "client", "peers would open listeners that bypass the ACL"
        assert node.to_zenoh() is not None
        up = section(UpConfig, deploy["up"], "up")
        assert set(up.services) <= set(COMMANDS)
    assert section(UpConfig, robot["up"], "up").services[0] == "router"


def test_robot_profile_router_listens_where_its_json5_does(tmp_path: Path) -> None:
    cell = install(tmp_path)
    args = argparse.Namespace(
        config=str(cell.profile("robot")),
        listen=None,
        connect=None,
        zenoh_config=None,
        lease_ms=None,
    )
    cfg = router_config(args)
    assert cfg.mode == "router"
    assert Path(cfg.zenoh_config) == cell.zenoh_dir / "robot-router.json5"
    json5_listen = zconfig(DEPLOY / "router" / "robot-router.json5")["listen"]["endpoints"]
    assert list(cfg.listen) == json5_listen
    assert cfg.to_zenoh() is not None


def test_profiles_name_only_installed_paths() -> None:
    for name in ("robot.toml", "operator.toml", "operator-quic.toml"):
        text = (DEPLOY / name).read_text()
        paths = re.findall(r'"(/etc/telerobot/[^"]+)"', text)
        # each profile names its Zenoh config there: none found means the pattern no longer
        # matches how the profiles write paths, and the loop below would check nothing
        assert paths, f"{name}: no /etc/telerobot path found"
        for path in paths:
            rel = Path(path).relative_to("/etc/telerobot")
            shipped = DEPLOY / ("router" if "router" in rel.name else rel.parts[0]) / rel.name
            assert shipped.is_file(), f"{name} names {path}; nothing in deploy/ installs it"


# --- certificates -----------------------------------------------------------------------


def openssl(*args: str) -> str:
    done = subprocess.run(["openssl", *args], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl (apt-get install openssl)")
def test_make_certs_issues_a_chain_with_the_hosts_in_the_san(tmp_path: Path) -> None:
    out = tmp_path / "certs"
    make_certs(out, "robot.lab.example", "192.0.2.10", "::1")
    for name in ("router", "operator", "observer"):
        openssl("verify", "-CAfile", str(out / "ca.pem"), str(out / f"{name}.pem"))
        assert (out / f"{name}.key").stat().st_mode & 0o077 == 0, "keys are private"
    san = openssl("x509", "-in", str(out / "router.pem"), "-noout", "-ext", "subjectAltName")
    assert "DNS:robot.lab.example" in san and "IP Address:192.0.2.10" in san
    assert "IP Address:0:0:0:0:0:0:0:1" in san
    subject = openssl("x509", "-in", str(out / "operator.pem"), "-noout", "-subject")
    assert subject.strip().endswith("CN = operator")
    usage = openssl("x509", "-in", str(out / "operator.pem"), "-noout", "-ext", "extendedKeyUsage")
    assert "Client Authentication" in usage

    # A second run reuses the CA: earlier client certificates stay valid.
    ca = (out / "ca.pem").read_bytes()
    assert "reusing the CA" in make_certs(out, "robot.lab.example", clients=("station2",))
    assert (out / "ca.pem").read_bytes() == ca
    openssl("verify", "-CAfile", str(out / "ca.pem"), str(out / "operator.pem"))
    openssl("verify", "-CAfile", str(out / "ca.pem"), str(out / "station2.pem"))


def test_make_certs_refuses_bad_arguments(tmp_path: Path) -> None:
    script = str(DEPLOY / "certs" / "make-certs.sh")
    for argv in ([], ["-c", "a b", "host"], ["-c", "router", "host"], ["-d", "x", "host"]):
        done = subprocess.run(
            ["bash", script, "-o", str(tmp_path), *argv],
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode == 2, (argv, done.stdout, done.stderr)


# --- units, compose, image --------------------------------------------------------------


def unit(path: Path) -> dict[str, list[str]]:
    """`Section.Key` → values, in order (systemd allows repeated keys)."""
    out: dict[str, list[str]] = {}
    sect = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("["):
            sect = line.strip("[]")
            continue
        key, _, value = line.partition("=")
        out.setdefault(f"{sect}.{key}", []).append(value)
    return out


def test_systemd_units_run_telerobot_commands_as_a_dedicated_user() -> None:
    systemd = DEPLOY / "systemd"
    router = unit(systemd / "telerobot-router.service")
    template = unit(systemd / "telerobot@.service")
    for u in (router, template):
        assert u["Service.User"] == ["telerobot"]
        assert u["Service.Restart"][0] in ("always", "on-failure")
        assert u["Service.NoNewPrivileges"] == ["yes"]
        exec_start = u["Service.ExecStart"][0].split()
        assert exec_start[0] == "/opt/telerobot/.venv/bin/telerobot"
        assert exec_start[-2:] == ["--config", "/etc/telerobot/robot.toml"]
    assert router["Service.ExecStart"][0].split()[1] == "router"
    assert template["Service.ExecStart"][0].split()[1] == "%i"
    assert "telerobot-router.service" in template["Unit.After"][0]
    target = unit(systemd / "telerobot-robot.target")
    wanted = " ".join(target["Unit.Wants"]).split()
    services = section(UpConfig, load_deploy(DEPLOY / "robot.toml")["up"], "up").services
    assert {w.removeprefix("telerobot@").removesuffix(".service") for w in wanted} == {
        "telerobot-router" if s == "router" else s for s in services
    }
    rt = unit(systemd / "telerobot@force.service.d" / "realtime.conf")
    assert rt["Service.AmbientCapabilities"] == ["CAP_SYS_NICE"]
    assert rt["Service.LimitRTPRIO"] == ["10"] and rt["Service.RestrictRealtime"] == ["no"]


def test_compose_files_use_the_shipped_paths_and_commands() -> None:
    robot = (DEPLOY / "compose" / "robot.yml").read_text()
    operator = (DEPLOY / "compose" / "operator.yml").read_text()
    assert "image: eclipse/zenoh:1.10" in robot
    assert 'command: ["-c", "/etc/telerobot/zenoh/robot-router.json5"]' in robot
    for text in (robot, operator):
        assert "dockerfile: deploy/Dockerfile" in text and "context: ../.." in text
        assert "network_mode: host" in text
    for svc in ("arm", "force", "decision", "vision"):
        assert f'command: ["{svc}", "--config", "/etc/telerobot/robot.toml"]' in robot
    assert 'command: ["up", "/etc/telerobot/operator.toml"]' in operator


def test_dockerfile_copies_what_exists() -> None:
    text = (DEPLOY / "Dockerfile").read_text()
    for src in re.findall(r"^COPY (.+) \S+$", text, flags=re.M):
        for part in src.split():
            assert (REPO / part).exists(), part
    assert 'ENTRYPOINT ["telerobot"]' in text and "USER telerobot" in text


def test_the_quic_profile_is_the_operator_profile_over_quic(tmp_path: Path) -> None:
    """operator-quic.toml differs from operator.toml in its link only, and dials the QUIC
    listener of robot.toml's router with the same `mixed_rel` (else no connection)."""
    cell = install(tmp_path)
    tls = load_deploy(cell.profile("operator"))
    quic = load_deploy(cell.profile("operator-quic"))
    assert quic["zenoh"].pop("connect") == ["quic/robot.lab.example:7449?mixed_rel=1"]
    assert tls["zenoh"].pop("connect") == ["tls/robot.lab.example:7448"]
    assert quic == tls
    listen = load_deploy(cell.profile("robot"))["router"]["listen"]
    assert "quic/0.0.0.0:7449?mixed_rel=1" in listen
    MasterConfig.from_mapping(quic["master"])
    assert section(NodeConfig, quic["zenoh"] | {"connect": ["quic/h:1?mixed_rel=1"]}, "zenoh")
