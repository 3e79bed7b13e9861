"""One contract test over every MasterDevice backend, each opened by `open_master_device`."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import pytest

from services.bus.errors import ConfigError
from services.control.master.backends import DEVICES, open_master_device
from services.control.master.config import MasterConfig
from services.control.master.device import (
    DeviceNotFound,
    HandReading,
    KeepsStats,
    MasterDevice,
    MayIdle,
    ReportsRejected,
    ShowsStatus,
    VirtualHand,
)
from services.control.master.devices.haply.fake import FakeInverseService, HandPose
from services.control.master.devices.keyboard import KeyboardMaster
from services.control.master.devices.master_arm.backend import SerialMasterArm
from services.control.master.devices.master_arm.fake import FakeMasterArm
from services.control.master.devices.scripted import ScriptedMaster
from services.control.master.devices.spacemouse import HidSpaceMouse
from services.geometry import is_rotation
from tests.control.master.devices.fake_hid import FakeHidApi, FakeHidInfo

NAVIGATOR = FakeHidInfo(b"/dev/hidraw1", 0x046D, 0xC626, "SpaceNavigator")
KINDS = ["virtual", "scripted", "keyboard", "spacemouse", "serial_arm", "haply", "haptic_sim"]


@pytest.fixture(params=KINDS)
def device(
    request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> Iterator[MasterDevice]:
    kind = request.param
    if kind == "keyboard":
        operator, terminal = os.openpty()
        dev = open_master_device(
            MasterConfig.from_mapping({"device": "keyboard", "port": os.ttyname(terminal)})
        )
        yield dev
        dev.close()
        os.close(operator)
        os.close(terminal)
    elif kind == "spacemouse":
        api = FakeHidApi([NAVIGATOR])
        api.push(NAVIGATOR.path, bytes.fromhex("01 5e 01 00 00 00 00"))
        monkeypatch.setitem(sys.modules, "hid", api)  # the backend imports hidapi as `hid`
        dev = open_master_device(MasterConfig(device="spacemouse"))
        yield dev
        dev.close()
    elif kind == "serial_arm":
        with FakeMasterArm() as arm:
            dev = open_master_device(
                MasterConfig.from_mapping({"device": "serial_arm", "port": arm.url})
            )
            yield dev
            dev.close()
    elif kind == "haply":
        with FakeInverseService(pose=HandPose(a=True)) as service:
            dev = open_master_device(
                MasterConfig.from_mapping({"device": "haply", "haply_url": service.url})
            )
            yield dev
            dev.close()
    else:
        dev = open_master_device(MasterConfig(device=kind))
        yield dev
        dev.close()


def test_every_device_kind_has_a_backend_and_the_contract_covers_it() -> None:
    assert set(DEVICES.names) == set(KINDS) == set(CAPABILITIES)


def test_backend_honours_the_master_device_contract(device: MasterDevice) -> None:
    assert isinstance(device, MasterDevice)
    assert isinstance(device.name, str) and device.name
    assert isinstance(device.can_display_force, bool)
    for dt in (0.0, 0.01, 0.01):
        r = device.read(dt)
        assert isinstance(r, HandReading)
        assert r.hand_p.shape == (3,) and np.all(np.isfinite(r.hand_p))
        assert is_rotation(r.hand_R)
        assert isinstance(r.clutch, bool) and isinstance(r.buttons, int)
        assert r.grip is None or 0.0 <= r.grip <= 1.0
        with pytest.raises(ValueError):
            r.hand_p[0] = 1.0  # readings are immutable
    device.display_force(np.array([0.5, 0.0, -0.5]), np.array([0.0, 0.01, 0.0]))
    device.close()
    device.close()


CAPABILITIES: dict[str, set[type]] = {
    "virtual": {MayIdle, VirtualHand},
    "scripted": {MayIdle, VirtualHand},
    "keyboard": {ShowsStatus},
    "spacemouse": set(),
    "serial_arm": {KeepsStats},
    "haply": {ReportsRejected, KeepsStats},
    "haptic_sim": set(),
}
"""What each backend offers beyond the role (docs/master.md, "Devices"): a Protocol that
stops matching (a renamed method) would switch the station's use of it off silently."""


