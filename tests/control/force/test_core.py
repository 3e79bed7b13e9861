"""ForceCore: the IForceSensor calls, the published samples, gravity, bias, tool placement."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from services.bus import codec
from services.bus.errors import ProtocolError, RpcError
from services.bus.messages import ForceSample
from services.control.force.config import ForceConfig
from services.control.force.core import ForceCore, _BiasRequest
from services.control.force.fake_serial_sensor import FakeSerialSensor
from services.control.force.sensors import IdlingSensor, SensorError, WorldAwareSensor
from services.control.force.serial_sensor import SerialSensor
from services.control.force.sim_sensor import SimSensor
from tests.conftest import wait_until
from tests.control.force.helpers import Events, rot

DOWN = np.diag([1.0, -1.0, -1.0])  # tool z pointing at the floor
TABLE_TOP_Z = 0.40
FREE = (0.6, 0.0, 1.5)
COUNTS = (1e-7, 1e-7, 1e-7, 1e-6, 1e-6, 1e-6)


class Published:
    def __init__(self) -> None:
        self.items: list[ForceSample] = []

    def __call__(self, s: ForceSample) -> None:
        self.items.append(s)


def make_core(**cfg: Any) -> tuple[ForceCore, Published, Events]:
    cfg.setdefault("noise_n", 0.0)
    cfg.setdefault("noise_nm", 0.0)
    pub, ev = Published(), Events()
    return ForceCore.from_config(ForceConfig(**cfg), pub, ev), pub, ev


@pytest.fixture
def sim() -> Iterator[tuple[ForceCore, Published, Events]]:
    core, pub, ev = make_core()
    yield core, pub, ev
    core.close()


@pytest.fixture(scope="module")
def shared() -> Iterator[ForceCore]:
    core, _, _ = make_core()
    core.update_robot_state(FREE, DOWN)
    core.rpc_sensor_start({})
    yield core
    core.close()


def test_samples_at_1khz_have_no_seq_gaps(sim: tuple[ForceCore, Published, Events]) -> None:
    core, pub, _ = sim
    core.update_robot_state(FREE, DOWN)
    core.rpc_sensor_start({})
    assert wait_until(lambda: len(pub.items) >= 2000, timeout_s=30.0)
    core.rpc_sensor_stop({})
    assert [s.seq for s in pub.items[:2000]] == list(range(1, 2001))
    t = [s.t_ns for s in pub.items[:2000]]
    assert t == sorted(t)
    st_ = core.rpc_sensor_status({})
    assert st_["drops"] == 0
    s = pub.items[-1]
    assert len(s.f) == 3 and len(s.c) == 3 and len(s.raw) == 6
    d = codec.to_fields(s)
    assert set(d) == {"seq", "t_ns", "f", "c", "raw"}


def test_status_start_stop(sim: tuple[ForceCore, Published, Events]) -> None:
    core, _pub, ev = sim
    st_ = core.rpc_sensor_status({})
    for key in ("running", "period_ms", "priority", "rate_hz", "samples"):
        assert key in st_
    assert (st_["running"], st_["period_ms"], st_["priority"], st_["samples"]) == (
        False,
        1.0,
        "normal",
        0,
    )
    assert st_["priority_applied"]["requested"] == "normal"
    with pytest.raises(RpcError) as e:
        core.rpc_sensor_read({})
    assert e.value.code == "not_ready"
    core.update_robot_state(FREE, DOWN)
    assert core.rpc_sensor_start({})["running"] is True
    assert core.rpc_sensor_start({})["running"] is True  # idempotent
    assert wait_until(lambda: core.rpc_sensor_status({})["samples"] >= 50)
    assert core.rpc_sensor_read({})["seq"] >= 50
    st_ = core.rpc_sensor_stop({})
    assert st_["running"] is False and st_["rate_hz"] == 0.0
    n = st_["samples"]
    assert core.rpc_sensor_status({})["samples"] == n  # stopped means stopped
    assert wait_until(lambda: ev.kinds().count("status") == 2)
    assert [d["running"] for k, _, d in ev.items if k == "status"] == [True, False]


def press(core: ForceCore, f_z: float) -> None:
    """A steady external force along the tool's z on the simulated wrist (N, tool frame):
    with the tool pointing down, −z is the table pushing up."""
    sensor = core.sensor
    assert isinstance(sensor, SimSensor)
    sensor.push((0.0, 0.0, f_z))


def test_sim_external_wrench_in_the_tool_frame(
    sim: tuple[ForceCore, Published, Events],
) -> None:
    core, _, _ = sim
    # Tool pointing down, pressed on: the push is read in the tool frame, weight removed.
    core.update_robot_state((0.6, 0.3, TABLE_TOP_Z), DOWN)
    press(core, -200.0)
    core.rpc_sensor_start({})
    assert wait_until(lambda: core.latest is not None and core.latest.seq > 5)
    s = core.rpc_sensor_read({})
    assert_allclose(s["f"], [0.0, 0.0, -20_000.0 * 0.010], atol=1e-6)
    assert_allclose(s["c"], [0.0, 0.0, 0.0], atol=1e-9)
    # Released, turned: weight compensated, zero.
    press(core, 0.0)
    core.update_robot_state(FREE, rot("x", 0.7) @ DOWN)
    assert wait_until(lambda: np.allclose(core.rpc_sensor_read({})["f"], 0.0, atol=1e-9))
    assert core.rpc_sensor_status({})["gravity_compensated"] is True


def test_unused_the_sim_sensor_idles_but_a_bias_is_taken_at_full_rate(
    sim: tuple[ForceCore, Published, Events],
) -> None:
    """Unused, the simulated sensor is sampled every IDLE_PERIOD_MS; a bias meanwhile
    switches to the period for its samples, then back; used again, the period."""
    core, _, _ = sim
    core.update_robot_state((0.6, 0.3, TABLE_TOP_Z), DOWN)
    core.rpc_sensor_start({})
    core.set_unused(True)
    assert core.idle
    seen: list[bool] = []
    real_add = _BiasRequest.add

    def add(self: _BiasRequest, f: Any, c: Any) -> bool:
        seen.append(core.idle)
        return real_add(self, f, c)

    with mock.patch.object(_BiasRequest, "add", add):
        out = core.rpc_sensor_bias({})
    assert out["samples"] == 16 and seen and not any(seen)  # every bias sample at full rate
    assert core.idle  # and back to idling
    core.set_unused(False)
    assert not core.idle


def test_only_the_sim_sensor_may_idle_and_takes_the_physics() -> None:
    """The optional capabilities the core decides once: a streaming sensor has neither."""
    sim, serial = SimSensor(), SerialSensor("socket://127.0.0.1:1")
    assert isinstance(sim, IdlingSensor) and sim.may_idle and isinstance(sim, WorldAwareSensor)
    assert not isinstance(serial, IdlingSensor) and not isinstance(serial, WorldAwareSensor)
    core = ForceCore(serial, ForceConfig(sensor="serial"), lambda s: None, lambda *a: None)
    try:
        core.set_unused(True)
        assert not core.idle and core.physics_updates == 0
    finally:
        core.close()


def test_bias_makes_the_current_reading_zero(sim: tuple[ForceCore, Published, Events]) -> None:
    core, _, _ = sim
    with pytest.raises(RpcError) as e:
        core.rpc_sensor_bias({})
    assert e.value.code == "not_ready"
    core.update_robot_state((0.6, 0.3, TABLE_TOP_Z), DOWN)
    press(core, -100.0)
    core.rpc_sensor_start({})
    out = core.rpc_sensor_bias({})
    assert out["samples"] == 16
    assert_allclose(out["f_bias"], [0, 0, -100.0], atol=1e-6)
    seq = core.rpc_sensor_read({})["seq"]
    assert wait_until(lambda: core.rpc_sensor_read({})["seq"] > seq)
    assert_allclose(core.rpc_sensor_read({})["f"], 0.0, atol=1e-6)
    core.rpc_sensor_bias({"clear": True})
    assert wait_until(lambda: core.rpc_sensor_read({})["f"][2] < -99.0)
    with pytest.raises(RpcError) as e:
        core.rpc_sensor_bias({"clear": "yes"})
    assert e.value.code == "bad_request" and "clear" in e.value.message


def test_config_changes_take_effect_and_are_reported(
    sim: tuple[ForceCore, Published, Events],
) -> None:
    core, _, _ = sim
    core.update_robot_state(FREE, DOWN)
    core.rpc_sensor_start({})
    st_ = core.rpc_sensor_config({"period_ms": 2.5, "priority": "lowest"})
    assert st_["period_ms"] == 2.5 and core.sampler.period_ms == 2.5
    assert st_["priority"] == "lowest"
    assert st_["priority_applied"]["applied"] == "lowest"
    assert st_["priority_applied"]["nice"] == 10
    st_ = core.rpc_sensor_config({"priority": "normal"})
    assert st_["priority_applied"]["requested"] == "normal"
    assert st_["period_ms"] == 2.5  # untouched
    for bad, field in (({"period_ms": 0}, "period_ms"), ({"priority": "max"}, "priority")):
        with pytest.raises(RpcError) as e:
            core.rpc_sensor_config(bad)
        assert e.value.code == "bad_request" and e.value.message.startswith(field)
    # Both are checked before either applies.
    with pytest.raises(RpcError):
        core.rpc_sensor_config({"period_ms": 5.0, "priority": "max"})
    assert core.sampler.period_ms == 2.5


junk = (
    st.none()
    | st.booleans()
    | st.integers(-(10**6), 10**6)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=5)
    | st.lists(st.floats(allow_nan=True), max_size=4)
)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(value=junk)
def test_any_period_is_applied_or_refused_by_name(shared: ForceCore, value: Any) -> None:
    """Safety: a bad period never reaches the sampler; a good one is what is reported."""
    before = shared.sampler.period_ms
    ok = isinstance(value, int | float) and not isinstance(value, bool) and 0.2 <= value <= 1000.0
    try:
        st_ = shared.rpc_sensor_config({"period_ms": value})
    except RpcError as e:
        assert not ok
        assert e.code == "bad_request" and e.message.startswith("period_ms")
        assert shared.sampler.period_ms == before
    else:
        assert ok and st_["period_ms"] == pytest.approx(float(value), abs=1e-6)
    shared.rpc_sensor_config({"period_ms": 1.0})


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(key=st.sampled_from(["K_l", "K_r"]), value=junk)
def test_any_stiffness_is_applied_or_refused_by_name(
    shared: ForceCore, key: str, value: Any
) -> None:
    """Safety: stiffness is positive and finite, else refused and unchanged."""
    before = shared.rpc_sensor_compliance({})
    try:
        out = shared.rpc_sensor_compliance({key: value})
    except RpcError as e:
        assert e.code == "bad_request" and e.message.startswith(key)
        assert shared.rpc_sensor_compliance({}) == before
    else:
        v = np.broadcast_to(np.asarray(value, dtype=float), (3,))
        assert np.all(v > 0) and np.all(np.isfinite(v))
        assert_allclose(out[key], v)
    shared.rpc_sensor_compliance({"K_l": 10_000.0, "K_r": 50.0})


def test_compliance_scales_the_measured_force() -> None:
    core, _, _ = make_core(tool_mass_kg=0.0)
    try:
        core.update_robot_state((0.6, 0.3, TABLE_TOP_Z), DOWN)
        press(core, -100.0)  # −100 N on the simulated wrist
        core.rpc_sensor_start({})
        assert wait_until(lambda: core.latest is not None)
        out = core.rpc_sensor_compliance({"K_l": [10_000.0, 10_000.0, 20_000.0]})
        assert out["K_l"] == [10_000.0, 10_000.0, 20_000.0] and out["K_r"] == [50.0] * 3
        # The simulated wrist is unchanged: a model twice as stiff reads twice the force.
        assert wait_until(lambda: abs(core.rpc_sensor_read({})["f"][2] + 200.0) < 1e-6)
    finally:
        core.close()


def test_tool_placement_follows_robot_state(sim: tuple[ForceCore, Published, Events]) -> None:
    core, _, ev = sim
    flange_R = DOWN
    flange_p = np.array([0.6, 0.0, 0.8])
    # arm's set_tool gave a 0.3 m tool: robot/state's tool pose is flange · eMt.
    tool_p = flange_p + flange_R @ np.array([0.0, 0.0, 0.3])
    core.update_robot_state(tool_p, flange_R, flange_p, flange_R)
    assert_allclose(core._model.p_et, [0, 0, 0.3], atol=1e-12)
    sensor = core.sensor
    assert isinstance(sensor, SimSensor)
    assert_allclose(sensor.model.p_et, [0, 0, 0.3], atol=1e-12)
    assert wait_until(lambda: "status" in ev.kinds())
    n = len(ev.items)
    core.update_robot_state(tool_p, flange_R, flange_p, flange_R)  # unchanged: no event
    core.set_tool([0, 0, 0.3], np.eye(3))
    assert wait_until(lambda: len(ev.items) == n + 1)
    with pytest.raises(ProtocolError):
        core.set_tool([0, 0, 0.2], 2 * np.eye(3))
    with pytest.raises(ProtocolError):
        core.update_robot_state(FREE, np.zeros(9))


def test_start_on_an_unreachable_sensor_is_unreachable() -> None:
    with FakeSerialSensor() as f:
        url = f.url
    core, _, _ = make_core(sensor="serial", port=url)
    try:
        with pytest.raises(RpcError) as e:
            core.rpc_sensor_start({})
        assert e.value.code == "unreachable"
        assert core.rpc_sensor_status({})["running"] is False
    finally:
        core.close()


def test_serial_sensor_stall_and_bad_data_reach_the_events() -> None:
    with FakeSerialSensor(rate_hz=1000.0) as fake:
        config = ForceConfig(
            sensor="serial",
            port=fake.url,
            period_ms=2.0,
            calibration=tuple(float(np.diag(COUNTS)[i, j]) for i in range(6) for j in range(6)),
        )
        pub, ev = Published(), Events()
        core = ForceCore(SerialSensor(fake.url), config, pub, ev)
        try:
            core.rpc_sensor_start({})
            assert wait_until(lambda: len(pub.items) >= 20)
            fake.stall(0.3)
            assert wait_until(lambda: "recovered" in ev.kinds(), what="stale then recovered")
            kinds = [k for k in ev.kinds() if k in ("stale", "recovered")]
            assert kinds[0] == "stale"
            assert all(a != b for a, b in itertools.pairwise(kinds))  # once per stall
            fake.inject_garbage(3)
            assert wait_until(lambda: core.rpc_sensor_status({})["bad"] == 3)
            assert wait_until(lambda: "bad_data" in ev.kinds())
            seqs = [s.seq for s in pub.items]
            assert seqs == list(range(1, len(seqs) + 1))
        finally:
            core.close()


def test_the_simulation_never_loads_pyserial() -> None:
    code = (
        "import sys\n"
        "from services.control.force.config import ForceConfig\n"
        "from services.control.force.core import ForceCore\n"
        "c = ForceCore.from_config(ForceConfig(), lambda s: None, lambda k, m, d: None)\n"
        "c.close()\n"
        "assert 'serial' not in sys.modules, 'pyserial loaded'\n"
    )
    repo = Path(__file__).resolve().parents[3]
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr


def test_close_is_idempotent_and_closes_the_sensor() -> None:
    core, _, _ = make_core()
    core.rpc_sensor_start({})
    core.close()
    core.close()
    assert math.isfinite(core.rpc_sensor_status({})["period_ms"])
    with pytest.raises(RpcError) as e:
        core.rpc_sensor_start({})
    assert e.value.code == "not_ready"
    with pytest.raises(SensorError):
        core.sensor.read()
