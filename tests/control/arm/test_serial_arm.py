"""The serial line protocol (docs/serial-arm-protocol.md): codec, fake controller, and
SerialArm under link faults — garbage, dropped bytes, a pulled cable — always ending in
`error` with the arm held, never a jump, and recovering with connect + initialize."""

from __future__ import annotations

import socket
import sys
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.arm.config import ArmConfig
from services.control.arm.driver import ArmError
from services.control.arm.fake_controller import FakeController
from services.control.arm.proxy import ArmProxy
from services.control.arm.serial_arm import (
    LineError,
    SerialArm,
    checksum,
    decode_line,
    encode_line,
    format_joints,
    parse_joints,
)
from tests.bus.test_router import spawned
from tests.conftest import wait_until

DEADLINE_S = 5.0


# --- codec -----------------------------------------------------------------------------------


def test_golden_sentences() -> None:
    # H^E^L^L^O = 0x48^0x45^0x4C^0x4C^0x4F = 0x42
    assert encode_line(["HELLO"]) == b"$HELLO*42\r\n"
    assert checksum(b"HELLO") == 0x42
    line = encode_line(["SP", "7", *format_joints([0.0, 0.785398, -3.141593, 0.0, 0.785398, 0.0])])
    assert line == (
        b"$SP,7,0.000000,0.785398,-3.141593,0.000000,0.785398,0.000000*"
        + f"{checksum(line[1:-5]):02X}".encode()
        + b"\r\n"
    )
    assert decode_line(line) == [
        "SP", "7", "0.000000", "0.785398", "-3.141593", "0.000000", "0.785398", "0.000000",
    ]  # fmt: skip
    assert decode_line(b"$HELLO*42\n") == ["HELLO"]  # a bare LF ends a line too


@pytest.mark.parametrize(
    ("raw", "code"),
    [
        (b"$HELLO*43\r\n", "CHK"),
        (b"HELLO*42\r\n", "SYNTAX"),
        (b"$HELLO42\r\n", "SYNTAX"),
        (b"$HELLO*4G\r\n", "SYNTAX"),
        (b"$HELLO*4\r\n", "SYNTAX"),
        (b"$HELLO*42 \r\n", "SYNTAX"),
        (b"$*00\r\n", "SYNTAX"),
        (b"$" + b"A" * 130 + b"*41\r\n", "SYNTAX"),
        (b"$HEL\xffLO*BD\r\n", "SYNTAX"),
    ],
)
def test_bad_lines_are_refused(raw: bytes, code: str) -> None:
    with pytest.raises(LineError) as info:
        decode_line(raw)
    assert info.value.code == code


def test_lowercase_checksum_digits_are_refused() -> None:
    line = next(
        line
        for seq in range(100)
        if not (line := encode_line(["JS", str(seq), *format_joints([0.1] * 6)]))[-4:-2].isdigit()
    )
    assert decode_line(line)[0] == "JS"
    with pytest.raises(LineError):
        decode_line(line[:-4] + line[-4:-2].lower() + b"\r\n")


def test_joint_fields_must_be_six_finite_numbers() -> None:
    np.testing.assert_allclose(
        parse_joints(["1", "-2.5", "0", "0", "0", "3e-3"]), [1, -2.5, 0, 0, 0, 0.003]
    )
    for bad in (["1"] * 5, ["1"] * 5 + ["x"], ["1"] * 5 + ["nan"], ["1"] * 5 + ["inf"]):
        with pytest.raises(LineError):
            parse_joints(bad)
    with pytest.raises(ValueError):
        encode_line(["SP", "1,2"])  # a field cannot smuggle a separator


joints = st.lists(st.floats(-4.7, 4.7, allow_nan=False), min_size=6, max_size=6)


@settings(max_examples=300, deadline=None)
@given(q=joints, seq=st.integers(0, 2**31), data=st.data())
def test_any_single_byte_error_is_detected(q: list[float], seq: int, data: st.DataObject) -> None:
    line = encode_line(["SP", str(seq), *format_joints(q)])
    body = line[:-2]  # without CR LF: what framing hands the decoder
    i = data.draw(st.integers(0, len(body) - 1), label="index")
    how = data.draw(st.sampled_from(["drop", "change", "insert"]), label="how")
    other = st.integers(0, 255).filter(lambda b: b not in b"\r\n")
    if how == "drop":
        bad = body[:i] + body[i + 1 :]
    elif how == "change":
        b = data.draw(other.filter(lambda b: b != body[i]), label="byte")
        bad = body[:i] + bytes([b]) + body[i + 1 :]
    else:
        b = data.draw(other, label="byte")
        bad = body[:i] + bytes([b]) + body[i:]
    with pytest.raises(LineError):
        decode_line(bad + b"\r\n")


