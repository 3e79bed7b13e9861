"""Configuration from one place: `section()` refuses what a misspelt TOML would slip through,
NodeConfig keeps the lease within the contract's 2 s, and the precedence is
defaults < deployment file `[zenoh]` < command-line flags (STYLE.md 'Services')."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import pytest

from services.bus.config import (
    MAX_LEASE_MS,
    NodeConfig,
    add_node_args,
    endpoints,
    load_deploy,
    node_config,
    section,
    service_config,
)
from services.bus.errors import ConfigError


@dataclass(frozen=True, slots=True)
class Gains:
    k_n_per_m: float = 100.0
    axes: tuple[int, int, int] = (1, 1, 1)


@dataclass(frozen=True, slots=True)
class ArmSection:
    """A service table like the ones services declare."""

    port: str
    rate_hz: float = 100.0
    period_ms: int = 10
    simulate: bool = False
    backend: Literal["sim", "serial"] = "sim"
    home: tuple[float, ...] = ()
    gains: Gains = field(default_factory=Gains)
    note: str | None = None

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ConfigError("arm.rate_hz", "must be > 0")


def _parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_node_args(p)
    return p.parse_args(list(argv))


# --- section() -------------------------------------------------------------------------


def test_section_builds_the_dataclass_with_coercion() -> None:
    s = section(
        ArmSection,
        {
            "port": "socket://127.0.0.1:5000",
            "rate_hz": 250,  # an int where a float is allowed
            "period_ms": 4,
            "simulate": True,
            "backend": "serial",
            "home": [0, 1.5, -1.5, 0, 0, 0],
            "gains": {"k_n_per_m": 50, "axes": [1, 0, 1]},
        },
        "arm",
    )
    assert s == ArmSection(
        port="socket://127.0.0.1:5000",
        rate_hz=250.0,
        period_ms=4,
        simulate=True,
        backend="serial",
        home=(0.0, 1.5, -1.5, 0.0, 0.0, 0.0),
        gains=Gains(k_n_per_m=50.0, axes=(1, 0, 1)),
    )
    assert isinstance(s.rate_hz, float) and isinstance(s.gains.k_n_per_m, float)
    assert section(ArmSection, {"port": "x"}, "arm") == ArmSection(port="x")


def test_section_refuses_unknown_keys_naming_section_dot_key() -> None:
    with pytest.raises(ConfigError) as info:
        section(ArmSection, {"port": "x", "rate_hx": 10.0}, "arm")
    assert info.value.key == "arm.rate_hx"
    assert "unknown key" in str(info.value) and "rate_hz" in str(info.value)


def test_section_refuses_unknown_keys_in_nested_tables() -> None:
    with pytest.raises(ConfigError) as info:
        section(ArmSection, {"port": "x", "gains": {"kp": 1.0}}, "arm")
    assert info.value.key == "arm.gains.kp"


def test_section_names_a_missing_required_key() -> None:
    with pytest.raises(ConfigError) as info:
        section(ArmSection, {}, "arm")
    assert info.value.key == "arm.port"


@pytest.mark.parametrize(
    ("key", "value", "named"),
    [
        ("port", 5000, "arm.port"),
        ("rate_hz", "fast", "arm.rate_hz"),
        ("rate_hz", True, "arm.rate_hz"),
        ("rate_hz", float("inf"), "arm.rate_hz"),
        ("rate_hz", float("nan"), "arm.rate_hz"),
        ("period_ms", 2.5, "arm.period_ms"),
        ("period_ms", True, "arm.period_ms"),
        ("period_ms", "10", "arm.period_ms"),
        ("simulate", 1, "arm.simulate"),
        ("simulate", "yes", "arm.simulate"),
        ("backend", "usb", "arm.backend"),
        ("home", 1.0, "arm.home"),
        ("home", [0.0, "x"], "arm.home[1]"),
        ("gains", 3, "arm.gains"),
        ("gains", {"axes": [1, 1]}, "arm.gains.axes"),
        ("gains", {"axes": [1, 1, 1.5]}, "arm.gains.axes[2]"),
        ("note", 5, "arm.note"),
    ],
)
def test_section_refuses_bad_types_naming_the_key(key: str, value: object, named: str) -> None:
    with pytest.raises(ConfigError) as info:
        section(ArmSection, {"port": "x", key: value}, "arm")
    assert info.value.key == named, str(info.value)


def test_section_runs_post_init_checks() -> None:
    with pytest.raises(ConfigError) as info:
        section(ArmSection, {"port": "x", "rate_hz": 0}, "arm")
    assert info.value.key == "arm.rate_hz"


def test_section_refuses_a_non_dataclass() -> None:
    with pytest.raises(TypeError):
        section(dict, {}, "x")


# --- NodeConfig -------------------------------------------------------------------------


def test_node_config_defaults_follow_the_contract() -> None:
    c = NodeConfig()
    assert c.mode == "peer" and c.lease_ms <= MAX_LEASE_MS == 2000
    assert c.multicast_scouting is False
    z = c.to_zenoh()
    assert json.loads(z.get_json("transport/link/tx/lease")) == c.lease_ms
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    assert json.loads(z.get_json("mode")) == "peer"


@pytest.mark.parametrize("lease_ms", [2001, 5000, 10_000, 99])
def test_lease_outside_100_to_2000_ms_is_refused(lease_ms: int) -> None:
    with pytest.raises(ConfigError) as info:
        NodeConfig(lease_ms=lease_ms)
    assert info.value.key == "zenoh.lease_ms"
    with pytest.raises(ConfigError) as info:
        section(NodeConfig, {"lease_ms": lease_ms}, "zenoh")
    assert info.value.key == "zenoh.lease_ms"


def test_lease_of_2000_ms_is_the_limit() -> None:
    z = NodeConfig(lease_ms=2000).to_zenoh()
    assert json.loads(z.get_json("transport/link/tx/lease")) == 2000


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"mode": "server"}, "zenoh.mode"),
        ({"connect": ("127.0.0.1:7447",)}, "zenoh.connect"),
        ({"listen": ("localhost",)}, "zenoh.listen"),
        ({"ns": "/cell2"}, "zenoh.ns"),
        ({"ns": "cell2/"}, "zenoh.ns"),
        ({"ns": "cell*"}, "zenoh.ns"),
        ({"zenoh_config": "/nonexistent/router.json5"}, "zenoh.zenoh_config"),
        ({"loopback": ("",)}, "zenoh.loopback"),
        ({"loopback": ("x" * 40,)}, "zenoh.loopback"),
        ({"loopback": ("lo/0",)}, "zenoh.loopback"),
    ],
)
def test_node_config_refuses_bad_values(kwargs: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        NodeConfig(**kwargs)  # type: ignore[arg-type]
    assert info.value.key == key


def test_to_zenoh_writes_endpoints_namespace_and_admin_space(tmp_path: Path) -> None:
    c = NodeConfig(
        mode="client",
        connect=("tcp/127.0.0.1:7447",),
        listen=("tcp/127.0.0.1:7448",),
        ns="cell2",
        lease_ms=1500,
        admin_space=True,
    )
    z = c.to_zenoh()
    assert json.loads(z.get_json("mode")) == "client"
    assert json.loads(z.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7448"]
    assert json.loads(z.get_json("namespace")) == "cell2"
    assert json.loads(z.get_json("adminspace/enabled")) is True


def test_zenoh_json5_file_is_applied_first_and_fields_override_it(tmp_path: Path) -> None:
    f = tmp_path / "z.json5"
    f.write_text(
        '{ // a JSON5 file as zenohd reads it\n mode: "router", '
        "transport: { link: { tx: { lease: 9000 } } }, "
        'listen: { endpoints: ["tcp/127.0.0.1:7999"] } }\n'
    )
    z = NodeConfig(zenoh_config=str(f), lease_ms=1000).to_zenoh()
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7999"]
    assert json.loads(z.get_json("transport/link/tx/lease")) == 1000
    assert json.loads(z.get_json("mode")) == "peer"


def test_a_broken_zenoh_json5_file_is_a_config_error(tmp_path: Path) -> None:
    f = tmp_path / "bad.json5"
    f.write_text("{ mode: ")
    with pytest.raises(ConfigError) as info:
        NodeConfig(zenoh_config=str(f)).to_zenoh()
    assert info.value.key == "zenoh.zenoh_config"


# --- precedence: defaults < file [zenoh] < flags -----------------------------------------


def test_node_config_precedence(tmp_path: Path) -> None:
    deploy = tmp_path / "deploy.toml"
    deploy.write_text(
        '[zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\nlease_ms = 1500\nns = "cell1"\n'
    )
    defaults: dict[str, Any] = {
        "connect": ("tcp/127.0.0.1:7447",),
        "lease_ms": 800,
        "listen": ("tcp/0.0.0.0:1",),
    }

    # defaults only
    c0 = node_config(_parse(), {}, **defaults)
    assert c0.connect == ("tcp/127.0.0.1:7447",) and c0.lease_ms == 800 and c0.mode == "peer"

    # the file overrides the defaults it names, keeps the others
    c1 = node_config(_parse("--config", str(deploy)), **defaults)
    assert c1.mode == "client" and c1.connect == ("tcp/10.0.0.1:7447",)
    assert c1.lease_ms == 1500 and c1.ns == "cell1" and c1.listen == ("tcp/0.0.0.0:1",)

    # flags override the file
    args = _parse(
        "--config",
        str(deploy),
        "--connect",
        "tcp/127.0.0.1:9000",
        "-e",
        "tcp/127.0.0.1:9001",
        "--mode",
        "peer",
        "--ns",
        "cell2",
        "--lease-ms",
        "2000",
        "--multicast",
    )
    c2 = node_config(args, **defaults)
    assert c2.connect == ("tcp/127.0.0.1:9000", "tcp/127.0.0.1:9001")
    assert c2.mode == "peer" and c2.ns == "cell2" and c2.lease_ms == 2000
    assert c2.multicast_scouting is True and c2.listen == ("tcp/0.0.0.0:1",)


def test_a_flag_lease_above_2000_ms_is_refused() -> None:
    with pytest.raises(ConfigError) as info:
        node_config(_parse("--lease-ms", "3000"), {})
    assert info.value.key == "zenoh.lease_ms"


def test_a_bad_zenoh_table_names_the_key(tmp_path: Path) -> None:
    deploy = tmp_path / "deploy.toml"
    deploy.write_text("[zenoh]\nlease = 1000\n")
    with pytest.raises(ConfigError) as info:
        node_config(_parse("--config", str(deploy)))
    assert info.value.key == "zenoh.lease"


# --- load_deploy and service_config -----------------------------------------------------


def test_load_deploy_of_a_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_deploy(tmp_path / "nope.toml")
    assert info.value.key == "--config" and "nope.toml" in str(info.value)


def test_load_deploy_of_broken_toml_is_a_config_error(tmp_path: Path) -> None:
    f = tmp_path / "broken.toml"
    f.write_text("[arm\nport = ")
    with pytest.raises(ConfigError) as info:
        load_deploy(f)
    assert info.value.key == "--config"


def test_load_deploy_without_a_file_is_empty() -> None:
    assert load_deploy(None) == {} and load_deploy("") == {}


def test_service_config_reads_its_table_and_overrides(tmp_path: Path) -> None:
    f = tmp_path / "deploy.toml"
    f.write_text('[arm]\nport = "/dev/ttyUSB0"\nrate_hz = 50.0\n[force]\nx = 1\n')
    args = _parse("--config", str(f))
    s = service_config(ArmSection, args, "arm", {"rate_hz": 200.0, "simulate": None})
    assert s.port == "/dev/ttyUSB0" and s.rate_hz == 200.0 and s.simulate is False
    f.write_text('[arm]\nport = "x"\nbaud = 9600\n')
    with pytest.raises(ConfigError) as info:
        service_config(ArmSection, args, "arm")
    assert info.value.key == "arm.baud"


def test_endpoints_normalises() -> None:
    assert endpoints(None) == ()
    assert endpoints("tcp/127.0.0.1:1") == ("tcp/127.0.0.1:1",)
    assert endpoints(["tcp/a:1", "tcp/b:2"]) == ("tcp/a:1", "tcp/b:2")


@dataclass(frozen=True, slots=True)
class Tables:
    commands: dict[str, Any] = field(default_factory=dict)
    rates_hz: dict[str, float] = field(default_factory=dict)


def test_section_reads_free_form_tables(tmp_path: Path) -> None:
    """Tables such as `[up.commands]` are read as dicts, values checked by their type."""
    f = tmp_path / "deploy.toml"
    f.write_text('[up.commands]\nrec = ["telerobot", "record"]\n[up.rates_hz]\nforce = 1000\n')
    t = section(Tables, load_deploy(f)["up"], "t")
    assert t.commands == {"rec": ["telerobot", "record"]} and t.rates_hz == {"force": 1000.0}
    with pytest.raises(ConfigError) as info:
        section(Tables, {"rates_hz": {"force": "fast"}}, "t")
    assert info.value.key == "t.rates_hz.force"
    with pytest.raises(ConfigError) as info:
        section(Tables, {"commands": ["rec"]}, "t")
    assert info.value.key == "t.commands"


def test_a_misspelt_table_is_refused_naming_it_and_the_known_ones(tmp_path: Path) -> None:
    """`[decison] max_force_n = 30.0` used to be ignored: the decision ran with 40 N."""
    f = tmp_path / "typo.toml"
    f.write_text("[decison]\nmax_force_n = 30.0\n")
    with pytest.raises(ConfigError) as info:
        load_deploy(f)
    assert info.value.key == "decison"
    assert "unknown table [decison] (did you mean [decision]?)" in str(info.value)
    assert "[force]" in str(info.value) and "typo.toml" in str(info.value)


def test_a_key_outside_any_table_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "loose.toml"
    f.write_text("max_force_n = 30.0\n[decision]\nwatchdog_ms = 100\n")
    with pytest.raises(ConfigError) as info:
        load_deploy(f)
    assert info.value.key == "max_force_n" and "outside any table" in str(info.value)


def test_a_huge_table_name_is_not_echoed_whole(tmp_path: Path) -> None:
    f = tmp_path / "huge.toml"
    f.write_text(f"[{'x' * 5000}]\na = 1\n")
    with pytest.raises(ConfigError) as info:
        load_deploy(f)
    assert len(str(info.value)) < 600


def test_every_shipped_profile_has_only_known_tables() -> None:
    from services.bus.config import TABLES

    root = Path(__file__).resolve().parents[2] / "deploy"
    profiles = sorted(root.glob("*.toml"))
    assert len(profiles) >= 3
    for p in profiles:
        assert set(load_deploy(p)) <= TABLES, p
