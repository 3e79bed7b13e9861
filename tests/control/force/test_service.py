"""The force service over Zenoh: 1 kHz in order, live period/priority changes."""

from __future__ import annotations

import itertools
import threading

import pytest

from services.bus import keys
from services.bus.errors import RpcError
from services.bus.messages import Event, ForceSample
from services.control.arm.puma560 import DEFAULT_eMt, Puma560, qn
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from tests.conftest import BEST_EFFORT_LOSS, Net, ready_state, wait_until

# A 1 kHz stream over Zenoh, checked for gaps: run alone in `make pytest`'s second pass.
pytestmark = [pytest.mark.system, pytest.mark.alone]


def _publish_pose(node, svc: ForceService) -> None:  # type: ignore[no-untyped-def]
    """Put the arm's pose until the service has sampled (as the arm does, at ≥ 100 Hz): one
    put could go out before the service's subscription reached this peer, and the simulated
    sensor gives nothing without a pose (fresh-clone CI, twice: 0 samples in 30 s)."""
    pub = node.publisher(keys.STATE)
    assert wait_until(
        lambda: svc.core.latest is not None or _put_pose(pub), 10.0, what="a first sample"
    )


def _put_pose(pub) -> bool:  # type: ignore[no-untyped-def]
    kin = Puma560()
    oMt, oMe = kin.fk_tool(qn, DEFAULT_eMt), kin.fk_flange(qn)
    pub.put(ready_state(1, 1, qn, oMt, oMe))
    return False  # put, not yet sampled: wait_until polls again


def test_streams_2000_samples_in_order(net) -> None:
    force_node = net.node("force")
    viewer = net.node("viewer")
    seqs: list[int] = []
    lock = threading.Lock()
    enough = threading.Event()

    def on_sample(s: ForceSample) -> None:
        with lock:
            seqs.append(s.seq)
            if len(seqs) >= 2100:
                enough.set()

    viewer.subscribe(keys.FORCE, on_sample)
    svc = ForceService(force_node, ForceConfig())
    try:
        _publish_pose(viewer, svc)
        if not enough.wait(30.0):
            st = viewer.call("force", "sensor_status", {}, timeout_s=5.0)
            said = {k: st.get(k) for k in ("running", "samples", "publishing", "unsent", "idle")}
            pytest.fail(f"only {len(seqs)} samples arrived; the service says {said}")
        status = viewer.call("force", "sensor_status", {}, timeout_s=5.0)
    finally:
        svc.close()
    with lock:
        window = seqs[50:2050]  # skip the first samples, published while the link settled
    # robot/force is best effort (PROTOCOL §3, keys.FORCE): a sample lost in transit is one
    # millisecond of a continuous signal, and on a starved 2-core CI host a few are (59
    # gaps in 2000 once, in the `alone` pass; 142 on this VM with its host stealing half
    # the CPU, 2026-12-02; none on a quiet one). What the service owes: every sample in
    # order, none twice, and its own count with no hole; the rate and the loss of a quiet
    # machine are `telerobot bench`'s (docs/bench.md).
    assert len(window) == 2000
    steps = [b - a for a, b in itertools.pairwise(window)]
    assert min(steps) >= 1, "a sample arrived twice or out of order"
    lost = sum(steps) - len(steps)
    assert lost <= BEST_EFFORT_LOSS * len(window), f"{lost} of {sum(steps) + 1} samples lost"
    assert status["running"] is True
    assert status["period_ms"] == 1.0
    assert status["samples"] >= 2000
    assert status["rate_hz"] > 0