# --- SerialArm against the fake --------------------------------------------------------------


@pytest.fixture
def fake() -> Iterator[FakeController]:
    f = FakeController(calibration_s=0.05).start()
    try:
        yield f
    finally:
        f.close()


@pytest.fixture
def arm(fake: FakeController) -> Iterator[SerialArm]:
    # 0.3 s per reply: the faults below are found in that much more, and on two loaded
    # cores the fake's thread can stall past 0.1 s between CAL and READY (an `error`
    # before `ready`, once in a full run).
    a = SerialArm(fake.url, cycle_ms=4.0, timeout_s=0.3)
    try:
        yield a
    finally:
        a.close()


def make_ready(arm: SerialArm) -> np.ndarray:
    arm.connect()
    arm.initialize()
    ready = wait_until(lambda: arm.status == "ready", what="ready")
    assert ready, (ready, arm.status, arm._last_error)
    return arm.read_joints()


def stream_until_error(arm: SerialArm, q_from: np.ndarray, direction: np.ndarray) -> int:
    """Stream a slow ramp until the arm reports an error; the number of setpoints given."""
    k = 0
    while arm.status != "error":
        k += 1
        arm.command(q_from + direction * min(k * 2e-4, 0.2))
        if k > 5000:
            raise AssertionError("no error")
        time.sleep(0.002)
    return k


def recover(arm: SerialArm) -> np.ndarray:
    arm.connect()
    arm.initialize()
    assert wait_until(lambda: arm.status == "ready", what="ready after recovery")
    return arm.read_joints()


def assert_held(fake: FakeController) -> np.ndarray:
    """Wait until the fake's arm is still; where it is."""
    seen: list[np.ndarray] = []

    def still() -> bool:
        seen.append(fake.q)
        return len(seen) > 30 and bool(np.max(np.abs(seen[-1] - seen[-30])) < 1e-9)

    assert wait_until(still, what="the arm to hold")
    return seen[-1]


@pytest.mark.parametrize(
    "fault",
    [
        "garble_reply",
        "drop_reply_bytes",
        "garble_rx",
        "noise",
        "pull_soft",
        "pull_hard",
        "pendant_estop",
    ],
)
def test_link_fault_gives_error_hold_and_recovery_without_jump(
    fake: FakeController, arm: SerialArm, fault: str
) -> None:
    q0 = make_ready(arm)
    direction = np.array([1.0, -1.0, 1.0, 1.0, -1.0, 1.0])
    # Move a little first, so a fault strikes a moving arm.
    for k in range(1, 60):
        arm.command(q0 + direction * k * 2e-4)
        time.sleep(0.002)
    {
        "garble_reply": lambda: fake.garble_next_reply(),
        "drop_reply_bytes": lambda: fake.drop_next_reply_bytes(3),
        "garble_rx": lambda: fake.garble_next_rx(),
        "noise": lambda: fake.set_noise(drop_per_byte=0.002, garble_per_byte=0.002),
        "pull_soft": lambda: fake.pull_cable(),
        "pull_hard": lambda: fake.pull_cable(hard=True),
        "pendant_estop": lambda: fake.press_estop(),
    }[fault]()
    stream_until_error(arm, q0, direction)
    assert arm.status == "error"
    assert arm.last_error
    accepted = len(fake.setpoints)
    q_held = assert_held(fake)
    # Nothing reaches the controller after the error, whatever the host keeps asking.
    for _ in range(30):
        arm.command(q0 + direction * 0.2)
        time.sleep(0.001)
    assert len(fake.setpoints) == accepted
    np.testing.assert_allclose(fake.q, q_held, atol=1e-12)

    # The fault has passed. (Under load the stream can fail on a late reply before a
    # one-shot fault fired; left armed, it would garble the recovery's handshake.)
    fake.clear_faults()
    if fault.startswith("pull"):
        with pytest.raises(ArmError):
            arm.connect()  # the cable is still out
        assert arm.status == "error"
        fake.plug_cable()
    q_back = recover(arm)
    np.testing.assert_allclose(q_back, q_held, atol=2e-6)
    for k in range(1, 40):
        arm.command(q_back + direction * k * 2e-4)
        time.sleep(0.002)
    assert arm.status == "ready"
    # Never a jump: each accepted setpoint was within the ramp step of the measured joints.
    assert fake.max_setpoint_jump_rad < 0.05
    assert fake.errors_sent["STEP"] == 0


