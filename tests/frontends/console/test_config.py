"""The `[console]` table: defaults, checks, and the start-up path that refuses bad values."""

from __future__ import annotations

import pytest

from services.bus.config import section
from services.bus.errors import ConfigError
from services.frontends.console.config import ConsoleConfig
from services.tools.cli.main import main as telerobot


def test_defaults() -> None:
    c = ConsoleConfig()
    assert (c.host, c.port, c.master, c.master_id) == ("127.0.0.1", 8080, True, "console")
    assert c.gui_period_s == pytest.approx(1 / 25)


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"port": 70000}, "console.port"),
        ({"master_id": "a/b"}, "console.master_id"),
        ({"gui_rate_hz": 500.0}, "console.gui_rate_hz"),
        ({"video_fps": 60.0}, "console.video_fps"),
        ({"video_fps": 0.0}, "console.video_fps"),
        ({"events": 0}, "console.events"),
        ({"force_rate_hz": 0.0}, "console.force_rate_hz"),
        ({"force_rate_hz": 2000.0}, "console.force_rate_hz"),
        ({"camera_position_m": [1.0, 2.0]}, "console.camera_position_m"),
        ({"prot": 1}, "console.prot"),
    ],
)
def test_bad_values_name_their_key(table: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as err:
        section(ConsoleConfig, table, "console")
    assert err.value.key == key


def test_toml_values() -> None:
    c = section(
        ConsoleConfig,
        {"port": 0, "master": False, "camera_position_m": [2, -1, 1.5]},
        "console",
    )
    assert c.port == 0 and c.master is False and c.camera_position_m == (2.0, -1.0, 1.5)


def test_telerobot_console_refuses_a_bad_port(capsys: pytest.CaptureFixture[str]) -> None:
    assert telerobot(["console", "--port", "70000"]) == 2
    assert "console.port" in capsys.readouterr().err