def test_period_and_priority_changes_are_applied_and_reported(net) -> None:
    force_node = net.node("force")
    client = net.node("client")
    svc = ForceService(force_node, ForceConfig())
    try:
        _publish_pose(client, svc)
        st = client.call(
            "force", "sensor_config", {"period_ms": 2.0, "priority": "below_normal"}, timeout_s=5.0
        )
        assert st["period_ms"] == 2.0
        assert st["priority"] == "below_normal"
        assert st["priority_applied"]["applied"] == "below_normal"
        st = client.call("force", "sensor_status", {}, timeout_s=5.0)
        assert st["period_ms"] == 2.0 and st["priority"] == "below_normal"
        with pytest.raises(RpcError) as err:
            client.call("force", "sensor_config", {"priority": "ludicrous"}, timeout_s=5.0)
        assert err.value.code == "bad_request"
        stopped = client.call("force", "sensor_stop", {}, timeout_s=5.0)
        assert stopped["running"] is False
        started = client.call("force", "sensor_start", {}, timeout_s=5.0)
        assert started["running"] is True
    finally:
        svc.close()


def test_nothing_is_sent_while_nobody_subscribes_and_a_subscriber_gets_it_at_once(
    net: Net,
) -> None:
    """The sensor samples all along; robot/force is put only while someone subscribes
    (Zenoh's matching status), so an idle system neither sends nor routes 1 kHz of force.
    A subscriber is fed at once, at the full rate, with `seq` counting what was not sent;
    meanwhile the simulated sensor is sampled every IDLE_PERIOD_MS, not every period."""
    svc = ForceService(net.node("force"), ForceConfig())
    client = net.node("client")
    try:
        _publish_pose(client, svc)
        assert wait_until(
            lambda: client.call("force", "sensor_status", {}, timeout_s=5.0)["unsent"] >= 50
        )
        st = client.call("force", "sensor_status", {}, timeout_s=5.0)
        assert st["publishing"] is False and st["running"] is True and st["idle"] is True
        assert st["period_ms"] == 1.0  # the configured period, kept for when it is used
        assert svc._pub.sent == 0
        assert svc.core.sampler.slow  # sampled every IDLE_PERIOD_MS (test_sampler: the rate)
        got: list[int] = []
        client.subscribe(keys.FORCE, lambda s: got.append(s.seq))
        assert wait_until(lambda: len(got) >= 100)
        st = client.call("force", "sensor_status", {}, timeout_s=5.0)
        assert st["publishing"] is True and st["idle"] is False
        assert got[0] > 50  # the samples taken before were counted, not sent
        assert got == sorted(got)
        client.close()  # the only subscriber leaves
        assert wait_until(lambda: not svc._watched)
        sent = svc._pub.sent
        unsent = svc.unsent
        assert wait_until(lambda: svc.unsent >= unsent + 20)
        assert svc._pub.sent == sent and svc.core.idle
    finally:
        svc.close()


def test_a_net_ft_that_never_answers_is_said_in_an_event_and_the_log(
    net, caplog: pytest.LogCaptureFixture
) -> None:
    """A Net F/T box at an address where nothing answers (a loopback port with no fake
    behind it): `sensing … publishing` and then nothing, before. Now a `stale` event that
    says the sensor has sent nothing, and a warning in the log, within a second."""
    import logging

    from tests.conftest import free_port

    viewer = net.node("viewer")
    events: list[Event] = []
    lock = threading.Lock()

    def on_event(ev: Event) -> None:
        with lock:
            events.append(ev)

    viewer.subscribe(keys.EVENTS, on_event)
    cfg = ForceConfig(sensor="netft", host="127.0.0.1", netft_port=free_port())
    with caplog.at_level(logging.WARNING, logger="telerobot.force"):
        svc = ForceService(net.node("force"), cfg)
        try:

            def said() -> bool:
                with lock:
                    return any(
                        e.kind == "stale" and "has sent nothing" in e.message for e in events
                    )

            assert wait_until(said, 10.0), [(e.kind, e.message) for e in events]
            assert svc.node.call("force", "status", {}, 5.0)["stale"] is True
        finally:
            svc.close()
    assert any("has sent nothing" in r.getMessage() for r in caplog.records)
