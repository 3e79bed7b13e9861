"""The serial master arm: line protocol, kinematics, and the backend against its fake."""

from __future__ import annotations

import binascii
import math
import socket
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.master.device import DeviceNotFound
from services.control.master.devices.master_arm.backend import SerialMasterArm
from services.control.master.devices.master_arm.fake import FakeMasterArm
from services.control.master.devices.master_arm.kinematics import (
    DEFAULT_MASTER_DH,
    DhRow,
    forward_kinematics,
    geometric_jacobian,
    joint_torques_for_wrench,
)
from services.control.master.devices.master_arm.protocol import (
    Identity,
    JointFrame,
    LineError,
    LineSplitter,
    TorqueFrame,
    crc16_ccitt,
    encode_line,
    parse_line,
)
from services.geometry import log_so3
from tests.conftest import wait_until

PUMA_DH = (
    (0.67183, 0.0, math.pi / 2),
    (0.0, 0.4318, 0.0),
    (0.15005, 0.0203, -math.pi / 2),
    (0.4318, 0.0, math.pi / 2),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.0, 0.0),
)

# --- protocol ---------------------------------------------------------------------------------


def test_crc_check_value_and_independent_reference() -> None:
    assert crc16_ccitt(b"123456789") == 0x29B1
    body = b"J,7,0,15708,-5000,0,2500,-31416,1,250"
    assert crc16_ccitt(body) == binascii.crc_hqx(body, 0xFFFF)


def test_golden_lines() -> None:
    frame = JointFrame(7, (0.0, 1.5708, -0.5, 0.0, 0.25, -3.1416), 1, 0.25)
    assert frame.encode() == b"$J,7,0,15708,-5000,0,2500,-31416,1,250*3A17\r\n"
    torque = TorqueFrame(12, (0.5, -0.25, 0.0, 0.001, 0.0, -1.0))
    assert torque.encode() == b"$T,12,500,-250,0,1,0,-1000*A49C\r\n"
    assert encode_line("I") == b"$I*381D\r\n"
    assert encode_line("S", ["100"]) == b"$S,100*53C3\r\n"


def test_parse_round_trips_and_rejects() -> None:
    kind, fields = parse_line(b"$J,7,0,15708,-5000,0,2500,-31416,1,250*3A17\r\n")
    assert kind == "J"
    frame = JointFrame.decode(fields)
    assert frame.seq == 7 and frame.buttons == 1 and frame.grip == 0.25
    assert frame.q_rad == pytest.approx((0.0, 1.5708, -0.5, 0.0, 0.25, -3.1416))
    with pytest.raises(LineError) as crc:
        parse_line(b"$J,7,0,15708,-5000,0,2500,-31416,1,250*3A18")
    assert crc.value.reason == "crc"
    for bad in (b"J,1*0000", b"$J,1", b"$J,1*12", b"$j,1*" + f"{crc16_ccitt(b'j,1'):04X}".encode()):
        with pytest.raises(LineError) as info:
            parse_line(bad)
        assert info.value.reason == "syntax"
    with pytest.raises(LineError):
        JointFrame.decode(["1", "2"])
    with pytest.raises(LineError) as rng:
        JointFrame.decode(["1", "0", "0", "0", "0", "0", "0", "0", "1001"])
    assert rng.value.reason == "range"
    assert JointFrame.decode(["65535", "0", "0", "0", "0", "0", "0", "A", ""]).grip is None
    assert Identity.decode(["arm", "2.1", "6"]) == Identity("arm", "2.1", 6)


@settings(max_examples=200, deadline=None)
@given(
    seq=st.integers(0, 65535),
    q=st.lists(st.floats(-7.0, 7.0), min_size=6, max_size=6),
    buttons=st.integers(0, 0xFFFF),
    grip=st.one_of(st.none(), st.floats(0.0, 1.0)),
)
def test_joint_frame_round_trip_within_quantisation(
    seq: int, q: list[float], buttons: int, grip: float | None
) -> None:
    line = JointFrame(seq, tuple(q), buttons, grip).encode()
    kind, fields = parse_line(line)
    back = JointFrame.decode(fields)
    assert kind == "J" and back.seq == seq and back.buttons == buttons
    np.testing.assert_allclose(back.q_rad, q, atol=0.5e-4 + 1e-12)
    assert (back.grip is None) == (grip is None)


