"""DecisionConfig: defaults, checks naming the key, the TOML table, the command line."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.bus.config import section
from services.bus.errors import ConfigError
from services.control.decision.__main__ import main
from services.control.decision.config import DecisionConfig
from services.control.passivity.slave import YIELD_M_S_N
from services.world.workcell.scene import TABLE


def test_defaults_keep_the_tool_out_of_the_table() -> None:
    cfg = DecisionConfig()
    assert cfg.rate_hz >= 500 and cfg.watchdog_ms == 100 and cfg.stale_ms == 50
    assert cfg.max_force_n == 40 and cfg.max_torque_nm == 4 and cfg.compliance is False
    assert cfg.workspace_min[2] >= TABLE.top_z  # the box floor is the table top
    lo, hi = TABLE.lo, TABLE.hi
    assert cfg.workspace_min[0] <= lo[0] and cfg.workspace_max[0] >= hi[0]
    assert cfg.workspace_min[1] <= lo[1] and cfg.workspace_max[1] >= hi[1]
    assert cfg.period_s == pytest.approx(0.002)
    assert cfg.settings()["workspace_max"] == [0.95, 0.5, 1.2]


@pytest.mark.parametrize(
    ("changes", "key"),
    [
        ({"rate_hz": 0.0}, "decision.rate_hz"),
        ({"watchdog_ms": -1.0}, "decision.watchdog_ms"),
        ({"max_force_n": float("nan")}, "decision.max_force_n"),
        ({"admittance_deadband_n": -0.1}, "decision.admittance_deadband_n"),
        ({"workspace_min": (0.0, 0.0, 2.0)}, "decision.workspace_max"),
        ({"workspace_max": (1.0, 1.0)}, "decision.workspace_max"),
        ({"compliance": 1}, "decision.compliance"),
        ({"estop_power_off": "yes"}, "decision.estop_power_off"),
        ({"max_tool_speed_m_s": float("inf")}, "decision.max_tool_speed_m_s"),
        ({"workspace_min": [0.25, "a", 0.4]}, "decision.workspace_min[1]"),
        ({"max_force_n": 1e9}, "decision.max_force_n"),
        ({"guarded_speed_m_s": 0.5}, "decision.guarded_speed_m_s"),
        ({"approach_zone_m": -0.01}, "decision.approach_zone_m"),
        ({"approach_zone_m": 5.0}, "decision.approach_zone_m"),
        ({"passivity_yield_m_s_n": -1e-5}, "decision.passivity_yield_m_s_n"),
        ({"passivity_yield_m_s_n": 2.0}, "decision.passivity_yield_m_s_n"),
        ({"passivity_yield_max_rtt_ms": 0.0}, "decision.passivity_yield_max_rtt_ms"),
        ({"passivity_yield_max_rtt_ms": 1e9}, "decision.passivity_yield_max_rtt_ms"),
        ({"passivity_yield_max_rtt_ms": float("nan")}, "decision.passivity_yield_max_rtt_ms"),
        ({"approach_speed_m_s": 0.0}, "decision.approach_speed_m_s"),
        ({"approach_speed_m_s": 0.3}, "decision.approach_speed_m_s"),
    ],
)
def test_bad_values_name_their_key(changes: dict[str, object], key: str) -> None:
    """Through the one config reader, as the deployment file and the `supervisor` method
    build it: types by the reader, ranges by the dataclass."""
    with pytest.raises(ConfigError) as e:
        section(DecisionConfig, changes, "decision")
    assert e.value.key == key


def test_the_toml_table() -> None:
    cfg = section(
        DecisionConfig,
        {"watchdog_ms": 150, "compliance": True, "workspace_max": [0.9, 0.4, 1.0]},
        "decision",
    )
    assert cfg.watchdog_ms == 150.0 and cfg.compliance
    assert cfg.workspace_max == (0.9, 0.4, 1.0)
    with pytest.raises(ConfigError) as e:
        section(DecisionConfig, {"watchdog": 150}, "decision")
    assert e.value.key == "decision.watchdog"


def test_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    assert "--compliance" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text("[decision]\nmax_force_n = -3\n")
    assert main(["--config", str(bad)]) == 2
    assert "'decision.max_force_n'" in capsys.readouterr().err


def test_the_yield_to_the_hand_is_on_for_short_round_trips_by_default() -> None:
    """The measured rate (the port's own constant), up to 500 ms of round trip
    (docs/passivity.md, "The round trip")."""
    cfg = DecisionConfig()
    assert cfg.passivity_yield_m_s_n == YIELD_M_S_N
    assert cfg.passivity_yield_max_rtt_ms == 500.0


def _described(**changes: object) -> object:
    from services.bus.messages import ArmDescription
    from services.control.arm.model import load_model

    return ArmDescription(seq=1, t_ns=1, **{**load_model("fr3").description(), **changes})


def test_the_arm_s_description_bounds_the_box_and_the_tool_speeds() -> None:
    box = {"min": [0.3, -0.2, 0.5], "max": [0.7, 0.2, 0.9]}
    cfg = DecisionConfig(task_speed_m_s=0.2, approach_speed_m_s=0.05)
    bound = cfg.with_arm(_described(workspace=box, max_tool_speed_m_s=0.1))
    assert bound.workspace_min == (0.3, -0.2, 0.5) and bound.workspace_max == (0.7, 0.2, 0.9)
    assert bound.max_tool_speed_m_s == 0.1 and bound.task_speed_m_s == 0.1
    assert bound.approach_speed_m_s == 0.05  # already below: unchanged
    # a faster arm never raises the configured speeds; a box of our own wins when asked
    own = DecisionConfig(workspace_from_arm=False)
    fast = own.with_arm(_described(workspace=box, max_tool_speed_m_s=50.0))
    assert fast.workspace_max == own.workspace_max
    assert fast.max_tool_speed_m_s == own.max_tool_speed_m_s
    # a description without a box leaves the configured one
    assert cfg.with_arm(_described(workspace=None)).workspace_min == cfg.workspace_min