def test_corrupted_setpoint_is_never_executed(fake: FakeController, arm: SerialArm) -> None:
    q0 = make_ready(arm)
    fake.garble_next_rx(kind="SP")
    arm.command(q0 + 0.01)
    assert wait_until(lambda: arm.status == "error", what="error")
    assert fake.errors_sent["CHK"] == 1
    assert "CHK" in (arm.last_error or "")
    assert len(fake.setpoints) == 0
    np.testing.assert_allclose(assert_held(fake), q0, atol=2e-6)


def test_controller_watchdog_holds_when_setpoints_stop(fake: FakeController) -> None:
    arm = SerialArm(fake.url, cycle_ms=4.0, setpoint_stale_s=0.05)
    try:
        q0 = make_ready(arm)
        for k in range(1, 80):
            arm.command(q0 + k * 1e-3)
            time.sleep(0.002)
        # The host loop stops giving setpoints: the link only reads the joints now, and the
        # controller's watchdog holds the arm.
        assert wait_until(lambda: fake.watchdog_trips == 1, what="the watchdog")
        n = len(fake.setpoints)
        assert_held(fake)
        assert len(fake.setpoints) == n
        assert arm.status == "ready"
    finally:
        arm.close()


def test_stop_sends_hold(fake: FakeController, arm: SerialArm) -> None:
    q0 = make_ready(arm)
    for k in range(1, 60):
        arm.command(q0 + k * 2e-3)
        time.sleep(0.002)
    arm.stop()
    assert fake.replies["ACK"] >= 3  # RESET, CAL, HOLD
    q_held = assert_held(fake)
    assert np.all(q_held > q0)


def test_connect_to_nothing_fails_cleanly() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    arm = SerialArm(f"socket://127.0.0.1:{port}", cycle_ms=10.0)
    with pytest.raises(ArmError):
        arm.connect()
    assert arm.status == "error"
    with pytest.raises(ArmError):
        arm.initialize()
    arm.close()


def test_cycle_faster_than_the_controller_allows_is_refused() -> None:
    with FakeController(min_cycle_us=10_000) as slow:
        arm = SerialArm(slow.url, cycle_ms=4.0)
        with pytest.raises(ArmError, match="minimum"):
            arm.connect()
        arm.close()


def test_streams_at_the_classic_28_ms_cycle(fake: FakeController) -> None:
    arm = SerialArm(fake.url)  # defaults: 28 ms, 115200 Bd
    try:
        q0 = make_ready(arm)
        calls = 0
        t0 = time.monotonic()
        while arm.setpoints_sent < 6:
            arm.command(q0 + 0.01)  # the host loop runs much faster than the link
            calls += 1
            time.sleep(0.002)
            assert time.monotonic() - t0 < DEADLINE_S
        elapsed_s = time.monotonic() - t0
        # At most one setpoint per 28 ms cycle, however often the host calls command().
        assert arm.setpoints_sent <= elapsed_s / 0.028 + 2
        assert calls > arm.setpoints_sent
    finally:
        arm.close()