def test_splitter_handles_fragments_and_noise() -> None:
    s = LineSplitter()
    assert s.feed(b"$I*38") == []
    assert s.feed(b"1D\r\n$A,S*") == [b"$I*381D"]
    assert s.feed(b"XXXX\r\n\r\n") == [b"$A,S*XXXX"]
    assert s.feed(b"#" * 300) == [] and s.overflows == 1
    assert s.feed(b"$I*381D\n") == [b"$I*381D"]


# --- kinematics -------------------------------------------------------------------------------


def test_dh_convention_matches_the_arm_qz_pose() -> None:
    # PROTOCOL §1 table at qz: flange at (a2 + a3, −d3, d1 + d4) with identity orientation.
    p, R = forward_kinematics(np.zeros(6), PUMA_DH)
    np.testing.assert_allclose(p, [0.4521, -0.15005, 1.10363], atol=1e-12)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)


def test_planar_two_link_hand_worked() -> None:
    dh = ((0.0, 1.0, 0.0), (0.0, 1.0, 0.0))
    p, _ = forward_kinematics([math.pi / 2, -math.pi / 2], dh)
    np.testing.assert_allclose(p, [1.0, 1.0, 0.0], atol=1e-12)
    J = geometric_jacobian([0.0, 0.0], dh)
    np.testing.assert_allclose(J[:3], [[0, 0], [2, 1], [0, 0]], atol=1e-12)


def fd_jacobian(
    q: np.ndarray, dh: tuple[DhRow, ...] = DEFAULT_MASTER_DH, h: float = 1e-6
) -> np.ndarray:
    """Central differences: linear velocity of the hand point and angular velocity."""
    J = np.zeros((6, len(q)))
    for i in range(len(q)):
        dq = np.zeros(len(q))
        dq[i] = h
        p1, R1 = forward_kinematics(q + dq, dh)
        p0, R0 = forward_kinematics(q - dq, dh)
        J[:3, i] = (p1 - p0) / (2 * h)
        J[3:, i] = log_so3(R1 @ R0.T) / (2 * h)
    return J


@settings(max_examples=50, deadline=None)
@given(q=st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6))
def test_geometric_jacobian_matches_finite_differences(q: list[float]) -> None:
    qa = np.array(q)
    np.testing.assert_allclose(geometric_jacobian(qa), fd_jacobian(qa), atol=1e-6)


# --- the backend against the fake arm ---------------------------------------------------------

Q_TEST = (0.3, 1.2, -0.4, 0.5, 0.7, -0.2)


@pytest.fixture
def fake() -> Iterator[FakeMasterArm]:
    with FakeMasterArm(q_rad=Q_TEST, model="lab-arm") as arm:
        yield arm


@pytest.fixture
def arm(fake: FakeMasterArm) -> Iterator[SerialMasterArm]:
    dev = SerialMasterArm(fake.url, stream_rate_hz=200, max_joint_torque_nm=5.0)
    dev.open()
    yield dev
    dev.close()


def test_open_identifies_and_streams(fake: FakeMasterArm, arm: SerialMasterArm) -> None:
    assert arm.name == "serial_arm:lab-arm" and arm.can_display_force
    assert fake.commands[:3] == ["X", "I", "S"]
    r = arm.read(0.01)
    q = arm.q_rad
    assert q is not None
    p, R = forward_kinematics(q, DEFAULT_MASTER_DH)
    np.testing.assert_allclose(q, fake.sent[-1].q_rad)
    np.testing.assert_allclose(q, Q_TEST, atol=0.5e-4)
    np.testing.assert_allclose(r.hand_p, p)
    np.testing.assert_allclose(r.hand_R, R)
    assert r.clutch is False


def test_torque_display_is_jacobian_transpose_times_wrench(
    fake: FakeMasterArm, arm: SerialMasterArm
) -> None:
    arm.read(0.01)
    q = arm.q_rad
    assert q is not None
    f, c = np.array([1.5, -2.0, 3.0]), np.array([0.1, 0.05, -0.2])
    arm.display_force(f, c)
    assert wait_until(lambda: len(fake.torques) == 1)
    expected = fd_jacobian(q).T @ np.concatenate([f, c])
    np.testing.assert_allclose(fake.torques[0].tau_nm, expected, atol=1e-3)
    np.testing.assert_allclose(
        fake.torques[0].tau_nm, joint_torques_for_wrench(q, f, c), atol=0.5e-3 + 1e-12
    )
    assert arm.stats.torques_sent == 1


def test_torques_are_clamped(fake: FakeMasterArm, arm: SerialMasterArm) -> None:
    arm.read(0.01)
    arm.display_force([500.0, 0, 0], [0, 0, 0])
    assert wait_until(lambda: len(fake.torques) == 1)
    tau = np.array(fake.torques[0].tau_nm)
    assert np.max(np.abs(tau)) == pytest.approx(5.0)


