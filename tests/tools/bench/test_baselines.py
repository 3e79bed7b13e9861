"""The baselines' code on tiny runs: counts and contents, never speed."""

from __future__ import annotations

from services.bus import codec
from services.bus.messages import ForceSample
from services.tools.bench import stats
from services.tools.bench.baselines import force_payload, tcp_floor, xmlrpc_round_trips, xmlrpc_safe


def test_force_payload_is_a_valid_force_sample() -> None:
    msg = codec.decode(ForceSample, force_payload(7, 123))
    assert (msg.seq, msg.t_ns) == (7, 123)
    assert msg.raw is not None and len(msg.raw) == 6


def test_tcp_floor_delivers_every_packet_in_order() -> None:
    run = tcp_floor(rate_hz=200.0, duration_s=0.3)
    assert run.sent >= 1
    assert len(run.seq) == run.sent == run.rx_ns.size == run.t_ns.size
    assert run.seq == list(range(1, run.sent + 1))
    loss = stats.seq_loss(run.seq)
    assert (loss.lost, loss.duplicates, loss.reordered) == (0, 0, 0)
    assert run.payload_bytes == len(force_payload(run.seq[-1], int(run.t_ns[-1])))
    # arrival never precedes the stamp on one clock
    assert (stats.latencies_ms(run.rx_ns, run.t_ns) >= 0).all()


def test_xmlrpc_round_trips_return_the_reply_every_time() -> None:
    reply = {"status": "ready", "q": [0.1, 0.2], "cmd_t_ns": 1_700_000_000_000_000_000, "e": None}
    rtt = xmlrpc_round_trips(reply, 12)
    assert len(rtt) == 12
    assert all(x > 0 for x in rtt)


def test_xmlrpc_safe_keeps_what_xmlrpc_carries() -> None:
    got = xmlrpc_safe({"a": 2**40, 3: [1, -(2**31), True, None, (1.5, "x")], "b": b"z"})
    assert got == {"a": float(2**40), "3": [1, -(2**31), True, None, [1.5, "x"]], "b": "b'z'"}
