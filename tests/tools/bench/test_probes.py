"""The bench's command driver and hold detection over a private Zenoh network."""

from __future__ import annotations

import threading
import time

import pytest

from services.bus.errors import RpcError
from services.bus.keys import CMD, FORCE
from services.bus.messages import IDENTITY_R, ForceSample, OperatorCommand
from services.bus.node import Node
from services.tools.bench.commands import HoldWatch
from services.tools.bench.probes import CommandDriver, StreamProbe, time_calls
from tests.conftest import Net, wait_until


def test_stream_encodes_k_per_engagement_and_engages_again_when_held(net: Net) -> None:
    listener = net.node("listener")
    bench = net.node("master", instance="bench")
    got: list[OperatorCommand] = []
    lock = threading.Lock()

    def on_cmd(m: OperatorCommand) -> None:
        with lock:
            got.append(m)

    listener.subscribe(CMD, on_cmd)
    _warm_up_cmd(bench, got, lock)
    driver = CommandDriver(bench, "bench")
    calls = {"n": 0}

    def held(started_ns: int) -> bool:
        calls["n"] += 1
        return calls["n"] == 10  # the decision "held" once, at the 10th command

    step = 1e-6
    run = driver.stream(200.0, 0.5, step, held=held, release=3)
    n = len(run.sent)
    assert n >= 11, f"only {n} commands in 0.5 s"
    assert [k for k, _ in run.sent] == list(range(n))
    assert [k0 for _, k0 in run.starts] == [0, 10]

    def bench_msgs() -> int:
        with lock:
            return sum(m.master == "bench" for m in got)

    assert wait_until(lambda: bench_msgs() >= n + 3, 5.0)
    with lock:
        msgs = [m for m in got if m.master == "bench"]
    assert len(msgs) == n + 3
    active = [m for m in msgs if m.active]
    assert len(active) == n
    assert [m.seq for m in msgs] == sorted(m.seq for m in msgs)
    engages = sorted({m.engage for m in active})
    assert len(engages) == 2 and engages[1] == engages[0] + 1
    for k, m in enumerate(active):
        k0 = 0 if k < 10 else 10
        assert m.dp[0] == pytest.approx((k - k0) * step, abs=1e-15)
        assert m.master == "bench" and m.frame == "world"
    assert [m.active for m in msgs[-3:]] == [False] * 3
    assert all(m.engage == engages[1] for m in msgs[-3:])
    assert [m.t_ns for m in active] == [t for _, t in run.sent]


def _warm_up_cmd(node: Node, got: list[OperatorCommand], lock: threading.Lock) -> None:
    """Publish from another master until the listener hears one: the route is up."""
    pub = node.publisher(CMD)
    deadline = time.monotonic() + 5.0
    seq = 0
    while time.monotonic() < deadline:
        seq += 1
        pub.put(
            OperatorCommand(
                seq=seq,
                t_ns=time.time_ns(),
                master="warmup",
                engage=1,
                active=False,
                frame="world",
                dp=(0.0, 0.0, 0.0),
                dR=IDENTITY_R,
            )
        )
        with lock:
            if got:
                return
        time.sleep(0.02)
    raise AssertionError("no route for robot/cmd")


def _rec(rx: int, active: bool, engage: int, master: str = "decision") -> tuple[int, tuple]:
    return (rx, (1, master, active, 0.0, engage, None))


def test_hold_watch() -> None:
    newest: list[tuple[int, tuple] | None] = [None]
    watch = HoldWatch(lambda: newest[0], refused_after_s=3600.0)
    start = time.time_ns()
    assert not watch(start)  # nothing yet, not waited long
    newest[0] = _rec(start - 1, False, 4)  # an old hold, from before this engagement
    assert not watch(start)
    newest[0] = _rec(start + 1, False, 4)  # the previous engagement still held: not ours
    assert not watch(start)
    newest[0] = _rec(start + 2, True, 5)  # the decision follows us with engage 5
    assert not watch(start)
    newest[0] = _rec(start + 3, True, 5, master="other")
    assert not watch(start)
    newest[0] = _rec(start + 4, False, 5)  # and now holds engage 5
    assert watch(start)
    # a new engagement forgets the old one
    assert not watch(start + 10)
    impatient = HoldWatch(lambda: None, refused_after_s=0.0)
    assert impatient(time.time_ns() - 1_000)  # never followed: refused


def test_stream_probe_records_and_counts_rejections(net: Net) -> None:
    sub = net.node("sub")
    pub_node = net.node("pub")
    probe = StreamProbe(sub, FORCE, lambda m: (m.seq, m.t_ns)).start()
    pub = pub_node.publisher(FORCE)
    zero = (0.0, 0.0, 0.0)
    deadline = time.monotonic() + 5.0
    while probe.count() == 0 and time.monotonic() < deadline:  # warm up the route with seq 0
        pub.put(ForceSample(seq=0, t_ns=1000, f=zero, c=zero))
        time.sleep(0.02)
    assert wait_until(lambda: probe.count() > 0, 5.0)  # seq 0s still in flight may follow
    # robot/force is best effort: a burst of 20 lost some on a loaded host (make test,
    # 2026-12-02). The probe is under test, not the bus: each sample is sent once the one
    # before it is in, and sent again only if it never came.
    for i in range(1, 21):
        sample = ForceSample(seq=i, t_ns=1000 + i, f=zero, c=zero)
        for _ in range(5):
            pub.put(sample)
            if wait_until(lambda i=i: _has_seq(probe, i), 1.0):  # type: ignore[misc]
                break
    pub.put_bytes(b"\x93not a map")
    assert wait_until(lambda: probe.rejected >= 1, 5.0)
    records = [r for r in probe.stop() if r[1][0] > 0]
    assert [r[1] for r in records] == [(i, 1000 + i) for i in range(1, 21)]
    assert probe.rejected == 1
    assert all(r[0] > 1000 for r in records)


def _has_seq(probe: StreamProbe[ForceSample], seq: int) -> bool:
    """Whether the probe holds a record of the sample `seq` (late seq 0s may follow it)."""
    return any(values[0] == seq for _, values in probe.snapshot())


def test_time_calls_times_answers_and_counts_failures(net: Net) -> None:
    server = net.node("svc")
    client = net.node("client")
    n_calls = {"ok": 0, "busy": 0}

    def ok(args: dict[str, object]) -> dict[str, object]:
        n_calls["ok"] += 1
        return {"ok": True}

    def busy(args: dict[str, object]) -> dict[str, object]:
        n_calls["busy"] += 1
        raise RpcError("busy", "try later")

    server.serve("svc", {"ok": ok, "busy": busy})
    server.announce()
    good = time_calls(client, "svc", "ok", 5)
    assert len(good.ms) == 5 and good.failures == {}
    assert n_calls["ok"] == 6  # one warm-up call, not timed
    assert all(x > 0 for x in good.ms)
    bad = time_calls(client, "svc", "busy", 3)
    assert bad.ms == [] and bad.failures == {"busy": 3}
