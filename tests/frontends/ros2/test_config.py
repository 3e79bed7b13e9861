"""The [ros2] table: the shipped profiles parse, bad values are refused, defaults resolve."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.bus.config import NodeConfig, load_deploy, section
from services.bus.errors import ConfigError
from services.frontends.ros2.config import Ros2Config
from services.frontends.ros2.service import bridge_node_config, ros_side_config
from services.tools.cli.launcher import UpConfig

DEPLOY = Path(__file__).resolve().parents[3] / "deploy"


@pytest.mark.parametrize("profile", ["sim.toml", "robot.toml"])
def test_profiles_enable_the_bridge(profile: str) -> None:
    deploy = load_deploy(DEPLOY / profile)
    cfg = section(Ros2Config, deploy["ros2"], "ros2")
    assert cfg.wrench_rate_hz == 250.0
    assert "ros2" in section(UpConfig, deploy["up"], "up").services


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"domain_id": 300}, "ros2.domain_id"),
        ({"namespace": "a b"}, "ros2.namespace"),
        ({"node_name": "x/y"}, "ros2.node_name"),
        ({"wrench_rate_hz": 0.0}, "ros2.wrench_rate_hz"),
        ({"target_timeout_s": float("inf")}, "ros2.target_timeout_s"),
        ({"master_rate_hz": 10.0}, "ros2.master_rate_hz"),
        ({"master_id": "a/b"}, "ros2.master_id"),
        ({"tool_frame": "stereo_left"}, "ros2"),
        # the world and the arm's frames are the URDF's (the arm's description), not ours
        ({"world_frame": "world"}, "ros2.world_frame"),
        ({"flange_frame": "flange"}, "ros2.flange_frame"),
        ({"typo_hz": 1.0}, "ros2.typo_hz"),
    ],
)
def test_bad_values_are_refused(table: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as e:
        section(Ros2Config, table, "ros2")
    assert e.value.key == key


def test_domain_and_namespace_resolution(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert Ros2Config().resolved_domain_id() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert Ros2Config().resolved_domain_id() == 42
    assert Ros2Config(domain_id=3).resolved_domain_id() == 3
    monkeypatch.setenv("ROS_DOMAIN_ID", "banana")
    with pytest.raises(ConfigError):
        Ros2Config().resolved_domain_id()
    assert Ros2Config().resolved_namespace("") == "/"
    assert Ros2Config().resolved_namespace("cell2") == "/cell2"
    assert Ros2Config(namespace="lab/arm").resolved_namespace("cell2") == "/lab/arm"


def test_downsampling_rules_carry_the_namespace() -> None:
    base = NodeConfig(connect=("tcp/127.0.0.1:7447",), ns="cell2")
    cfg = bridge_node_config(base, Ros2Config(state_rate_hz=40.0))
    rules = json.loads(cfg.to_zenoh().get_json("downsampling"))[0]
    assert rules["flows"] == ["ingress"]
    assert {(r["key_expr"], r["freq"]) for r in rules["rules"]} == {
        ("cell2/robot/state", 40.0),
        ("cell2/robot/force", 250.0),
    }
    assert cfg.ns == "cell2" and cfg.connect == base.connect


def test_the_ros_side_session_has_no_namespace_and_no_listener() -> None:
    zc = ros_side_config(NodeConfig(listen=("tcp/0.0.0.0:7448",), ns="cell2"))
    assert json.loads(zc.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7448"]
    assert json.loads(zc.get_json("namespace")) is None
    with pytest.raises(ConfigError):
        ros_side_config(NodeConfig(ns="cell2"))
