"""ForceConfig: defaults are valid, every bad value names its key."""

from __future__ import annotations

import subprocess
import sys
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from services.bus.errors import ConfigError
from services.control.force.backends import BACKENDS, open_force_sensor, sensor_options
from services.control.force.config import ForceConfig
from services.control.force.netft import NetFTSensor
from services.control.force.sensors import SENSOR_KINDS
from services.control.force.serial_sensor import SerialSensor
from services.control.force.sim_sensor import SimSensor


def test_defaults_are_the_papers_and_the_protocols() -> None:
    c = ForceConfig()
    assert (c.sensor, c.period_ms, c.priority) == ("sim", 1.0, "normal")
    assert c.handoff == "inline"  # one put per sample from the sampling thread, no queue
    m = c.wrist_model()
    assert_allclose(m.p_et, [0, 0, 0.2])  # PROTOCOL.md's default tool
    assert_allclose(m.R_es, np.eye(3))  # the paper's R_s ≡ R_e at rest
    assert_allclose(m.calibration, np.eye(6))


@pytest.mark.parametrize(
    ("kw", "key"),
    [
        ({"sensor": "usb"}, "force.sensor"),
        ({"priority": "realtime"}, "force.priority"),
        ({"period_ms": 0.0}, "force.period_ms"),
        ({"period_ms": float("nan")}, "force.period_ms"),
        ({"K_l_n_per_m": -1.0}, "force.K_l_n_per_m"),
        ({"K_r_nm_per_rad": (1.0, 0.0, 1.0)}, "force.K_r_nm_per_rad"),
        ({"calibration": (1.0,) * 35}, "force.calibration"),
        ({"calibration": (0.0,) * 36}, "force.calibration"),
        ({"tool_R": (1.0, 0, 0, 0, 1.0, 0, 0, 0, -1.0)}, "force.tool_R"),
        ({"sensor_R": (2.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0)}, "force.sensor_R"),
        ({"tool_mass_kg": -0.1}, "force.tool_mass_kg"),
        ({"tool_com_m": (0.0, float("inf"), 0.0)}, "force.tool_com_m"),
        ({"noise_n": -1.0}, "force.noise_n"),
        ({"stale_after_periods": 11}, "force.stale_after_periods"),
        ({"queue_len": 0}, "force.queue_len"),
        ({"netft_port": 70000}, "force.netft_port"),
        ({"counts_per_force": 0.0}, "force.counts_per_force"),
        ({"bias_samples": True}, "force.bias_samples"),
        ({"sensor": "serial", "port": ""}, "force.port"),
        ({"handoff": "thread"}, "force.handoff"),
        ({"inertia": 1}, "force.inertia"),
    ],
)
def test_bad_values_name_their_key(kw: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as e:
        ForceConfig(**kw)
    assert e.value.key == key


@settings(max_examples=100, deadline=None)
@given(k=st.floats(allow_nan=True, allow_infinity=True))
def test_stiffness_must_be_positive_and_finite(k: float) -> None:
    try:
        ForceConfig(K_l_n_per_m=k)
    except ConfigError as e:
        assert e.key == "force.K_l_n_per_m"
        assert not (k > 0 and np.isfinite(k))
    else:
        assert k > 0 and np.isfinite(k)


def test_open_force_sensor_builds_each_backend_from_the_config() -> None:
    assert set(BACKENDS.names) == set(SENSOR_KINDS)
    assert isinstance(open_force_sensor(ForceConfig()), SimSensor)
    serial = ForceConfig(sensor="serial", port="socket://127.0.0.1:1")
    assert isinstance(open_force_sensor(serial), SerialSensor)
    assert sensor_options(serial) == {"port": "socket://127.0.0.1:1", "baudrate": 921_600}
    net = ForceConfig(sensor="netft", host="127.0.0.1", netft_port=2)
    sensor = open_force_sensor(net)
    assert isinstance(sensor, NetFTSensor) and sensor.name == "netft 127.0.0.1:2"


def test_a_name_without_a_backend_is_a_config_error() -> None:
    with pytest.raises(ConfigError) as e:
        BACKENDS.build("usb", {})
    assert e.value.key == "force.sensor"


def test_the_simulation_does_not_load_pyserial() -> None:
    code = (
        "import sys\n"
        "from services.control.force.backends import open_force_sensor\n"
        "from services.control.force.config import ForceConfig\n"
        "open_force_sensor(ForceConfig())\n"
        "print('serial' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_reads_from_a_deployment_table() -> None:
    section = pytest.importorskip("services.bus.config").section
    c = section(
        ForceConfig,
        {
            "sensor": "netft",
            "host": "127.0.0.1",
            "period_ms": 2,
            "priority": "above_normal",
            "K_l_n_per_m": [1e4, 1e4, 2e4],
            "K_r_nm_per_rad": 40,
            "calibration": "identity",
            "tool_com_m": [0.0, 0.0, -0.05],
        },
        "force",
    )
    assert c.period_ms == 2.0 and c.K_l_n_per_m == (1e4, 1e4, 2e4) and c.K_r_nm_per_rad == 40.0
    with pytest.raises(ConfigError) as e:
        section(ForceConfig, {"periode_ms": 2}, "force")
    assert e.value.key == "force.periode_ms"
    with pytest.raises(ConfigError) as e:
        section(ForceConfig, {"calibration": [1.0] * 36}, "force")
    assert e.value.key == "force.calibration"
