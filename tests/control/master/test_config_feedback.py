"""MasterConfig validation and force feedback (frames, scaling, saturation)."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import ArrayLike

from services.bus.errors import ConfigError
from services.control.master.backends import DEVICES, options_class
from services.control.master.config import Frame, MasterConfig
from services.control.master.device import HandReading
from services.control.master.devices.haply.backend import HaplyOptions
from services.control.master.devices.keyboard import KeyboardOptions
from services.control.master.devices.scripted import ScriptedOptions
from services.control.master.feedback import (
    CONTACT_DAMPING_FULL_N,
    MAX_DAMPED_DT_S,
    DisplayWrench,
    ForceDisplay,
    ForceFeedback,
    HandVelocity,
    contact_damping,
    operator_wrench,
    ramp_gain,
    saturate,
)
from services.control.master.teleop import scaled_motion
from services.geometry import exp_so3, log_so3, rot_x, rot_z


def test_defaults_are_valid() -> None:
    cfg = MasterConfig()
    assert cfg.rate_hz == 100.0 and cfg.scale_t == 1.0 and cfg.scale_r == 1.0
    assert cfg.frame == "world" and cfg.period_s == pytest.approx(0.01)
    np.testing.assert_array_equal(cfg.alignment_matrix, np.eye(3))


@pytest.mark.parametrize(
    ("device", "engages"),
    [
        ("virtual", True),
        ("scripted", True),
        ("spacemouse", False),
        ("serial_arm", False),
        ("keyboard", False),
        ("haply", False),
    ],
)
def test_engage_on_start_defaults_by_device(device: str, engages: bool) -> None:
    assert MasterConfig(device=device).engage_on_start is engages  # type: ignore[arg-type]
    assert MasterConfig(device=device, engage_on_start=not engages).engage_on_start is (not engages)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("master_id", ""),
        ("master_id", "a/b"),
        ("master_id", "m" * 129),
        ("device", "joystick"),
        ("rate_hz", 0.5),
        ("rate_hz", 1001),
        ("rate_hz", math.inf),
        ("rate_hz", "100"),
        ("scale_t", 0.0),
        ("scale_t", 1.01),
        ("scale_r", -0.5),
        ("frame", "flange"),
        ("alignment", (1.0, 0.0, 0.0) * 3),
        ("alignment", (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0)),
        ("alignment", (1.0,) * 8),
        ("force_scale", -1.0),
        ("max_force_n", 0.0),
        ("max_torque_nm", -2.0),
        ("deadband", 1.0),
        ("deadband", -0.1),
        ("sensitivity", 0.0),
        ("clutch_button", 64),
        ("grip_button", True),
        ("grip_button", 0),
        ("engage_on_start", 1),
        ("arm_dh", ((0.0, 0.0, 0.0),) * 5),
        ("baudrate", 0),
        ("force_ramp_s", -0.1),
        ("force_ramp_s", 11.0),
        ("force_stale_ms", 9.0),
        ("force_stale_ms", 5001.0),
        ("force_stale_ms", math.nan),
        ("force_stale_ms", "100"),
        ("haply_max_force_n", 0.0),
        ("haply_max_force_n", math.nan),
        ("haply_url", "localhost:10001"),
        ("haply_url", "http://localhost:10001"),
        ("haply_url", "ws://localhost"),
        ("haply_url", "ws://localhost:99999"),
        ("haply_url", "ws://:10001"),
        ("haply_url", 10001),
        ("passivity_device_mass_kg", 0.0),
        ("passivity_device_mass_kg", 0.009),
        ("passivity_device_mass_kg", 21.0),
        ("passivity_device_mass_kg", math.inf),
        ("passivity_device_inertia_kg_m2", 0.0),
        ("passivity_device_inertia_kg_m2", 2.0),
        ("passivity_device_inertia_kg_m2", math.nan),
        ("passivity_device_mass_kg", "0.5"),
        ("passivity_moments", "yes"),
        ("contact_damping_ns_m", -1.0),
        ("contact_damping_ns_m", math.nan),
        ("contact_damping_ns_m", "150"),
        ("contact_damping_ns_m", 51.0),  # above 0.5 × 2 × 0.5 kg × 100 Hz
        ("contact_tangential_gain", -0.1),
        ("contact_tangential_gain", 1.5),
        ("contact_tangential_gain", math.nan),
        ("contact_tangential_gain", "0"),
    ],
)
def test_bad_values_name_their_key(key: str, value: object) -> None:
    """Whichever device the key is for: the chosen one, or another (checked, unused)."""
    owner = next((name for name in DEVICES.names if key in _fields(options_class(name))), None)
    for device in {"virtual", owner or "virtual"}:
        with pytest.raises(ConfigError) as info:
            MasterConfig.from_mapping({"device": device, key: value})
        assert info.value.key == f"master.{key}"
    with pytest.raises(ConfigError) as info:
        if owner is None:
            MasterConfig(**{key: value})  # type: ignore[arg-type]
        else:
            options_class(owner)(**{key: value})
    assert info.value.key == f"master.{key}"


def _fields(cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


@pytest.mark.parametrize("key", ["clutch_button", "grip_button"])
def test_haply_buttons_are_a_b_or_c(key: str) -> None:
    with pytest.raises(ConfigError) as info:
        MasterConfig.from_mapping({"device": "haply", key: 3})
    assert info.value.key == f"master.{key}"
    cfg = MasterConfig.from_mapping({"device": "haply", "clutch_button": 2, "grip_button": 0})
    assert isinstance(cfg.options, HaplyOptions)
    assert (cfg.options.clutch_button, cfg.options.haply_url) == (2, "ws://localhost:10001")
    # the same keys for another device are its bits, 0 … 63, as before
    cfg = MasterConfig.from_mapping({"device": "keyboard", key: 3})
    assert isinstance(cfg.options, KeyboardOptions)


def test_the_keys_go_to_the_chosen_device_and_another_devices_are_checked_then_unused() -> None:
    table = {"device": "haply", "haply_url": "ws://host:1", "script": "line", "port": "/dev/x"}
    cfg = MasterConfig.from_mapping(table)
    assert cfg.options == HaplyOptions(haply_url="ws://host:1")
    cfg = MasterConfig.from_mapping(
        {"device": "scripted", "script": "line", "haply_url": "ws://h:1"}
    )
    assert cfg.options == ScriptedOptions(script="line") and cfg.engage_on_start is True
    with pytest.raises(ConfigError) as info:
        MasterConfig.from_mapping({"device": "scripted", "haply_url": "http://h:1"})
    assert info.value.key == "master.haply_url"
    with pytest.raises(ConfigError) as info:
        MasterConfig.from_mapping({"device": "virtual", "options": {}})
    assert info.value.key == "master.options"
    with pytest.raises(ConfigError) as info:
        MasterConfig(device="haply", options=ScriptedOptions())
    assert info.value.key == "master.device"


def test_from_mapping_accepts_toml_lists_and_rejects_unknown_keys() -> None:
    a = list(rot_z(math.pi / 2).reshape(9))
    cfg = MasterConfig.from_mapping({"master_id": "left", "alignment": a, "scale_t": 0.5})
    assert cfg.master_id == "left" and cfg.scale_t == 0.5
    np.testing.assert_allclose(cfg.alignment_matrix, rot_z(math.pi / 2))
    with pytest.raises(ConfigError) as info:
        MasterConfig.from_mapping({"scale": 0.5})
    assert info.value.key == "master.scale"


# --- feedback -------------------------------------------------------------------------------


def wrench(
    f: ArrayLike,
    c: ArrayLike,
    tool_R: ArrayLike,
    *,
    A: ArrayLike | None = None,
    frame: Frame = "world",
    scale: float = 1.0,
    fmax: float = 100.0,
    cmax: float = 100.0,
) -> DisplayWrench:
    return operator_wrench(
        f,
        c,
        tool_R,
        alignment=np.eye(3) if A is None else A,
        frame=frame,
        force_scale=scale,
        max_force_n=fmax,
        max_torque_nm=cmax,
    )


def test_world_mode_rotates_tool_wrench_to_world_then_to_master() -> None:
    tool_R = rot_z(math.pi / 2)  # tool x is world y
    out = wrench((1.0, 0, 0), (0, 0, 2.0), tool_R)
    np.testing.assert_allclose(out.f, [0, 1.0, 0], atol=1e-12)
    np.testing.assert_allclose(out.c, [0, 0, 2.0], atol=1e-12)
    # The moment about the tool's axes, shown about the hand's: a tool pointing down
    # (its z the world's −z) that the hand turns about +z meets a moment about the tool's
    # −z, shown about the hand's −z: against the turn (about the world's axes it was +z).
    down = rot_x(math.pi)
    out = wrench((0, 0, 0), (0, 0, -2.0), down)
    np.testing.assert_allclose(out.c, [0, 0, -2.0], atol=1e-12)
    turned = operator_wrench(
        (0, 0, 0),
        (0, 0, -2.0),
        down,
        alignment=np.eye(3),
        frame="world",
        force_scale=1.0,
        max_force_n=100.0,
        max_torque_nm=100.0,
        hand_R=rot_x(math.pi / 2),
    )
    np.testing.assert_allclose(turned.c, [0, 2.0, 0], atol=1e-12)  # the hand's z is now −y
    # Master x drives slave y (A = Rz(90°)): a push along world y is felt along master x.
    out = wrench((1.0, 0, 0), (0, 0, 0), tool_R, A=rot_z(math.pi / 2))
    np.testing.assert_allclose(out.f, [1.0, 0, 0], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    c=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
    m0=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    r0=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    turn=st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3),
    step=st.lists(st.floats(-1e-4, 1e-4), min_size=3, max_size=3),
    frame=st.sampled_from(["world", "tool"]),
)
def test_the_moment_shown_has_the_power_of_the_tool_moment_against_the_tools_turn(
    c: list[float],
    m0: list[float],
    r0: list[float],
    turn: list[float],
    step: list[float],
    frame: Frame,
) -> None:
    """The hand turns a small step; eq. (5) turns the tool by it. The moment shown on the
    hand does the same work on the hand's step as the tool's moment on the tool's step,
    whatever the hand's and the tool's orientations and the mode."""
    M0, R0 = exp_so3(m0), exp_so3(r0)
    M1 = M0 @ exp_so3(turn)
    M2 = M1 @ exp_so3(step)
    dR1 = scaled_motion(np.zeros(3), M0, np.zeros(3), M1, 1.0, 1.0).dR
    dR2 = scaled_motion(np.zeros(3), M0, np.zeros(3), M2, 1.0, 1.0, near_rad=None).dR
    tool_step = log_so3((R0 @ dR1).T @ (R0 @ dR2))  # the tool's turn, its own axes
    hand_step = log_so3(M2 @ M1.T)  # the hand's turn, master frame
    shown = operator_wrench(
        (0.0, 0.0, 0.0),
        c,
        R0 @ dR1,
        alignment=exp_so3(m0),
        frame=frame,
        force_scale=1.0,
        max_force_n=1e9,
        max_torque_nm=1e9,
        hand_R=M1,
    ).c
    work_tool = float(np.dot(c, tool_step))
    work_hand = float(np.dot(shown, hand_step))
    assert work_hand == pytest.approx(work_tool, rel=1e-3, abs=1e-9 * (1.0 + np.linalg.norm(c)))


def test_tool_mode_ignores_tool_orientation() -> None:
    out = wrench((0, 0, -3.0), (0.1, 0, 0), rot_x(2.0), frame="tool", scale=0.5)
    np.testing.assert_allclose(out.f, [0, 0, -1.5], atol=1e-12)
    np.testing.assert_allclose(out.c, [0.05, 0, 0], atol=1e-12)


def test_saturation_keeps_direction_and_flags() -> None:
    out = wrench((30.0, 40.0, 0.0), (0, 0, 5.0), np.eye(3), fmax=10.0, cmax=1.0)
    np.testing.assert_allclose(out.f, [6.0, 8.0, 0.0])
    np.testing.assert_allclose(out.c, [0, 0, 1.0])
    assert out.force_saturated and out.torque_saturated
    calm = wrench((1.0, 0, 0), (0, 0, 0.1), np.eye(3), fmax=10.0, cmax=1.0)
    assert not calm.force_saturated and not calm.torque_saturated


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(ValueError):
        wrench((math.nan, 0, 0), (0, 0, 0), np.eye(3))
    with pytest.raises(ValueError):
        wrench((1, 0, 0), (0, 0, 0), 2 * np.eye(3))
    with pytest.raises(ValueError):
        wrench((1, 0, 0), (0, 0, 0), np.eye(3), frame="flange")  # type: ignore[arg-type]


def test_force_feedback_uses_config() -> None:
    cfg = MasterConfig(force_scale=0.5, max_force_n=2.0, max_torque_nm=0.1)
    out = ForceFeedback(cfg).compute((0, 0, 10.0), (0, 0.4, 0), np.eye(3).reshape(9), "world")
    np.testing.assert_allclose(out.f, [0, 0, 2.0])
    np.testing.assert_allclose(out.c, [0, 0.1, 0])
    zero = ForceFeedback.zero()
    assert not np.any(zero.f) and not np.any(zero.c)


vec = st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3)


@settings(max_examples=300, deadline=None)
@given(
    f=vec,
    c=vec,
    w=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    a=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    frame=st.sampled_from(["world", "tool"]),
    scale=st.floats(0.0, 5.0),
    fmax=st.floats(0.1, 50.0),
    cmax=st.floats(0.01, 5.0),
)
def test_displayed_wrench_never_exceeds_limits_and_keeps_direction(
    f: list[float],
    c: list[float],
    w: list[float],
    a: list[float],
    frame: Frame,
    scale: float,
    fmax: float,
    cmax: float,
) -> None:
    tool_R, A = exp_so3(w), exp_so3(a)
    out = wrench(f, c, tool_R, A=A, frame=frame, scale=scale, fmax=fmax, cmax=cmax)
    assert np.linalg.norm(out.f) <= fmax * (1 + 1e-12)
    assert np.linalg.norm(out.c) <= cmax * (1 + 1e-12)
    to_master = A.T @ tool_R if frame == "world" else A.T
    for got, raw in ((out.f, to_master @ f), (out.c, np.asarray(c))):  # c: the hand's axes
        if np.linalg.norm(raw) * scale > 1e-9:
            cos = float(got @ raw) / (np.linalg.norm(got) * np.linalg.norm(raw))
            assert cos > 1 - 1e-9


def test_saturate_passes_short_vectors_unchanged() -> None:
    v, sat = saturate((0.1, 0.2, 0.3), 1.0)
    np.testing.assert_array_equal(v, [0.1, 0.2, 0.3])
    assert not sat


# --- the force path: gate, ramp, hook -------------------------------------------------------

HAND = HandReading(np.zeros(3), np.eye(3), False)
PUSH = ((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), np.eye(3).reshape(9))


def test_ramp_gain_goes_from_zero_to_one_over_the_ramp() -> None:
    assert [ramp_gain(t, 0.5) for t in (-1.0, 0.0, 0.25, 0.5, 9.0)] == [0.0, 0.0, 0.5, 1.0, 1.0]
    assert ramp_gain(0.0, 0.0) == 1.0


def test_force_is_zero_unless_engaged_and_ramps_in_at_each_engagement() -> None:
    display = ForceDisplay(MasterConfig(force_ramp_s=1.0))
    assert not display.update(PUSH, "world", False, HAND, 0.01, 10.0).f.any()
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 10.0).f, 0.0)
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 10.5).f[2], 2.0)
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 12.0).f[2], 4.0)
    assert not display.update(PUSH, "world", False, HAND, 0.01, 13.0).f.any()  # master-shift
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 14.0).f, 0.0)
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 14.25).f[2], 1.0)
    assert not display.update(None, "world", True, HAND, 0.01, 20.0).f.any()  # stale data


def test_a_force_that_comes_back_after_a_stale_gap_ramps_in_again() -> None:
    """Engaged and ramped in (4 N shown); the stream goes stale for a while (zero shown);
    when it comes back the 4 N ramp in again over force_ramp_s instead of at once."""
    display = ForceDisplay(MasterConfig(force_ramp_s=1.0))
    display.update(PUSH, "world", True, HAND, 0.01, 10.0)
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 12.0).f[2], 4.0)
    assert not display.update(None, "world", True, HAND, 0.01, 12.5).f.any()
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 13.0).f, 0.0)
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 13.25).f[2], 1.0)
    np.testing.assert_allclose(display.update(PUSH, "world", True, HAND, 0.01, 14.5).f[2], 4.0)


def test_non_finite_input_shows_zero_and_counts_a_fault() -> None:
    display = ForceDisplay(MasterConfig(force_ramp_s=0.0))
    bad = ((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0), np.eye(3).reshape(9))
    assert not display.update(bad, "world", True, HAND, 0.01, 0.0).f.any()
    assert display.faults == 1


def test_a_hook_sees_the_wrench_and_cannot_exceed_the_limits() -> None:
    seen: list[tuple[DisplayWrench, HandReading, float]] = []

    def hook(w: DisplayWrench, hand: HandReading, dt_s: float) -> DisplayWrench:
        seen.append((w, hand, dt_s))
        return DisplayWrench(w.f * 100.0, w.c, False, False)

    cfg = MasterConfig(force_ramp_s=0.0, max_force_n=10.0)
    display = ForceDisplay(cfg, hook)
    out = display.update(PUSH, "world", True, HAND, 0.02, 0.0)
    np.testing.assert_allclose(out.f, [0.0, 0.0, 10.0])
    assert out.force_saturated and seen[0][0].f[2] == 4.0 and seen[0][2] == 0.02
    assert not display.update(PUSH, "world", False, HAND, 0.02, 1.0).f.any() and len(seen) == 1
    display.hook = lambda w, hand, dt: DisplayWrench(w.f * math.nan, w.c, False, False)
    assert not display.update(PUSH, "world", True, HAND, 0.02, 2.0).f.any()
    assert display.faults == 1


@settings(max_examples=200, deadline=None)
@given(
    ticks=st.lists(
        st.tuples(
            st.booleans(),
            st.floats(0.0, 0.2),
            st.lists(st.floats(-1e6, 1e6), min_size=6, max_size=6),
            st.booleans(),
        ),
        min_size=1,
        max_size=40,
    ),
    ramp_s=st.floats(0.0, 2.0),
)
def test_the_displayed_wrench_is_bounded_zero_when_disengaged_and_never_above_the_ramp(
    ticks: list[tuple[bool, float, list[float], bool]], ramp_s: float
) -> None:
    """Engagements, master-shifts and stale ticks in any order: zero while disengaged or
    stale, and never above the ramp since the later of the engagement and the force's
    return from a stale gap."""
    cfg = MasterConfig(force_ramp_s=ramp_s, max_force_n=3.0, max_torque_nm=0.5)
    display = ForceDisplay(cfg)
    now, since, fresh = 0.0, None, None
    for engaged, dt, w, stale in ticks:
        now += dt
        since = (since if since is not None else now) if engaged else None
        measured = None if stale else (w[:3], w[3:], np.eye(3).reshape(9))
        if engaged:
            fresh = None if stale else (fresh if fresh is not None else now)
        out = display.update(measured, "tool", engaged, HAND, dt, now)
        assert np.linalg.norm(out.f) <= 3.0 * (1 + 1e-12)
        assert np.linalg.norm(out.c) <= 0.5 * (1 + 1e-12)
        if since is None or fresh is None:
            assert not out.f.any() and not out.c.any()
        else:
            limit = 3.0 * ramp_gain(now - max(since, fresh), ramp_s)
            assert np.linalg.norm(out.f) <= limit * (1 + 1e-9) + 1e-12


# --- the contact damper ---------------------------------------------------------------------


def test_the_contact_dampers_bound_follows_the_devices_mass_and_the_loops_rate() -> None:
    """0.5 × 2·m·rate: 50 N·s/m for 0.5 kg at 100 Hz, 250 at 500 Hz, 500 for 1 kg there."""
    assert MasterConfig(contact_damping_ns_m=50.0).contact_damping_ns_m == 50.0
    assert MasterConfig(rate_hz=500.0, contact_damping_ns_m=250.0).contact_damping_ns_m == 250.0
    with pytest.raises(ConfigError, match="0 … 250 N·s/m") as info:
        MasterConfig(rate_hz=500.0, contact_damping_ns_m=251.0)
    assert info.value.key == "master.contact_damping_ns_m"
    heavy = MasterConfig(rate_hz=500.0, passivity_device_mass_kg=1.0, contact_damping_ns_m=500.0)
    assert heavy.contact_damping_ns_m == 500.0


def _moving(z_m: float) -> HandReading:
    return HandReading(np.array([0.0, 0.0, z_m]), np.eye(3), False)


def test_the_contact_damper_resists_the_hands_motion_in_contact_only() -> None:
    """Engaged, 4 N shown, the hand rising at 10 mm/s: 100 N·s/m take 1 N off once the
    velocity filter has settled; with no force shown (free space) nothing; at 0.5 N, half
    the gain (it ramps in with the force over CONTACT_DAMPING_FULL_N)."""
    cfg = MasterConfig(force_ramp_s=0.0, rate_hz=1000.0, contact_damping_ns_m=100.0)
    display = ForceDisplay(cfg)
    dt, v = 0.001, 0.01
    outs = [display.update(PUSH, "world", True, _moving(v * dt * k), dt, dt * k) for k in range(50)]
    assert outs[0].f[2] == 4.0  # no velocity from one position: no kick at engagement
    np.testing.assert_allclose(outs[-1].f, [0.0, 0.0, 4.0 - 100.0 * v], atol=1e-6)
    assert all(a.f[2] >= b.f[2] for a, b in itertools.pairwise(outs))  # no overshoot
    free = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), np.eye(3).reshape(9))
    light = ((0.0, 0.0, 0.5 * CONTACT_DAMPING_FULL_N), (0.0, 0.0, 0.0), np.eye(3).reshape(9))
    t = dt * 50
    for measured, want in ((free, 0.0), (light, 0.5 * CONTACT_DAMPING_FULL_N - 0.5)):
        for k in range(50, 100):
            out = display.update(measured, "world", True, _moving(v * dt * k), dt, t)
            t += dt
        np.testing.assert_allclose(out.f, [0.0, 0.0, want], atol=1e-6)


def test_the_contact_damper_is_off_when_disengaged_stale_or_after_a_stall() -> None:
    """Master-shift and a stale stream show nothing at all, however the hand moves; after
    either, and after a loop stalled past MAX_DAMPED_DT_S, the velocity starts afresh (one
    position is no velocity), so the damper never kicks the hand."""
    cfg = MasterConfig(force_ramp_s=0.0, rate_hz=1000.0, contact_damping_ns_m=100.0)
    display = ForceDisplay(cfg)
    dt = 0.001
    for k in range(20):
        display.update(PUSH, "world", True, _moving(0.001 * k), dt, dt * k)
    assert not display.update(PUSH, "world", False, _moving(0.5), dt, 0.1).f.any()
    assert display.update(PUSH, "world", True, _moving(0.9), dt, 0.2).f[2] == 4.0
    assert not display.update(None, "world", True, _moving(0.0), dt, 0.3).f.any()
    assert display.update(PUSH, "world", True, _moving(0.2), MAX_DAMPED_DT_S * 2, 0.4).f[2] == 4.0


@settings(max_examples=300, deadline=None)
@given(
    f=st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3),
    v=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3),
    b=st.floats(0.0, 500.0),
)
def test_the_contact_damper_only_takes_energy_from_the_hand(
    f: list[float], v: list[float], b: float
) -> None:
    """Its power against the hand's velocity is never positive, and it is no stronger than
    b·|v|, nor stronger than the force shown calls for (b × |f| / CONTACT_DAMPING_FULL_N)."""
    d = contact_damping(f, v, b)
    assert float(np.dot(d, v)) <= 1e-12
    gain = b * min(float(np.linalg.norm(f)) / CONTACT_DAMPING_FULL_N, 1.0)
    assert float(np.linalg.norm(d)) <= gain * float(np.linalg.norm(v)) * (1 + 1e-12) + 1e-12


def test_hand_velocity_is_the_filtered_difference_of_its_positions() -> None:
    hv = HandVelocity()
    assert not hv.update([0.0, 0.0, 0.0], 0.001).any()
    for k in range(1, 100):
        v = hv.update([0.002 * k, 0.0, 0.0], 0.001)
    np.testing.assert_allclose(v, [2.0, 0.0, 0.0], rtol=1e-9)
    hv.reset()
    assert not hv.update([5.0, 0.0, 0.0], 0.001).any()
