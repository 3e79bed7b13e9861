"""One contract for every ForceSensor backend: Sim, Serial and Net F/T against their fakes.

Each backend gets a way to apply a known wrench at the tool point (tool frame); the contract
then checks, through the same eq. (4) model the service uses, that the sensor reports it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass

import numpy as np
import pytest

from services.bus.errors import ConfigError
from services.control.force.backends import open_force_sensor
from services.control.force.config import ForceConfig
from services.control.force.fake_netft import FakeNetFT
from services.control.force.fake_serial_sensor import FakeSerialSensor
from services.control.force.gravity import ToolLoad
from services.control.force.model import Vec, WristModel
from services.control.force.sensors import ForceSensor, Reading, SensorError
from services.control.force.sim_sensor import SimSensor
from tests.conftest import wait_until
from tests.control.force.helpers import Events

COUNTS = np.diag([1e-7, 1e-7, 1e-7, 1e-6, 1e-6, 1e-6])  # 0.1 µm, 1 µrad per ADC count


@dataclass
class Rig:
    sensor: ForceSensor
    model: WristModel
    apply: Callable[[Vec, Vec], None]
    tol: float


def sim_rig() -> Generator[Rig, None, None]:
    model = WristModel()
    sensor = SimSensor(model, ToolLoad())
    sensor.update_pose((0.0, 0.0, 3.0), np.eye(3))  # in free space: only the push acts
    yield Rig(sensor, model, sensor.push, 1e-9)


def serial_rig() -> Generator[Rig, None, None]:
    model = WristModel(calibration=COUNTS)
    with FakeSerialSensor(rate_hz=1000.0) as fake:

        def apply(f: Vec, c: Vec) -> None:
            fake.set_signals([round(v) for v in model.signals_from_wrench(f, c)])

        yield Rig(
            open_force_sensor(ForceConfig(sensor="serial", port=fake.url)), model, apply, 5e-3
        )


def netft_rig() -> Generator[Rig, None, None]:
    model = WristModel(p_et=np.array([0.0, 0.0, 0.15]))
    with FakeNetFT(rate_hz=1000.0) as fake:

        def apply(f: Vec, c: Vec) -> None:
            fs, cs = model.sensor_wrench_from_tool(f, c)
            fake.set_wrench(fs.tolist(), cs.tolist())

        yield Rig(
            open_force_sensor(ForceConfig(sensor="netft", host="127.0.0.1", netft_port=fake.port)),
            model,
            apply,
            1e-5,
        )


@pytest.fixture(params=["sim", "serial", "netft"])
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    make = {"sim": sim_rig, "serial": serial_rig, "netft": netft_rig}[request.param]
    gen = make()
    r = next(gen)
    try:
        yield r
    finally:
        r.sensor.close()
        gen.close()


def reads_wrench(rig: Rig, f: Vec, c: Vec) -> None:
    """Read (never blocking) until the sensor reports (f, c) through the model."""
    last: list[Reading] = []

    def matches() -> bool:
        r = rig.sensor.read()
        if r is None:
            return False
        last.append(r)
        assert r.kind in ("signals", "wrench")
        assert len(r.values) == 6 and all(math.isfinite(v) for v in r.values)
        v = np.asarray(r.values)
        got = (
            rig.model.wrench_from_signals(v)
            if r.kind == "signals"
            else rig.model.wrench_from_sensor_wrench(v[:3], v[3:])
        )
        return bool(
            np.allclose(got[0], f, atol=rig.tol * 10) and np.allclose(got[1], c, atol=rig.tol)
        )

    assert wait_until(matches, what=f"wrench {f}, {c}")


def test_contract(rig: Rig) -> None:
    s = rig.sensor
    assert isinstance(s, ForceSensor)
    assert isinstance(s.name, str) and s.name
    assert (s.bad, s.gaps) == (0, 0)
    events = Events()
    s.on_event = events
    with pytest.raises(SensorError):
        s.read()

    s.open()
    s.open()  # idempotent
    f1, c1 = np.array([1.0, -2.0, 5.0]), np.array([0.1, 0.0, -0.05])
    rig.apply(f1, c1)
    reads_wrench(rig, f1, c1)
    f2, c2 = np.array([-20.0, 0.5, 0.0]), np.array([0.0, 0.3, 0.0])
    rig.apply(f2, c2)
    reads_wrench(rig, f2, c2)
    assert (s.bad, s.gaps) == (0, 0)
    assert events.items == []

    s.close()
    s.close()  # idempotent
    with pytest.raises(SensorError):
        s.read()

    s.open()  # and again after a close
    reads_wrench(rig, f2, c2)
    s.close()


def test_unknown_kind() -> None:
    # refused at the config, naming the key, before any backend is looked up
    with pytest.raises(ConfigError, match=r"force\.sensor"):
        open_force_sensor(ForceConfig(sensor="usb"))  # type: ignore[arg-type]
