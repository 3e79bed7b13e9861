"""Typed streams on a Zenoh session: publishers, subscriptions, and the newest sample of a
fast stream decoded only when read (`Latest`). `Node` (node.py) declares them; the rules
they keep are its (ZENOH_NOTES.md): callbacks decode and store or hand over, payloads above
a topic's `max_bytes` are refused before decoding, latest-wins keeps the highest `seq`.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import zenoh

from services.bus import codec
from services.bus.errors import ProtocolError
from services.bus.keys import ENCODING, Delivery, QoS, Topic
from services.bus.messages import Message

if TYPE_CHECKING:
    from services.bus.node import Node

M = TypeVar("M", bound=Message)

RESTART_GAP_NS = 250_000_000

ZENOH_ENCODING = zenoh.Encoding(ENCODING)
_QOS: dict[QoS, dict[str, Any]] = {
    QoS.CONTROL: {
        "priority": zenoh.Priority.REAL_TIME,
        "express": True,
        # Block, as keys.QoS.CONTROL and PROTOCOL.md §3 say: with DROP a loaded 2-core host
        # lost up to half of a 300-sample burst on loopback; only video may drop.
        "congestion_control": zenoh.CongestionControl.BLOCK,
    },
    QoS.STATE: {
        "priority": zenoh.Priority.INTERACTIVE_HIGH,
        "express": False,
        "congestion_control": zenoh.CongestionControl.DROP,
    },
    QoS.BULK: {
        "priority": zenoh.Priority.DATA_LOW,
        "express": False,
        "congestion_control": zenoh.CongestionControl.DROP,
    },
    QoS.RELIABLE: {
        "priority": zenoh.Priority.DATA,
        "express": False,
        "congestion_control": zenoh.CongestionControl.BLOCK,
    },
}


_RELIABILITY: dict[Delivery, zenoh.Reliability] = {
    Delivery.BEST_EFFORT: zenoh.Reliability.BEST_EFFORT,
    Delivery.RELIABLE: zenoh.Reliability.RELIABLE,
}


def publisher_qos(topic: Topic[Any]) -> dict[str, Any]:
    """The Zenoh publisher options of a topic: its class's priority, express and congestion
    control, and its own reliability (keys.py says why per key)."""
    return {**_QOS[topic.qos], "reliability": _RELIABILITY[topic.delivery]}


class Publisher(Generic[M]):
    """A typed publisher: `put(msg)` validates, encodes and sends with the topic's QoS.

    `cache` > 0: a Zenoh advanced publisher keeping the last `cache` samples, which a late
    subscriber with `history` (`Node.subscribe(…, history=True)`) is handed when it comes;
    the session must stamp its samples (NodeConfig.timestamping)."""

    def __init__(self, session: zenoh.Session, topic: Topic[M], cache: int = 0) -> None:
        self.topic = topic
        qos = publisher_qos(topic)
        if cache > 0:
            self._pub: Any = zenoh.ext.declare_advanced_publisher(
                session,
                topic.key,
                encoding=ZENOH_ENCODING,
                cache=zenoh.ext.CacheConfig(cache),
                publisher_detection=True,
                **qos,
            )
        else:
            self._pub = session.declare_publisher(topic.key, encoding=ZENOH_ENCODING, **qos)
        self.sent = 0

    def put(self, msg: M) -> None:
        self._pub.put(codec.encode(msg))
        self.sent += 1

    def put_bytes(self, payload: bytes, attachment: bytes | None = None) -> None:
        """Send an already-encoded payload (replay, fuzzing), with a Zenoh attachment when
        given (the replayer marks what it sends: `replay`)."""
        if attachment is None:
            self._pub.put(payload)
        else:
            self._pub.put(payload, attachment=attachment)
        self.sent += 1

    def undeclare(self) -> None:
        self._pub.undeclare()


def wait_latest(
    cond: threading.Condition,
    latest: Callable[[], M | None],
    pred: Callable[[M], bool],
    timeout_s: float,
) -> M | None:
    """Block until `latest()` is a message satisfying `pred`, or `timeout_s` has passed; the
    message (or None). Whoever stores a new latest notifies `cond`."""
    deadline = time.monotonic() + timeout_s
    with cond:
        while True:
            m = latest()
            if m is not None and pred(m):
                return m
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            cond.wait(left)


@dataclass
class Subscription(Generic[M]):
    """A typed subscription. `latest` holds the newest valid message (highest `seq`)."""

    topic: Topic[M]
    latest: M | None = None
    received: int = 0
    rejected: int = 0
    last_error: str | None = None
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _sub: Any = None

    def get(self) -> M | None:
        return self.latest

    def wait_for(self, pred: Callable[[M], bool], timeout_s: float) -> M | None:
        """Block until the newest message satisfies `pred` (or the deadline); returns it."""
        return wait_latest(self._cond, lambda: self.latest, pred, timeout_s)

    def wait_count(self, n: int, timeout_s: float) -> bool:
        """Block until `received` ≥ n or the deadline."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self.received < n:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True