def test_proxy_over_the_serial_arm_never_jumps_across_a_fault(fake: FakeController) -> None:
    """The whole chain: proxy → SerialArm → wire → controller, a fault mid-motion, recovery."""
    arm = SerialArm(fake.url, cycle_ms=4.0)
    events: list[tuple[str, str, dict]] = []
    cfg = ArmConfig(driver="serial", port=fake.url)
    proxy = ArmProxy(arm, cfg, lambda k, m, d: events.append((k, m, d)))
    dt = 1.0 / cfg.control_rate_hz

    def run_until(pred: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + DEADLINE_S
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            proxy.tick(dt)
            time.sleep(dt)

    try:
        proxy.rpc_connect({})
        proxy.rpc_initialize({})
        run_until(lambda: proxy.state()["status"] == "ready", "ready")
        q0 = np.array(proxy.state()["q"])
        proxy.rpc_move_joints({"q": list(q0 + 0.3)})
        run_until(lambda: len(fake.setpoints) > 20, "motion")
        fake.garble_next_reply()
        run_until(lambda: proxy.state()["status"] == "error", "error")
        assert any(k == "error" and d.get("code") == "internal" for k, _, d in events)
        q_held = assert_held(fake)
        proxy.rpc_connect({})
        proxy.rpc_initialize({})
        run_until(lambda: proxy.state()["status"] == "ready", "ready again")
        np.testing.assert_allclose(proxy.state()["q"], q_held, atol=2e-6)
        r = proxy.rpc_move_joints({"q": list(q0 + 0.1)})
        run_until(lambda: proxy.state()["status"] == "ready", "the move to finish")
        assert proxy.wait_motion(r["motion"], 0.0)["completed"]
        assert wait_until(
            lambda: bool(np.max(np.abs(fake.q - (q0 + 0.1))) < 1e-3), what="the arm to arrive"
        )
        # The controller's own record: no setpoint was ever far from where the arm was.
        assert fake.max_setpoint_jump_rad < 0.1
        assert fake.errors_sent["STEP"] == 0
    finally:
        proxy.close()


def test_fake_controller_runs_as_a_program() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = [sys.executable, "-m", "services.control.arm.fake_controller", "--port", str(port)]
    with spawned([*argv, "--calibration-s", "0"], merge_stderr=False) as fake:
        first = fake.expect(lambda _: True).strip()
        assert first == f"fake PUMA controller on socket://127.0.0.1:{port}"
        arm = SerialArm(f"socket://127.0.0.1:{port}", cycle_ms=5.0)
        arm.connect()
        assert arm.controller_id == "PUMA560,FAKE-1.0"
        arm.close()


def test_cleared_faults_do_not_fire_later(fake: FakeController, arm: SerialArm) -> None:
    q0 = make_ready(arm)
    fake.garble_next_reply(5)
    fake.drop_next_reply_bytes(3)
    fake.garble_next_rx(2, kind="SP")
    fake.set_noise(drop_per_byte=0.5, garble_per_byte=0.5)
    fake.clear_faults()
    for k in range(1, 20):
        arm.command(q0 + k * 1e-4)
        time.sleep(0.002)
    q_held = assert_held(fake)
    np.testing.assert_allclose(arm.read_joints(), q_held, atol=1e-6)
    assert arm.status == "ready", arm.last_error
    assert sum(fake.errors_sent.values()) == 0


def test_a_serial_port_that_does_not_exist_is_said_at_start_up_and_connect_says_why(
    net, tmp_path, caplog: pytest.LogCaptureFixture
) -> None:
    """`telerobot arm --driver serial --port /dev/ttyUSB0` with no such device: before, it
    logged "up" and failed only at `connect`, with `internal`. Now an `error` event and a
    warning at start-up naming the port, and `connect` fails `not_ready` saying why."""
    import logging
    import threading

    from services.bus import keys
    from services.bus.errors import RpcError
    from services.bus.messages import Event
    from services.control.arm.service import ArmService

    missing = str(tmp_path / "ttyUSB0")
    assert SerialArm("socket://127.0.0.1:1").preflight() is None  # URLs: only connect knows
    events: list[Event] = []
    lock = threading.Lock()

    def on_event(ev: Event) -> None:
        with lock:
            events.append(ev)

    net.node("viewer").subscribe(keys.EVENTS, on_event)
    with caplog.at_level(logging.WARNING, logger="telerobot.arm"):
        svc = ArmService(net.node("arm"), ArmConfig(driver="serial", port=missing))
    try:

        def said() -> bool:
            with lock:
                return any(e.kind == "error" and missing in e.message for e in events)

        assert wait_until(said, DEADLINE_S), [(e.kind, e.message) for e in events]
        assert any("no serial port" in r.getMessage() for r in caplog.records)
        with pytest.raises(RpcError) as err:
            svc.proxy.rpc_connect({})
        assert err.value.code == "not_ready" and missing in err.value.message
        assert svc.proxy.status == "error"
    finally:
        svc.close()
