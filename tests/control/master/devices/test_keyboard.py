"""Keyboard jog: the pure key mapping, hold timing, and the tty backend on a pty."""

from __future__ import annotations

import os
import select
from dataclasses import replace

import numpy as np
import pytest

from services.bus import keys
from services.control.master.config import MasterConfig
from services.control.master.devices.keyboard import (
    KEY_AXES,
    KeyboardMaster,
    KeyJogState,
    key_action,
    parse_keys,
)
from services.control.master.service import MasterService
from services.control.master.status_line import WIDTH, StatusInfo, render
from tests.conftest import Net, wait_until


def test_parse_keys_splits_characters_and_arrows() -> None:
    data = b"wD\x1b[A\x1b[D g\x1b[5~x\x1bOB"
    assert parse_keys(data) == ["w", "d", "up", "left", " ", "g", "x", "down"]


@pytest.mark.parametrize(
    ("key", "axis", "direction"),
    [
        ("d", 0, 1.0),
        ("a", 0, -1.0),
        ("right", 0, 1.0),
        ("left", 0, -1.0),
        ("w", 1, 1.0),
        ("s", 1, -1.0),
        ("up", 1, 1.0),
        ("down", 1, -1.0),
        ("r", 2, 1.0),
        ("f", 2, -1.0),
        ("i", 3, 1.0),
        ("k", 3, -1.0),
        ("l", 4, 1.0),
        ("j", 4, -1.0),
        ("u", 5, 1.0),
        ("o", 5, -1.0),
    ],
)
def test_key_to_axis_mapping(key: str, axis: int, direction: float) -> None:
    action = key_action(key)
    assert (action.kind, action.axis, action.direction) == ("jog", axis, direction)


def test_every_axis_has_both_directions() -> None:
    covered = {(axis, d) for axis, d in KEY_AXES.values()}
    assert covered == {(axis, d) for axis in range(6) for d in (1.0, -1.0)}
    assert key_action(" ").kind == "clutch"
    assert key_action("g").kind == "grip"
    assert key_action("x").kind == "stop"
    assert key_action("z").kind == "none"


def test_hold_timing_clutch_grip_and_stop() -> None:
    s = KeyJogState(hold_s=0.5)
    assert s.clutch is True  # starts with the master-shift on
    s.press("w", 0.0)
    np.testing.assert_array_equal(s.deflection(0.3), [0, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(s.deflection(0.6), np.zeros(6))
    s.press("w", 0.0)
    s.press("s", 0.2)  # the opposite key takes over the axis
    s.press("u", 0.2)
    np.testing.assert_array_equal(s.deflection(0.4), [0, -1, 0, 0, 0, 1])
    s.press("x", 0.4)
    np.testing.assert_array_equal(s.deflection(0.41), np.zeros(6))
    s.press("d", 0.5)
    s.press(" ", 0.5)
    assert s.clutch is False
    np.testing.assert_array_equal(s.deflection(0.51), np.zeros(6))  # clutch also stops
    s.press("g", 0.6)
    assert s.grip == 1.0


def test_keyboard_on_a_pty() -> None:
    operator, terminal = os.openpty()
    kb = KeyboardMaster(fd=terminal, speed_m_s=0.05, rate_rad_s=0.3, hold_s=0.5)
    try:
        kb.open()
        first = kb.read(0.01)
        assert first.clutch is True and kb.name == "keyboard"
        os.write(operator, b" ")
        assert wait_until(lambda: not kb.read(0.0).clutch)
        os.write(operator, b"w")
        assert wait_until(lambda: kb.read(0.001).hand_p[1] > 0.0)
        before = kb.read(0.0).hand_p
        after = kb.read(0.02).hand_p
        np.testing.assert_allclose(after - before, [0, 0.05 * 0.02, 0], atol=1e-15)
        os.write(operator, b"g")
        assert wait_until(lambda: kb.read(0.0).grip == 1.0)
    finally:
        kb.close()
        os.close(operator)
        os.close(terminal)


def test_the_keyboard_station_shows_its_status_line_on_its_terminal(net: Net) -> None:
    keys_in, terminal = os.openpty()
    screen, status_tty = os.openpty()
    kb = KeyboardMaster(fd=terminal, status_fd=status_tty, hold_s=0.5)
    kb.open()  # a device handed to the service comes open, as open_master_device() gives it
    seen: list[str] = []

    def screen_has(text: str) -> bool:
        while select.select([screen], [], [], 0.0)[0]:
            seen.append(os.read(screen, 65536).decode(errors="replace"))
        return text in "".join(seen)

    station = MasterService(
        net.node("master", instance="kb"),
        MasterConfig(device="keyboard", master_id="kb"),
        device=kb,
    )
    decision = net.node("decision")
    try:
        assert wait_until(lambda: screen_has("SHIFT: slave holds"), 10.0)
        assert screen_has("wasd rf move")  # the keys, until there is news
        os.write(keys_in, b" ")
        assert wait_until(lambda: screen_has("ENGAGED"), 10.0)
        events = decision.publisher(keys.EVENTS)
        assert wait_until(lambda: bool(events._pub.matching_status.matching), 10.0)
        decision.event(
            "watchdog", "no command from master 'kb' for 100 ms: holding", {"master": "kb"}
        )
        assert wait_until(lambda: screen_has("held: engage again (space twice)"), 10.0)
        assert "\n" not in "".join(seen)  # one line, rewritten in place
    finally:
        station.close()
        kb.close()
        for fd in (keys_in, terminal, screen, status_tty):
            os.close(fd)


def test_the_status_line_says_what_to_do() -> None:
    info = StatusInfo("keyboard", False, 0.5, 1.0, "world", 0.0)
    line = render(info)
    assert line.startswith("SHIFT: slave holds") and "scale 0.50/1.00 · world" in line
    assert "grip open" in line and "space engage" in line and "x stop" in line
    held = render(replace(info, engaged=True, notice=("estop", "emergency stop: " + "x" * 500)))
    assert "ENGAGED" in held and "E-STOP latched: reset it first" in held
    assert len(held) <= WIDTH
