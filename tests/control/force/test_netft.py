"""ATI Net F/T RDT: golden bytes, and NetFTSensor against the fake on UDP 127.0.0.1."""

from __future__ import annotations

import math
import socket
from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.control.force import netft
from services.control.force.fake_netft import FakeNetFT
from services.control.force.netft import (
    CMD_SET_SOFTWARE_BIAS,
    CMD_START_STREAMING,
    CMD_STOP_STREAMING,
    NetFTSensor,
    RdtRecord,
    pack_record,
    pack_request,
    unpack_record,
    unpack_request,
)
from services.control.force.sensors import SensorError
from tests.conftest import wait_until
from tests.control.force.helpers import Events, drain_until


def test_golden_request_bytes() -> None:
    assert pack_request(CMD_START_STREAMING, 0) == bytes.fromhex("1234 0002 00000000")
    assert pack_request(CMD_STOP_STREAMING, 0) == bytes.fromhex("1234 0000 00000000")
    assert pack_request(CMD_SET_SOFTWARE_BIAS, 0) == bytes.fromhex("1234 0042 00000000")
    assert pack_request(CMD_START_STREAMING, 1) == bytes.fromhex("1234 0002 00000001")
    assert unpack_request(bytes.fromhex("1234 0002 0000000a")) == (2, 10)
    with pytest.raises(ValueError, match="header"):
        unpack_request(bytes.fromhex("4321 0002 00000000"))


def test_golden_record_bytes() -> None:
    data = bytes.fromhex(
        "00000007"  # rdt_sequence
        "000001f4"  # ft_sequence
        "00000000"  # status
        "000f4240"  # Fx = 1 000 000
        "fff0bdc0"  # Fy = −1 000 000
        "00000000"  # Fz
        "0007a120"  # Tx = 500 000
        "00000001"  # Ty
        "ffffffff"  # Tz = −1
    )
    rec = unpack_record(data)
    assert rec == RdtRecord(7, 500, 0, (1_000_000, -1_000_000, 0, 500_000, 1, -1))
    assert pack_record(rec) == data


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_any_datagram_is_a_record_or_a_value_error(data: bytes) -> None:
    try:
        rec = unpack_record(data)
    except ValueError:
        assert len(data) != 36
        return
    assert len(data) == 36 and pack_record(rec) == data


@pytest.fixture
def fake() -> Iterator[FakeNetFT]:
    with FakeNetFT(rate_hz=1000.0) as f:
        yield f


def test_streams_scaled_wrench(fake: FakeNetFT) -> None:
    s = NetFTSensor("127.0.0.1", fake.port)
    with pytest.raises(SensorError):
        s.read()
    s.open()
    fake.set_wrench((1.5, -2.0, 10.0), (0.1, 0.0, -0.25))
    r = drain_until(s, lambda: s.records >= 100)
    assert r is not None and r.kind == "wrench"
    assert r.values == pytest.approx((1.5, -2.0, 10.0, 0.1, 0.0, -0.25), abs=1e-6)
    assert (s.bad, s.gaps) == (0, 0)
    assert fake.requests[0] == (CMD_START_STREAMING, 0)
    s.close()
    assert wait_until(lambda: (CMD_STOP_STREAMING, 0) in fake.requests)
    assert wait_until(lambda: not fake.streaming)


def test_counts_per_unit_are_configurable() -> None:
    with FakeNetFT(counts_per_force=1_000_000.0, counts_per_torque=1000.0) as f:
        s = NetFTSensor("127.0.0.1", f.port, counts_per_force=1e6, counts_per_torque=1e3)
        s.open()
        f.set_wrench((1.0, 0, 0), (0.5, 0, 0))
        r = drain_until(s, lambda: s.records >= 20)
        assert r is not None and r.values == pytest.approx((1.0, 0, 0, 0.5, 0, 0))
        s.close()


def test_faults_are_dropped_counted_and_reported(fake: FakeNetFT) -> None:
    events = Events()
    s = NetFTSensor("127.0.0.1", fake.port, on_event=events)
    s.open()
    drain_until(s, lambda: s.records >= 50)
    fake.inject_gap(3)
    fake.inject_short(2)
    fake.inject_status(1)
    drain_until(s, lambda: s.bad >= 3 and s.gaps >= 3)
    n = s.records
    drain_until(s, lambda: s.records >= n + 200)
    assert (s.bad, s.gaps) == (3, 3)
    reasons = sorted(d["reason"] for k, _, d in events.items if k == "bad_data")
    assert reasons == ["short", "short", "status"]
    assert [d["missing"] for k, _, d in events.items if k == "gap"] == [3]
    s.close()


def test_silence_re_requests_streaming(fake: FakeNetFT, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(netft, "RESTART_AFTER_S", 0.05)
    s = NetFTSensor("127.0.0.1", fake.port)
    s.open()
    drain_until(s, lambda: s.records >= 20)
    fake.stall(0.3)
    drain_until(s, lambda: s.requests >= 2)  # the sensor went quiet: ask again
    n = s.records
    drain_until(s, lambda: s.records >= n + 50)
    assert (s.bad, s.gaps) == (0, 0)
    assert fake.requests.count((CMD_START_STREAMING, 0)) >= 2
    s.close()


def test_hardware_bias(fake: FakeNetFT) -> None:
    s = NetFTSensor("127.0.0.1", fake.port)
    s.open()
    fake.set_wrench((3.0, 0, 0), (0, 0, 0))
    drain_until(s, lambda: s.records >= 20)
    s.set_hardware_bias()
    assert wait_until(lambda: (CMD_SET_SOFTWARE_BIAS, 0) in fake.requests)
    n = s.records
    r = drain_until(s, lambda: s.records >= n + 20)
    assert r is not None and r.values == (0.0,) * 6
    s.close()


def test_sample_count_limits_the_stream() -> None:
    with FakeNetFT() as f:
        # A request for 5 records: the fake stops by itself after 5.
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as c:
            c.settimeout(5.0)
            c.connect(("127.0.0.1", f.port))
            c.send(pack_request(CMD_START_STREAMING, 5))
            recs = [unpack_record(c.recv(64)) for _ in range(5)]
        assert [r.rdt_sequence for r in recs] == [1, 2, 3, 4, 5]
        assert wait_until(lambda: not f.streaming)


def test_values_are_finite_even_at_the_extremes() -> None:
    with FakeNetFT() as f:
        s = NetFTSensor("127.0.0.1", f.port)
        s.open()
        f.set_wrench((2147.0, -2147.0, 0), (0, 0, 0))
        r = drain_until(s, lambda: s.records >= 10)
        assert r is not None and all(math.isfinite(v) for v in r.values)
        s.close()