class Latest(Generic[M]):
    """The newest message of a fast stream, kept by Zenoh and decoded only when read.

    Zenoh holds the newest sample in a ring of one: no Python runs per sample (a Python
    callback costs ~9 % of a core at 1 kHz), so a service that needs `robot/force` only
    when it acts pays only then. `read()` returns the newest valid message and its arrival
    time on the monotonic clock. A sample `read()` finds arrived after the previous read
    (reading empties the ring) and was sent at its `t_ns`; its arrival is taken as the
    later of the two, so a stream that flows is fresh as often as it is read, and an old
    sample found after a long pause is as old as its `t_ns` says. Bad payloads are counted
    and reported when read. Not thread-safe: one reader.

    `watch(False)` drops the subscription (Zenoh receives nothing, the router forwards
    nothing, a publisher following its matching status stops sending); `read()` then keeps
    returning the last message, ageing. `watch(True)` subscribes again. Call it from the
    reader's thread (or under the reader's lock).

    `each`: a reader that must see every message, not only the newest (a field only some
    messages carry: the passivity ports' echoes), gets a ring of `depth` instead of one;
    `read()` then decodes every message queued since the previous read and hands each valid
    one to `each` in arrival order (at most `depth` of them: older ones are Zenoh's to drop),
    on the reader's thread, before returning the newest.
    """

    def __init__(
        self,
        node: Node,
        topic: Topic[M],
        watch: bool = True,
        each: Callable[[M], None] | None = None,
        depth: int = 64,
    ) -> None:
        self.topic = topic
        self._node = node
        self._each = each
        self._depth = depth if each is not None else 1
        self._sub: Any = None
        if watch:
            self.watch(True)
        self._msg: M | None = None
        self._rx_ns = 0
        self._read_ns = 0
        self.received = 0
        self.rejected = 0

    @property
    def watching(self) -> bool:
        return self._sub is not None

    def watch(self, on: bool) -> None:
        """Subscribe (on) or drop the subscription (off); no-op if already so."""
        if on and self._sub is None:
            self._sub = self._node.session.declare_subscriber(
                self.topic.key, zenoh.handlers.RingChannel(self._depth)
            )
        elif not on and self._sub is not None:
            sub, self._sub = self._sub, None
            with contextlib.suppress(zenoh.ZError):  # the session is closing
                sub.undeclare()

    def read(self) -> tuple[M, int] | None:
        """(newest message, its arrival on time.monotonic_ns()) or None if none yet."""
        sub = self._sub
        samples = []
        try:
            while sub is not None:
                sample = sub.try_recv()
                if sample is None:
                    break
                samples.append(sample)
                if self._each is None:
                    break  # a ring of one
        except zenoh.ZError:  # the session is closing
            pass
        now_mono = time.monotonic_ns()
        previous, self._read_ns = self._read_ns, now_mono
        now_wall = time.time_ns() if samples else 0
        for sample in samples:
            try:
                msg = codec.decode(
                    self.topic.type, payload_bytes(sample.payload, self.topic.max_bytes)
                )
            except ProtocolError as e:
                self.rejected += 1
                self._node.report_rejected(str(sample.key_expr), str(e))
                continue
            self.received += 1
            if self._each is not None:
                self._each(msg)
            if newer(msg, self._msg):
                age_ns = min(max(now_wall - int(getattr(msg, "t_ns", now_wall)), 0), 10**12)
                self._msg, self._rx_ns = msg, max(previous, now_mono - age_ns)
        return None if self._msg is None else (self._msg, self._rx_ns)


def payload_bytes(payload: zenoh.ZBytes, max_bytes: int) -> bytes:
    """The payload's bytes, or ProtocolError when it is larger than `max_bytes` (it is not
    even copied out of Zenoh then)."""
    n = len(payload)
    if n > max_bytes:
        raise ProtocolError("payload", f"{n} bytes is more than the {max_bytes} allowed")
    return payload.to_bytes()


def newer(msg: Message, newest: Message | None) -> bool:
    """Latest-wins: a higher `seq` replaces; so does a lower one sent well after the newest,
    which is a restarted publisher counting from 1 again, not a stale sample."""
    if newest is None:
        return True
    seq, t_ns = getattr(msg, "seq", 0), getattr(msg, "t_ns", 0)
    return bool(
        seq > getattr(newest, "seq", 0) or t_ns - getattr(newest, "t_ns", 0) > RESTART_GAP_NS
    )
