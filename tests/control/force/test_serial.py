"""The serial line format (docs/serial-force-protocol.md) and SerialSensor against the fake."""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.force.fake_serial_sensor import FakeSerialSensor
from services.control.force.sensors import SensorError
from services.control.force.serial_sensor import (
    LineError,
    SerialFrame,
    SerialSensor,
    checksum,
    decode_line,
    encode_command,
    encode_sample,
)
from tests.conftest import wait_until
from tests.control.force.helpers import Events, drain_until

# --- golden bytes -------------------------------------------------------------------------


def test_golden_sample_line() -> None:
    line = encode_sample(42, [1, -2, 300, 0, 12345, -8388608])
    assert line == b"$FS,42,1,-2,300,0,12345,-8388608*3B\r\n"
    assert checksum(b"FS,42,1,-2,300,0,12345,-8388608") == 0x3B
    assert decode_line(line) == SerialFrame(42, (1.0, -2.0, 300.0, 0.0, 12345.0, -8388608.0))


def test_golden_commands() -> None:
    # S^T^A^R^T = 0x53^0x54^0x41^0x52^0x54 = 0x40; S^T^O^P = 0x18
    assert encode_command("START") == b"$START*40\r\n"
    assert encode_command("STOP") == b"$STOP*18\r\n"


def test_decimal_channels_and_other_sentences() -> None:
    frame = decode_line(
        b"$FS,7,0.5,-1.25e-3,+3,.5,2.,1E2*" + b"%02X" % checksum(b"FS,7,0.5,-1.25e-3,+3,.5,2.,1E2")
    )
    assert frame == SerialFrame(7, (0.5, -1.25e-3, 3.0, 0.5, 2.0, 100.0))
    assert decode_line(b"$ID,wrist-3*" + b"%02X" % checksum(b"ID,wrist-3")) is None


@pytest.mark.parametrize(
    ("line", "fault", "seq"),
    [
        (b"\x00\xff#garbage!", "garbage", None),
        (b"FS,1,1,2,3,4,5,6*00", "garbage", None),
        (b"$FS,1,1,2,3,4,5,6*00", "checksum", None),
        (b"$FS,1,1,2,3", "short", None),
        (b"$FS,1,1,2,3*" + b"%02X" % checksum(b"FS,1,1,2,3"), "short", 1),
        (b"$FS,9,1,NaN,3,4,5,6*" + b"%02X" % checksum(b"FS,9,1,NaN,3,4,5,6"), "nan", 9),
        (b"$FS,9,1,-inf,3,4,5,6*" + b"%02X" % checksum(b"FS,9,1,-inf,3,4,5,6"), "nan", 9),
        (b"$FS,9,1,1e999,3,4,5,6*" + b"%02X" % checksum(b"FS,9,1,1e999,3,4,5,6"), "nan", 9),
        (b"$FS,9,1,0x1f,3,4,5,6*" + b"%02X" % checksum(b"FS,9,1,0x1f,3,4,5,6"), "number", 9),
        (b"$FS,70000,1,2,3,4,5,6*" + b"%02X" % checksum(b"FS,70000,1,2,3,4,5,6"), "garbage", None),
        (b"$" + b"1" * 200, "overlong", None),
    ],
)
def test_bad_lines_are_classified(line: bytes, fault: str, seq: int | None) -> None:
    with pytest.raises(LineError) as e:
        decode_line(line)
    assert (e.value.fault, e.value.seq) == (fault, seq)


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=160))
def test_any_bytes_decode_to_a_finite_frame_or_a_line_error(data: bytes) -> None:
    """Safety: no input line makes the parser crash or yield a non-finite signal."""
    try:
        frame = decode_line(data)
    except LineError:
        return
    if frame is not None:
        assert all(math.isfinite(v) for v in frame.channels)


@settings(max_examples=200, deadline=None)
@given(
    seq=st.integers(0, 65535),
    ch=st.lists(st.integers(-(2**31), 2**31) | st.floats(-1e12, 1e12), min_size=6, max_size=6),
)
def test_encode_decode_round_trip(seq: int, ch: list[float]) -> None:
    frame = decode_line(encode_sample(seq, ch))
    assert frame is not None and frame.seq == seq
    for got, want in zip(frame.channels, ch, strict=True):
        assert got == pytest.approx(want, rel=1e-8, abs=1e-9)


# --- SerialSensor against the fake ------------------------------------------------------


@pytest.fixture
def fake() -> Iterator[FakeSerialSensor]:
    with FakeSerialSensor(rate_hz=1000.0, signals=(1, 2, 3, 4, 5, 6)) as f:
        yield f


def test_reads_the_stream_and_sends_start_stop(fake: FakeSerialSensor) -> None:
    events = Events()
    s = SerialSensor(fake.url, on_event=events)
    with pytest.raises(SensorError):
        s.read()
    s.open()
    r = drain_until(s, lambda: s.frames >= 200)
    assert r is not None and r.kind == "signals" and r.values == (1, 2, 3, 4, 5, 6)
    fake.set_signals((-7, 0, 0, 0, 0, 8))
    r = drain_until(s, lambda: s.frames >= 400)
    assert r is not None and r.values == (-7, 0, 0, 0, 0, 8)
    assert (s.bad, s.gaps) == (0, 0)
    assert events.items == []
    s.close()
    assert wait_until(lambda: len(fake.commands) == 2)
    assert fake.commands == [encode_command("START"), encode_command("STOP")]


def test_faults_are_dropped_counted_and_reported(fake: FakeSerialSensor) -> None:
    events = Events()
    s = SerialSensor(fake.url, on_event=events)
    s.open()
    drain_until(s, lambda: s.frames >= 50)
    fake.inject_garbage(2)
    fake.inject_nan(1)
    fake.inject_short(1)
    fake.inject_bad_checksum(1)
    fake.skip(3)
    # garbage, NaN, short, checksum: 5 bad; short and checksum lose a sample each, plus 3.
    drain_until(s, lambda: s.bad >= 5 and s.gaps >= 5)
    n = s.frames
    r = drain_until(s, lambda: s.frames >= n + 200)
    assert (s.bad, s.gaps) == (5, 5)
    assert r is not None and all(math.isfinite(v) for v in r.values)
    reasons = sorted(d["reason"] for k, _, d in events.items if k == "bad_data")
    assert reasons == ["checksum", "garbage", "garbage", "nan", "short"]
    assert sum(d["missing"] for k, _, d in events.items if k == "gap") == 5
    s.close()


def test_stall_gives_no_data_then_resumes_without_gap(fake: FakeSerialSensor) -> None:
    s = SerialSensor(fake.url)
    s.open()
    drain_until(s, lambda: s.frames >= 20)
    fake.stall(0.2)
    assert wait_until(lambda: s.read() is None)  # nothing new while stalled
    n = s.frames
    drain_until(s, lambda: s.frames >= n + 50)
    assert (s.bad, s.gaps) == (0, 0)
    s.close()


def test_partial_first_line_of_a_running_device_is_not_bad() -> None:
    with FakeSerialSensor(rate_hz=1000.0, streaming=True) as f:
        s = SerialSensor(f.url)
        s.open()
        drain_until(s, lambda: s.frames >= 100)
        assert (s.bad, s.gaps) == (0, 0)
        s.close()


def test_unreachable_port_raises_sensor_error() -> None:
    with FakeSerialSensor() as f:
        url = f.url
    with pytest.raises(SensorError, match="cannot open"):
        SerialSensor(url).open()
