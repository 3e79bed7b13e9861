"""`[master] contact_tangential_gain`: the contact's friction shown to the hand scaled, its
press in full, across a normal estimated over the contact's first moments."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.master.config import MasterConfig
from services.control.master.device import HandReading
from services.control.master.feedback import (
    CONTACT_LOST_S,
    NORMAL_WINDOW_S,
    ContactNormal,
    ForceDisplay,
    across_normal,
)
from services.geometry import rot_x

DT = 0.001
STILL = HandReading(np.zeros(3), np.eye(3), False)
TOOL = np.eye(3).reshape(9)


def _press(f: tuple[float, float, float]) -> tuple[tuple[float, ...], tuple[float, ...], object]:
    return (f, (0.0, 0.0, 0.0), TOOL)


def test_the_normal_is_the_mean_direction_over_the_contacts_first_moments() -> None:
    """A touch whose first sample is tilted 45° (its impact) and whose next are straight:
    the normal is their mean, near the straight one, and only once the window is full."""
    cn = ContactNormal()
    assert cn.update([0.3, 0.0, 0.0], 0.0) is None  # under 1 N: no contact
    assert cn.update([2.0, 0.0, 2.0], 0.010) is None  # the touch: the window starts
    t = 0.010
    while t < 0.010 + NORMAL_WINDOW_S - DT / 2:
        t += DT
        n = cn.update([0.0, 0.0, 3.0], t)
        assert n is None or t >= 0.010 + NORMAL_WINDOW_S - 1e-9
    n = cn.update([0.0, 0.0, 3.0], t + DT)
    assert n is not None
    assert abs(float(np.linalg.norm(n)) - 1.0) < 1e-12
    assert n[2] > 0.999 and 0.0 < n[0] < 0.01  # one tilted sample of ~100 barely tilts it
    # Kept through friction building up: a later sideways force does not move it.
    assert np.array_equal(cn.update([5.0, 0.0, 3.0], t + 2 * DT), n)


def test_a_bounce_is_one_contact_and_a_lift_off_ends_it() -> None:
    """Under 0.5 N for less than CONTACT_LOST_S (the touch's chatter) keeps the normal; for
    longer, the contact is over and the next takes its normal anew."""
    cn = ContactNormal()
    t = 0.0
    for _ in range(int(NORMAL_WINDOW_S / DT) + 2):
        t += DT
        cn.update([0.0, 0.0, 3.0], t)
    n = cn.n
    assert n is not None
    t += DT
    assert np.array_equal(cn.update([0.0, 0.0, 0.1], t), n)  # a bounce
    t += CONTACT_LOST_S / 2
    assert np.array_equal(cn.update([0.0, 0.0, 0.1], t), n)
    t += DT
    assert np.array_equal(cn.update([0.0, 0.0, 3.0], t), n)  # back on: the same contact
    t += DT
    cn.update([0.0, 0.0, 0.0], t)
    assert cn.update([0.0, 0.0, 0.0], t + CONTACT_LOST_S) is None  # lifted off
    assert cn.update([0.0, 3.0, 0.0], t + CONTACT_LOST_S + DT) is None  # a new window
    cn.reset()
    assert cn.n is None


def test_forces_that_cancel_name_no_normal() -> None:
    cn = ContactNormal()
    t = 0.0
    for k in range(int(NORMAL_WINDOW_S / DT) + 2):
        t += DT
        cn.update([0.0, 0.0, 2.0 if k % 2 else -2.0], t)
    assert cn.n is None


@settings(max_examples=300, deadline=None)
@given(
    f=st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3),
    n=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(
        lambda v: float(np.linalg.norm(v)) > 0.1
    ),
    gain=st.floats(0.0, 1.0),
)
def test_across_normal_keeps_the_press_and_never_adds(
    f: list[float], n: list[float], gain: float
) -> None:
    """The part along the normal unchanged, the part across it × gain, never longer."""
    u = np.asarray(n) / np.linalg.norm(n)
    out = across_normal(f, u, gain)
    assert float(out @ u) == pytest.approx(float(np.dot(f, u)), abs=1e-9)
    across_in = np.asarray(f) - float(np.dot(f, u)) * u
    across_out = out - float(out @ u) * u
    np.testing.assert_allclose(across_out, gain * across_in, atol=1e-9)
    assert float(np.linalg.norm(out)) <= float(np.linalg.norm(f)) + 1e-9


def _show(display: ForceDisplay, forces: list[tuple[float, float, float]]) -> list[np.ndarray]:
    return [
        display.update(_press(f), "world", True, STILL, DT, DT * k).f
        for k, f in enumerate(forces, start=1)
    ]


def test_the_display_shows_the_press_in_full_and_the_friction_scaled() -> None:
    """A press straight down, then friction building up sideways: with gain 0 the hand is
    shown the press alone once the normal is known (the full force before it is); with the
    default 1, the force as measured, every tick."""
    window = int(NORMAL_WINDOW_S / DT) + 2
    forces = [(0.0, 0.0, 4.0)] * window + [(2.0, -1.0, 4.0)] * 20

    def display(gain: float) -> ForceDisplay:
        return ForceDisplay(MasterConfig(force_ramp_s=0.0, contact_tangential_gain=gain))

    hidden = _show(display(0.0), forces)
    np.testing.assert_allclose(hidden[-1], [0.0, 0.0, 4.0], atol=1e-9)
    first = display(0.0).update(_press((2.0, -1.0, 4.0)), "world", True, STILL, DT, DT).f
    np.testing.assert_array_equal(first, [2.0, -1.0, 4.0])  # before the normal: whole
    half = _show(display(0.5), forces)
    np.testing.assert_allclose(half[-1], [1.0, -0.5, 4.0], atol=1e-9)
    shown = _show(ForceDisplay(MasterConfig(force_ramp_s=0.0)), forces)
    for got, want in zip(shown, forces, strict=True):
        np.testing.assert_array_equal(got, want)


def test_disengaging_forgets_the_normal() -> None:
    """A new engagement is a new contact: the normal is taken anew (the full force is shown
    while it is), never one from before the master-shift."""
    display = ForceDisplay(MasterConfig(force_ramp_s=0.0, contact_tangential_gain=0.0))
    window = int(NORMAL_WINDOW_S / DT) + 2
    _show(display, [(0.0, 0.0, 4.0)] * window)
    display.update(_press((0.0, 0.0, 4.0)), "world", False, STILL, DT, 1.0)
    got = display.update(_press((4.0, 0.0, 0.0)), "world", True, STILL, DT, 1.001).f
    np.testing.assert_allclose(got, [4.0, 0.0, 0.0], atol=1e-9)


def test_the_normal_stays_put_in_the_world_while_the_tool_turns() -> None:
    """The normal is the world's: pressing straight down with the tool turned 90° about x,
    then turned back in contact with friction built up, the hand is shown the press alone —
    in the `tool` frame too, where the display turns with the tool."""
    window = int(NORMAL_WINDOW_S / DT) + 2
    for frame in ("world", "tool"):
        display = ForceDisplay(MasterConfig(force_ramp_s=0.0, contact_tangential_gain=0.0))
        t = 0.0
        for _ in range(window):
            t += DT
            r1 = rot_x(np.pi / 2)
            display.update(
                (r1.T @ [0.0, 0.0, 4.0], (0.0,) * 3, r1.reshape(9)), frame, True, STILL, DT, t
            )
        r2 = rot_x(0.3)
        world = np.array([2.0, -1.0, 4.0])
        got = display.update(
            (r2.T @ world, (0.0,) * 3, r2.reshape(9)), frame, True, STILL, DT, t + DT
        ).f
        want = [0.0, 0.0, 4.0] if frame == "world" else r2.T @ [0.0, 0.0, 4.0]
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_bad_input_is_left_for_the_display_to_refuse() -> None:
    """A non-finite force or a tool orientation that is no rotation shows zero and counts a
    fault, as without the option, and leaves the contact's normal untouched."""
    display = ForceDisplay(MasterConfig(force_ramp_s=0.0, contact_tangential_gain=0.0))
    for bad in (
        ((math.nan, 0.0, 4.0), (0.0,) * 3, TOOL),
        ((0.0, 0.0, 4.0), (0.0,) * 3, (2.0,) * 9),
    ):
        assert not display.update(bad, "world", True, STILL, DT, DT).f.any()
    assert display.faults == 2
    assert display._normal.n is None and display._normal._since_s is None


def test_an_absurd_force_does_not_poison_the_contact() -> None:
    """A finite but absurd wrist force (1e308 N) in contact is shown saturated like any
    other, and the press after it is still shown with its friction hidden: the normal
    stays a finite unit vector."""
    cfg = MasterConfig(force_ramp_s=0.0, contact_tangential_gain=0.0)
    display = ForceDisplay(cfg)
    window = int(NORMAL_WINDOW_S / DT) + 2
    t = 0.0
    for f in [(1e308, 1e308, 1e308)] + [(0.0, 0.0, 4.0)] * window:
        t += DT
        out = display.update(_press(f), "world", True, STILL, DT, t).f
        assert np.all(np.isfinite(out)) and float(np.linalg.norm(out)) <= cfg.max_force_n + 1e-9
    got = display.update(_press((2.0, -1.0, 4.0)), "world", True, STILL, DT, t + DT).f
    assert np.all(np.isfinite(got)) and got[2] > 0.0
    assert float(np.hypot(got[0], got[1])) < 0.2 * float(np.hypot(2.0, -1.0))


def test_the_gain_is_a_checked_setting() -> None:
    assert MasterConfig().contact_tangential_gain == 1.0
    assert MasterConfig.from_mapping({"contact_tangential_gain": 0}).contact_tangential_gain == 0
