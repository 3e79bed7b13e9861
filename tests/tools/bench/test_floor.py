"""The bare-Zenoh floor: the same bytes and QoS as robot/force, and both processes on tiny
runs over a private Zenoh network (counts and contents, never speed)."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import pytest

from services.bus import codec, streams
from services.bus.keys import FORCE, QoS
from services.bus.messages import ForceSample
from services.tools.bench import floor, stats
from services.tools.bench.baselines import FORCE_C_NM, FORCE_F_N, FORCE_RAW, force_payload
from services.tools.bench.probes import StreamProbe
from tests.bus.test_router import spawned
from tests.conftest import BEST_EFFORT_LOSS, Net, wait_until

RUN_TIMEOUT_S = 60.0


def test_the_floor_sends_exactly_the_bytes_codec_encodes() -> None:
    for seq, t_ns in ((1, 123), (2**40, 1_700_000_000_000_000_000)):
        sample = ForceSample(seq=seq, t_ns=t_ns, f=FORCE_F_N, c=FORCE_C_NM, raw=FORCE_RAW)
        assert force_payload(seq, t_ns) == codec.encode(sample)


def test_the_floor_has_robot_force_qos() -> None:
    assert FORCE.qos is QoS.CONTROL is floor.FLOOR_TOPIC.qos
    control = streams._QOS[QoS.CONTROL]
    assert control["priority"] == floor.FLOOR_PRIORITY
    assert control["express"] is floor.FLOOR_EXPRESS
    assert control["congestion_control"] == floor.FLOOR_CONGESTION
    assert floor.FLOOR_TOPIC.type is ForceSample


def test_parse_sent() -> None:
    sent = floor.FloorSent(1000, 0.08, 1.0)
    assert floor.parse_sent("some log\n" + sent.line() + "\n") == sent
    assert sent.cpu_pct == pytest.approx(8.0)
    assert floor.FloorSent(0, 0.0, 0.0).cpu_pct == 0.0
    with pytest.raises(ValueError):
        floor.parse_sent("nothing here")


def test_publisher_process_delivers_its_samples_in_order(net: Net) -> None:
    """The floor's samples arrive in order, none twice, decoded as sent; being robot/force's
    QoS (best effort), at most BEST_EFFORT_LOSS of them lost in transit on a loaded host."""
    sub = net.node("sub")  # listens: the publisher process connects to it as a peer
    probe = StreamProbe(sub, floor.FLOOR_TOPIC, lambda m: (m.seq, m.t_ns)).start()
    done = subprocess.run(
        floor.pub_argv(net.endpoint, 200.0, 0.3, mode="peer"),
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    sent = floor.parse_sent(done.stdout)
    assert sent.sent >= 1 and sent.wall_s > 0
    least = math.ceil((1.0 - BEST_EFFORT_LOSS) * sent.sent)
    assert probe.wait_count(least, 10.0), (probe.count(), sent.sent)
    records = probe.stop()
    seqs = [r[1][0] for r in records]
    assert seqs == sorted(set(seqs)) and set(seqs) <= set(range(1, sent.sent + 1)), seqs
    assert probe.rejected == 0
    # arrival never precedes the stamp on one clock
    assert (stats.latencies_ms([r[0] for r in records], [r[1][1] for r in records]) >= 0).all()


def test_queryable_process_answers_every_get(net: Net, tmp_path: Path) -> None:
    client = net.node("client")
    reply = {"status": "ready", "counters": {"commands": 3}, "q": [0.0] * 6}
    reply_file = tmp_path / "reply.msgpack"
    reply_file.write_bytes(codec.pack(reply))
    argv = floor.serve_argv(net.endpoint, reply_file, mode="peer")
    with spawned(argv, merge_stderr=False) as server:
        got = floor.time_gets(client.session, 5, startup_s=RUN_TIMEOUT_S)
        assert len(got.ms) == 5 and got.failures == 0
        assert all(x > 0 for x in got.ms)
        server.proc.terminate()  # SIGTERM: the server leaves through its own close
        assert server.wait(RUN_TIMEOUT_S) == 0, server.errors
        out = "\n".join(server.rest(RUN_TIMEOUT_S))
        assert f"{floor.SERVING} {floor.FLOOR_RPC_KEY}" in out


def test_time_gets_gives_up_when_nobody_serves(net: Net) -> None:
    client = net.node("client")
    with pytest.raises(TimeoutError, match="no reply"):
        floor.time_gets(client.session, 1, timeout_s=0.1, startup_s=0.3)


def test_relay_process_puts_every_sample_on_again_untouched(net: Net) -> None:
    bench = net.node("bench")  # listens: the relay process connects to it as a peer
    probe = StreamProbe(bench, floor.FLOOR_RELAY_OUT, lambda m: (m.seq, m.t_ns)).start()
    pub = floor.declare_floor_publisher(bench.session, floor.FLOOR_RELAY_IN.key)
    argv = floor.relay_argv(net.endpoint, mode="peer", take=("robot/force", "robot/state"))
    try:
        with spawned(argv, merge_stderr=False) as relay:
            # route set-up: put seq 1 until it comes back, then 2…50 once each, then the
            # tail (51, 52, …) until one comes back: best effort, any may be lost on a busy
            # host, and the check below is of order and bytes, with BEST_EFFORT_LOSS
            assert wait_until(lambda: pub.put(force_payload(1, 11)) or probe.count() > 0, 30.0)
            for seq in range(2, 51):
                pub.put(force_payload(seq, seq * 11))
            tail = iter(range(51, 10_000))

            def back() -> bool:
                newest = probe.newest()
                if newest is not None and newest[1][0] >= 50:
                    return True
                seq = next(tail)
                pub.put(force_payload(seq, seq * 11))
                return False

            assert wait_until(back, 30.0), probe.newest()
            relay.proc.terminate()  # SIGTERM: the relay leaves through its own close
            code = relay.wait(RUN_TIMEOUT_S)
            out = "\n".join(relay.rest(RUN_TIMEOUT_S))
    finally:
        pub.undeclare()
    records = probe.stop()
    seqs = [r[1][0] for r in records]
    assert code == 0, relay.errors
    assert floor.RELAYING in out
    after = [r[1] for r in records if r[1][0] >= 2]
    assert set(seqs) - {r[0] for r in after} == {1}  # the set-up's seq 1, put until back
    assert [s for s, _ in after] == sorted({s for s, _ in after}), seqs  # in order, once
    assert all(t == s * 11 for s, t in after)  # bytes untouched
    assert len([s for s, _ in after if s <= 50]) >= (1.0 - BEST_EFFORT_LOSS) * 49, seqs
    # set-up puts the relay got before the way back existed were relayed to nobody
    assert int(out.split("relayed ")[-1]) >= len(records)
    assert probe.rejected == 0


def test_relay_argv_takes_each_key() -> None:
    argv = floor.relay_argv("tcp/127.0.0.1:7447", take=("robot/force", "robot/state"))
    assert argv[argv.index("relay") :] == [
        "relay", "--connect", "tcp/127.0.0.1:7447", "--mode", "client",
        "--take", "robot/force", "--take", "robot/state",
    ]  # fmt: skip
