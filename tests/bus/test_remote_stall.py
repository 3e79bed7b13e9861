"""A stalled link to another machine never blocks the control class's publisher
(`NodeConfig.loopback`, `control_qos_rules`).

Found over the passivity link bench: `robot/force` is sent blocking on congestion, and while
the TCP link to the remote master stalled (a retransmission at 700 ms round trip) the force
service's `put` blocked 160–480 ms, so the decision on the same host read no force either.

Here the remote reader is a session whose subscriber callback is wedged: Zenoh's reader for
that link stops, the socket fills, then the publisher's queue. A reader in the publisher's
own session stands for the robot host's decision. With the link counted as leaving the host
(`loopback=()`), the publisher sends on and the local reader gets every sample; with it
counted as loopback (the default on `lo`), the publisher blocks, and the wedged reader, once
released, gets every sample: the rules change nothing on the robot host itself.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
import zenoh

from services.bus.config import NodeConfig, control_qos_rules
from services.bus.keys import QoS
from services.bus.streams import _QOS
from tests.conftest import free_port, wait_until

pytestmark = pytest.mark.timeout(120)

KEY = "robot/force"
PAYLOAD = bytes(4096)
#: 20 MB: far more than a loopback socket's buffers and Zenoh's queue hold
COUNT = 5000


@dataclass
class Counter:
    n: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self) -> None:
        with self.lock:
            self.n += 1

    def get(self) -> int:
        with self.lock:
            return self.n


@dataclass
class Rig:
    """A publisher session with a local reader, a remote session with a wedged reader."""

    pub: zenoh.Session
    remote: zenoh.Session
    local: Counter
    far: Counter
    wedge: threading.Event
    sent: Counter
    thread: threading.Thread


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    loopback: tuple[str, ...] = request.param
    port = free_port()
    pub = zenoh.open(NodeConfig(listen=(f"tcp/127.0.0.1:{port}",), loopback=loopback).to_zenoh())
    remote = zenoh.open(NodeConfig(connect=(f"tcp/127.0.0.1:{port}",)).to_zenoh())
    local, far, sent = Counter(), Counter(), Counter()
    wedge = threading.Event()

    def wedged(s: zenoh.Sample) -> None:
        if len(s.payload) == len(PAYLOAD):  # not a warm-up sample
            wedge.wait(30.0)
            far.add()

    def near(s: zenoh.Sample) -> None:
        if len(s.payload) == len(PAYLOAD):
            local.add()

    subs = [
        pub.declare_subscriber(KEY, near),
        remote.declare_subscriber(KEY, wedged),
    ]
    publisher = pub.declare_publisher(KEY, **_QOS[QoS.CONTROL])

    def send() -> None:
        for _ in range(COUNT):
            publisher.put(PAYLOAD)
            sent.add()

    thread = threading.Thread(target=send, daemon=True)
    r = Rig(pub, remote, local, far, wedge, sent, thread)
    try:
        # The remote subscriber must be known to the publisher before anything is sent:
        # empty warm-up samples, never counted, until one arrives.
        seen = threading.Event()
        warm = remote.declare_subscriber(KEY, lambda _s: seen.set())
        assert wait_until(
            lambda: publisher.put(b"") or seen.is_set(), 10.0, poll_s=0.05, what="connected"
        )
        warm.undeclare()
        yield r
    finally:
        wedge.set()
        if thread.is_alive():
            thread.join(30.0)
        for s in subs:
            s.undeclare()
        publisher.undeclare()
        remote.close()
        pub.close()


def test_the_rules_drop_off_host_and_block_on_loopback() -> None:
    cfg = NodeConfig(loopback=("lo",)).to_zenoh()
    rules = json.loads(cfg.get_json("qos/network"))
    assert [r["id"] for r in rules] == ["control-drops-off-host", "control-blocks-on-loopback"]
    assert rules[0]["interfaces"] is None and rules[0]["flows"] == ["egress"]
    assert (rules[0]["qos"]["priority"], rules[0]["overwrite"]["congestion_control"]) == (
        "real_time",
        "drop",
    )
    assert rules[1]["interfaces"] == ["lo"]
    assert rules[1]["overwrite"]["congestion_control"] == "block"
    assert json.loads(NodeConfig(loopback=()).to_zenoh().get_json("qos/network")) == []
    assert control_qos_rules(["lo"])[1]["interfaces"] == ["lo"]


@pytest.mark.parametrize("rig", [()], indirect=True)
def test_a_wedged_remote_reader_never_blocks_the_publisher(rig: Rig) -> None:
    rig.thread.start()
    assert wait_until(lambda: rig.sent.get() == COUNT, 60.0, what="every put returned")
    # The reader on the publisher's host got every sample while the far one was wedged.
    assert wait_until(lambda: rig.local.get() == COUNT, 30.0, what="the local reader got all")
    rig.wedge.set()
    assert wait_until(lambda: rig.far.get() >= 1, 10.0)
    # The far reader got what its queue held and no more: the rest were dropped for it.
    assert rig.far.get() < COUNT


@pytest.mark.parametrize("rig", [("lo", "lo0")], indirect=True)
def test_on_loopback_the_control_class_still_blocks_and_loses_nothing(rig: Rig) -> None:
    rig.thread.start()
    last = {"n": -1, "since": 0.0}

    def stuck() -> bool:
        n, now = rig.sent.get(), time.monotonic()
        if n != last["n"]:
            last["n"], last["since"] = n, now
            return False
        return n < COUNT and now - last["since"] > 0.5

    assert wait_until(stuck, 30.0, poll_s=0.02, what="the publisher blocked by the far reader")
    assert rig.sent.get() < COUNT
    rig.wedge.set()
    assert wait_until(lambda: rig.far.get() == COUNT, 60.0, what="the far reader got all")
    assert rig.sent.get() == rig.local.get() == COUNT