def test_each_backend_offers_its_capabilities(
    request: pytest.FixtureRequest, device: MasterDevice
) -> None:
    kind = request.node.callspec.params["device"]
    offered = {
        cap
        for cap in (ShowsStatus, MayIdle, ReportsRejected, VirtualHand, KeepsStats)
        if isinstance(device, cap)
    }
    assert offered == CAPABILITIES[kind]
    assert not isinstance(device, MayIdle) or device.may_idle


def test_unknown_kind() -> None:
    with pytest.raises(ConfigError, match="unknown master device") as info:
        MasterConfig(device="joystick")
    assert info.value.key == "master.device"


def test_missing_spacemouse_lists_hid_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    mouse = FakeHidInfo(b"/dev/hidraw0", 0x046D, 0xC52B, "USB Receiver", "Logitech", 1, 2)
    monkeypatch.setitem(sys.modules, "hid", FakeHidApi([mouse]))
    with pytest.raises(DeviceNotFound) as info:
        open_master_device(MasterConfig(device="spacemouse"))
    assert "046d:c52b" in str(info.value)


def test_the_simulated_devices_do_not_load_device_libraries() -> None:
    code = (
        "import sys\n"
        "from services.control.master.backends import open_master_device\n"
        "from services.control.master.config import MasterConfig\n"
        "for kind in ('virtual', 'scripted', 'haptic_sim'):\n"
        "    open_master_device(MasterConfig(device=kind)).close()\n"
        "print(sorted(m for m in ('hid', 'serial', 'websockets') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_hand_reading_validation() -> None:
    with pytest.raises(ValueError):
        HandReading(np.zeros(2), np.eye(3), False)
    with pytest.raises(ValueError):
        HandReading(np.zeros(3), np.diag([1.0, 1.0, -1.0]), False)
    with pytest.raises(ValueError):
        HandReading(np.zeros(3), np.eye(3), False, grip=1.5)
    r = HandReading([0.1, 0.2, 0.3], np.eye(3).reshape(9), 1, 0, 5)  # type: ignore[arg-type]
    assert r.clutch is True and r.grip == 0.0 and r.hand_R.shape == (3, 3)


def constructor_args(
    monkeypatch: pytest.MonkeyPatch, backend: type, table: dict[str, object]
) -> tuple[tuple[object, ...], dict[str, object]]:
    """What the options of the `[master]` table `table` construct `backend` with."""
    calls: list[tuple[tuple[object, ...], dict[str, object]]] = []
    monkeypatch.setattr(
        sys.modules[backend.__module__],
        backend.__name__,
        lambda *args, **kwargs: calls.append((args, kwargs)),
    )
    cfg = MasterConfig.from_mapping(table)
    cfg.options.build(cfg)
    return calls[0]


def test_options_from_config(monkeypatch: pytest.MonkeyPatch) -> None:
    table: dict[str, object] = {"device": "serial_arm", "port": "socket://127.0.0.1:1"}
    args, kwargs = constructor_args(monkeypatch, SerialMasterArm, {**table, "rate_hz": 50})
    assert args == ("socket://127.0.0.1:1",) and kwargs["stream_rate_hz"] == 50
    table = {"device": "spacemouse", "deadband": 0.2, "clutch_button": 3}
    args, kwargs = constructor_args(monkeypatch, HidSpaceMouse, table)
    assert (args, kwargs["deadband"], kwargs["clutch_button"]) == ((None,), 0.2, 3)
    table = {"device": "scripted", "script": "line"}
    assert constructor_args(monkeypatch, ScriptedMaster, table) == (("line",), {})
    args, _ = constructor_args(monkeypatch, KeyboardMaster, {"device": "keyboard"})
    assert args == (None,)


def test_open_master_device_with_scripted_and_serial_configs() -> None:
    dev = open_master_device(MasterConfig.from_mapping({"device": "scripted", "script": "square"}))
    assert dev.name == "scripted:square"
    dev.close()
    with FakeMasterArm() as arm:
        dev = open_master_device(
            MasterConfig.from_mapping({"device": "serial_arm", "port": arm.url, "rate_hz": 100})
        )
        assert dev.read(0.01).hand_R.shape == (3, 3)
        dev.close()
