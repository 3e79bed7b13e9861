"""SpaceMouse decoding from recorded report bytes (both layouts) and the HID backend."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.control.master.device import DeviceLost, DeviceNotFound
from services.control.master.devices.spacemouse import (
    SINGLE_REPORT,
    TWO_REPORTS,
    HidSpaceMouse,
    SpaceMouseState,
    decode_report,
    find_model,
)
from services.control.master.jog import MAX_STEP_S, apply_deadband
from services.geometry import rot_z
from tests.control.master.devices.fake_hid import FakeHidApi, FakeHidInfo


def hx(text: str) -> bytes:
    return bytes.fromhex(text)


# Recorded from a SpaceNavigator (046d:c626): cap pushed fully right; pulled toward the user
# (HID +y) and pressed down (HID +z); tilted (HID Ry = −30); left button; right; released.
NAV_RIGHT = hx("01 5e 01 00 00 00 00")
NAV_PULL_PRESS = hx("01 00 00 c8 00 64 00")
NAV_TILT = hx("02 00 00 e2 ff 00 00")
NAV_TWIST_CCW = hx("02 00 00 00 00 a2 fe")  # HID Rz = −350: counter-clockwise from above
NAV_ZERO_T = hx("01 00 00 00 00 00 00")
NAV_ZERO_R = hx("02 00 00 00 00 00 00")
BTN_LEFT, BTN_RIGHT, BTN_NONE = hx("03 01 00"), hx("03 02 00"), hx("03 00 00")
# A SpaceMouse Wireless (256f:c62e): one 13-byte report, x = 350, ry = −30, rz = +175.
WIRELESS = hx("01 5e 01 00 00 00 00 00 00 e2 ff af 00")
# SpaceMouse Pro: SHIFT is bit 0 of the 4th button byte.
PRO_SHIFT = hx("03 00 00 00 01")


def test_two_report_layout_translation() -> None:
    d = decode_report(NAV_RIGHT, TWO_REPORTS)
    assert d.axes[:3] == (1.0, 0.0, 0.0) and d.axes[3:] == (None, None, None)
    d = decode_report(NAV_PULL_PRESS, TWO_REPORTS)
    # toward the user is −y, pressing down is −z in the master frame (z up, y away)
    assert d.axes[:3] == pytest.approx((0.0, -200 / 350, -100 / 350))
    assert d.buttons is None


def test_two_report_layout_rotation() -> None:
    d = decode_report(NAV_TILT, TWO_REPORTS)
    assert d.axes[:3] == (None, None, None)
    assert d.axes[3:] == pytest.approx((0.0, 30 / 350, 0.0))
    assert decode_report(NAV_TWIST_CCW, TWO_REPORTS).axes[5] == pytest.approx(1.0)


def test_single_report_layout() -> None:
    d = decode_report(WIRELESS, SINGLE_REPORT)
    assert d.axes == pytest.approx((1.0, 0.0, 0.0, 0.0, 30 / 350, -0.5))


def test_buttons_bitmask() -> None:
    assert decode_report(BTN_LEFT, TWO_REPORTS).buttons == 1
    assert decode_report(BTN_RIGHT, SINGLE_REPORT).buttons == 2
    assert decode_report(BTN_NONE, TWO_REPORTS).buttons == 0
    assert decode_report(PRO_SHIFT, SINGLE_REPORT).buttons == 1 << 24
    assert decode_report(BTN_LEFT, TWO_REPORTS).axes == (None,) * 6


def test_short_and_unknown_reports_change_nothing() -> None:
    assert decode_report(b"", TWO_REPORTS).axes == (None,) * 6
    assert decode_report(hx("01 5e"), TWO_REPORTS).axes == (None,) * 6
    assert decode_report(hx("17 64"), SINGLE_REPORT).axes == (None,) * 6  # battery report


def test_state_merges_reports_and_switches_layout() -> None:
    s = SpaceMouseState(TWO_REPORTS)
    s.feed(NAV_RIGHT)
    s.feed(NAV_TILT)
    s.feed(BTN_LEFT)
    np.testing.assert_allclose(s.deflection, [1.0, 0, 0, 0, 30 / 350, 0])
    assert s.buttons == 1
    s.feed(WIRELESS)  # a two-report model sending the 13-byte form after a firmware update
    assert s.layout is SINGLE_REPORT
    np.testing.assert_allclose(s.deflection, [1.0, 0, 0, 0, 30 / 350, -0.5])


def test_model_table() -> None:
    nav = find_model(0x046D, 0xC626)
    assert nav is not None and nav.layout is TWO_REPORTS and nav.name == "SpaceNavigator"
    wireless = find_model(0x256F, 0xC62E)
    assert wireless is not None and wireless.layout is SINGLE_REPORT
    assert find_model(0x046D, 0xC52B) is None  # a Logitech mouse receiver
    unknown = find_model(0x256F, 0xC6FF)
    assert unknown is not None and unknown.layout is SINGLE_REPORT


def test_deadband_rescales_continuously() -> None:
    out = apply_deadband([0.04, -0.05, 0.5, -1.0, 1.2, 0.0], 0.05)
    np.testing.assert_allclose(out, [0.0, 0.0, 0.45 / 0.95, -1.0, 1.0, 0.0])


@given(st.floats(-2.0, 2.0), st.floats(0.0, 0.9))
def test_deadband_is_monotone_bounded_and_zero_inside(v: float, d: float) -> None:
    out = float(apply_deadband([v], d)[0])
    assert -1.0 <= out <= 1.0
    assert out == 0.0 if abs(v) <= d else math.copysign(1.0, out) == math.copysign(1.0, v)
    assert float(apply_deadband([v + 0.01], d)[0]) >= out


# --- the backend over a fake hidapi -----------------------------------------------------------

RECEIVER = FakeHidInfo(b"/dev/hidraw0", 0x046D, 0xC52B, "USB Receiver", "Logitech", 1, 2)
NAVIGATOR = FakeHidInfo(b"/dev/hidraw1", 0x046D, 0xC626, "SpaceNavigator")
WIRELESS_DEV = FakeHidInfo(b"/dev/hidraw2", 0x256F, 0xC62E, "SpaceMouse Wireless")


def open_mouse(api: FakeHidApi, **opts: Any) -> HidSpaceMouse:
    mouse = HidSpaceMouse(hid_api=api, **opts)
    mouse.open()
    return mouse


def test_picks_the_spacemouse_not_the_logitech_mouse() -> None:
    api = FakeHidApi([RECEIVER, NAVIGATOR])
    mouse = open_mouse(api)
    assert api.opened == [NAVIGATOR.path]
    assert mouse.name == "spacemouse:SpaceNavigator"
    assert mouse.can_display_force is False


def test_open_by_path() -> None:
    api = FakeHidApi([NAVIGATOR, WIRELESS_DEV])
    mouse = open_mouse(api, path="/dev/hidraw2")
    assert api.opened == [WIRELESS_DEV.path]
    assert mouse.model is not None and mouse.model.product_id == 0xC62E


def test_missing_device_lists_what_was_found() -> None:
    with pytest.raises(DeviceNotFound) as info:
        open_mouse(FakeHidApi([RECEIVER]))
    assert info.value.found == ["046d:c52b Logitech USB Receiver"]
    assert "046d:c52b Logitech USB Receiver" in str(info.value)


def test_rates_integrate_into_a_hand_pose() -> None:
    api = FakeHidApi([NAVIGATOR])
    mouse = open_mouse(api, full_speed_m_s=0.1, full_rate_rad_s=0.5, deadband=0.05)
    api.push(NAVIGATOR.path, NAV_RIGHT)
    r = mouse.read(0.01)
    np.testing.assert_allclose(r.hand_p, [0.001, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.hand_R, np.eye(3))
    assert api.pending(NAVIGATOR.path) == 0
    api.push(NAVIGATOR.path, NAV_ZERO_T, NAV_TWIST_CCW)
    r = mouse.read(0.02)
    np.testing.assert_allclose(r.hand_p, [0.001, 0, 0], atol=1e-15)
    np.testing.assert_allclose(r.hand_R, rot_z(0.01), atol=1e-12)
    r = mouse.read(1.0)  # a stall is integrated as at most MAX_STEP_S
    np.testing.assert_allclose(r.hand_R, rot_z(0.01 + 0.5 * MAX_STEP_S), atol=1e-12)
    api.push(NAVIGATOR.path, NAV_ZERO_R)
    assert mouse.read(0.01).hand_R == pytest.approx(r.hand_R)


def test_sensitivity_and_deadband() -> None:
    api = FakeHidApi([WIRELESS_DEV])
    mouse = open_mouse(api, sensitivity=2.0, deadband=0.1)
    api.push(WIRELESS_DEV.path, hx("01 0a 00 00 00 00 00 00 00 00 00 00 00"))  # 10/350: noise
    np.testing.assert_array_equal(mouse.read(0.01).hand_p, [0, 0, 0])
    api.push(WIRELESS_DEV.path, WIRELESS)
    r = mouse.read(0.01)
    np.testing.assert_allclose(r.hand_p, [2 * 0.1 * 0.01, 0, 0], atol=1e-15)


def test_clutch_button_freezes_the_hand_and_grip_button_toggles() -> None:
    api = FakeHidApi([NAVIGATOR])
    mouse = open_mouse(api, clutch_button=0, grip_button=1)
    api.push(NAVIGATOR.path, NAV_RIGHT, BTN_LEFT)
    r = mouse.read(0.01)
    assert r.clutch is True and r.buttons == 1 and r.grip == 0.0
    np.testing.assert_array_equal(r.hand_p, [0, 0, 0])
    api.push(NAVIGATOR.path, BTN_NONE)
    r = mouse.read(0.01)
    assert r.clutch is False
    np.testing.assert_allclose(r.hand_p, [0.001, 0, 0])
    grips = []
    for report in (BTN_RIGHT, BTN_RIGHT, BTN_NONE, BTN_RIGHT, BTN_NONE):
        api.push(NAVIGATOR.path, report)
        grips.append(mouse.read(0.0).grip)
    assert grips == [1.0, 1.0, 1.0, 0.0, 0.0]


def test_unplugged_device_is_lost() -> None:
    api = FakeHidApi([NAVIGATOR])
    mouse = open_mouse(api)
    api.unplug(NAVIGATOR.path)
    with pytest.raises(DeviceLost):
        mouse.read(0.01)
    mouse.close()
    mouse.close()
    assert api.closed == 1