def test_buttons_and_grip(fake: FakeMasterArm, arm: SerialMasterArm) -> None:
    fake.set_buttons(0b01)
    fake.set_grip(0.4)
    assert wait_until(lambda: arm.read(0.0).clutch)
    assert arm.read(0.0).grip == pytest.approx(0.4)
    fake.set_buttons(0)
    assert wait_until(lambda: not arm.read(0.0).clutch)


def test_motion_script_is_followed(fake: FakeMasterArm, arm: SerialMasterArm) -> None:
    fake.set_motion(lambda t: (min(t, 0.05), *Q_TEST[1:]))
    assert wait_until(
        lambda: abs(arm.read(0.0).hand_p[0] - forward_kinematics((0.05, *Q_TEST[1:]))[0][0]) < 1e-9
    )


def test_corrupted_frames_are_counted_and_skipped(
    fake: FakeMasterArm, arm: SerialMasterArm
) -> None:
    fake.corrupt_next(3)
    assert wait_until(lambda: (arm.read(0.0), arm.stats.crc_errors)[1] == 3)
    frames = arm.stats.frames
    assert wait_until(lambda: (arm.read(0.0), arm.stats.frames)[1] > frames)
    assert arm.stats.lost >= 3  # the three bad frames leave a gap in seq


def test_silent_line_reads_as_master_shift(fake: FakeMasterArm) -> None:
    arm = SerialMasterArm(fake.url, stale_s=0.05)
    arm.open()
    try:
        assert arm.read(0.0).clutch is False
        fake.set_silent(True)
        assert wait_until(lambda: arm.read(0.0).clutch)
        fake.set_silent(False)
        assert wait_until(lambda: not arm.read(0.0).clutch)
    finally:
        arm.close()


def test_arm_watchdog_zeroes_torque_when_the_host_stops() -> None:
    with FakeMasterArm(q_rad=Q_TEST, torque_watchdog_s=0.05) as fake:
        arm = SerialMasterArm(fake.url)
        arm.open()
        try:
            arm.read(0.0)
            arm.display_force([0, 0, 2.0], [0, 0, 0])
            assert wait_until(lambda: any(fake.applied_torque_nm))
            assert wait_until(lambda: not any(fake.applied_torque_nm))
            assert wait_until(lambda: (arm.read(0.0), arm.stats.watchdogs)[1] == 1)
        finally:
            arm.close()


def test_close_stops_streaming_and_zeroes_torque(fake: FakeMasterArm) -> None:
    arm = SerialMasterArm(fake.url)
    arm.open()
    arm.read(0.0)
    arm.display_force([0, 0, 1.0], [0, 0, 0])
    arm.close()
    assert wait_until(lambda: fake.commands[-1:] == ["X"])
    assert not any(fake.applied_torque_nm)
    arm.close()


def test_nothing_listening_is_device_not_found() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(DeviceNotFound) as info:
        SerialMasterArm(f"socket://127.0.0.1:{port}").open()
    assert "cannot open master arm" in str(info.value)


def test_no_port_says_which_flag_gives_it() -> None:
    """`master --device serial_arm` without `--port` said "cannot open master arm at :"."""
    with pytest.raises(DeviceNotFound) as info:
        SerialMasterArm("").open()
    assert "needs its port: --port" in str(info.value)


def test_mute_peer_is_device_not_found() -> None:
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        url = f"socket://127.0.0.1:{server.getsockname()[1]}"
        with pytest.raises(DeviceNotFound) as info:
            SerialMasterArm(url, open_timeout_s=0.2).open()
    assert "no master arm answered" in str(info.value)


def test_wrong_joint_count_is_refused() -> None:
    with FakeMasterArm(n_joints=7) as fake, pytest.raises(DeviceNotFound) as info:
        SerialMasterArm(fake.url).open()
    assert "7 joints" in str(info.value)


def test_fake_naks_bad_host_lines(fake: FakeMasterArm) -> None:
    with socket.create_connection(("127.0.0.1", fake.port)) as s:
        s.sendall(b"$Q*0000\r\n" + encode_line("Q") + encode_line("S", ["5000"]))
        assert wait_until(lambda: fake.naks_sent == 3)
        data = b""
        while data.count(b"\n") < 3:
            data += s.recv(1024)
    reasons = [parse_line(line)[1][0] for line in data.splitlines()[:3]]
    assert reasons == ["crc", "unknown", "range"]
