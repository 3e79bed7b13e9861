"""A ROS 2 node in the rmw_zenoh graph, on a plain Zenoh session: tokens, publishers, subscriptions.

`RosNode` declares the node's liveliness token, then one token per publisher (`MP`) and
subscription (`MS`), so `ros2 node list`, `ros2 topic list -v` and `ros2 topic info -v` see
them (rmw.py has the formats). A publisher puts CDR bytes with the attachment every rmw_zenoh
subscriber requires (it drops samples without one). TRANSIENT_LOCAL is what rmw_zenoh does
(docs/design.md "Publishers", rmw_publisher_data.cpp): an advanced publisher with a cache of
`depth` samples, publisher detection (so a late advanced subscriber finds it and queries the
cache) and, when RELIABLE, sporadic heartbeats every 500 ms for sample-miss detection.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

from services.frontends.ros2 import rmw
from services.frontends.rosmsg.defs import TypeDef

log = logging.getLogger("telerobot.ros2")

HEARTBEAT_S = 0.5
"""rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (500 ms, sporadic)."""


class RosPublisher:
    """One topic publisher. `put(cdr)` is thread-safe, and a no-op once undeclared (a late
    callback's put must not race the undeclaration); `matching` says whether anyone
    listens."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        token: str,
        qos: rmw.Qos,
        priority: zenoh.Priority,
        express: bool,
    ) -> None:
        self.key = key
        self.token_key = token
        self.qos = qos
        self.gid = rmw.gid_of(token)
        self._lock = threading.Lock()
        self._put_lock = threading.Lock()
        """Held by a put and by undeclare: Zenoh's handle is not to be used by both at once."""
        self._closed = False
        self._seq = 0
        self.sent = 0
        reliability = (
            zenoh.Reliability.RELIABLE
            if qos.reliability == rmw.Reliability.RELIABLE
            else zenoh.Reliability.BEST_EFFORT
        )
        self._listener: Any = None
        self._on_matching: list[Callable[[bool], None]] = []
        self._matching = False
        if qos.durability == rmw.Durability.TRANSIENT_LOCAL:
            heartbeat = (
                zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S)
                if qos.reliability == rmw.Reliability.RELIABLE
                else None
            )
            self._pub: Any = zenoh.ext.declare_advanced_publisher(
                session,
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=priority,
                express=express,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(qos.depth),
                sample_miss_detection=heartbeat,
                publisher_detection=True,
            )
            self._advanced = True
        else:
            self._pub = session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=priority,
                express=express,
                reliability=reliability,
            )
            self._advanced = False
            self._listener = self._pub.declare_matching_listener(self._matching_changed)
            # A subscriber already there when we declare: start from the current status.
            with self._lock:
                self._matching = self._matching or bool(self._pub.matching_status.matching)
        self._token = session.liveliness().declare_token(token)

    def _matching_changed(self, status: Any) -> None:
        with self._lock:
            self._matching = bool(status.matching)
            callbacks = list(self._on_matching)
            matching = self._matching
        for cb in callbacks:
            try:
                cb(matching)
            except Exception:  # a listener's bug must not kill Zenoh's callback thread
                log.exception("matching listener of %s failed", self.key)

    @property
    def matching(self) -> bool:
        """True while a subscriber matches (always True for a cached, transient-local one)."""
        if self._advanced:
            return True
        with self._lock:
            return self._matching

    def on_matching(self, cb: Callable[[bool], None]) -> None:
        """Call `cb(matching)` now and on every change (from Zenoh's thread: keep it short)."""
        with self._lock:
            self._on_matching.append(cb)
            now = self._matching if not self._advanced else True
        cb(now)

    def put(self, cdr: bytes, t_ns: int | None = None) -> None:
        """Publish one serialized message; the attachment carries `t_ns` (default: now)."""
        stamp = time.time_ns() if t_ns is None else t_ns
        with self._put_lock:
            if self._closed:
                return
            with self._lock:
                self._seq += 1
                seq = self._seq
            self._pub.put(cdr, attachment=rmw.attachment(seq, stamp, self.gid))
            self.sent += 1

    def undeclare(self) -> None:
        with self._put_lock:
            self._closed = True
            for handle in (self._token, self._listener, self._pub):
                if handle is not None:
                    try:
                        handle.undeclare()
                    except zenoh.ZError:
                        log.debug("undeclare of %s failed", self.key, exc_info=True)


class RosSubscription:
    """One topic subscription: `on_sample(payload, attachment_or_None)` on Zenoh's thread."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        token: str,
        on_sample: Callable[[bytes, bytes | None], None],
    ) -> None:
        self.key = key
        self.token_key = token

        def callback(sample: zenoh.Sample) -> None:
            att = sample.attachment
            on_sample(sample.payload.to_bytes(), None if att is None else att.to_bytes())

        self._sub = session.declare_subscriber(key, callback)
        self._token = session.liveliness().declare_token(token)

    def undeclare(self) -> None:
        for handle in (self._token, self._sub):
            try:
                handle.undeclare()
            except zenoh.ZError:
                log.debug("undeclare of %s failed", self.key, exc_info=True)


class RosNode:
    """A ROS 2 node `namespace/name` in domain `domain_id`, on `session` (not owned)."""

    NODE_ID = 0

    def __init__(self, session: zenoh.Session, domain_id: int, namespace: str, name: str) -> None:
        rmw.check_name(namespace, "namespace")
        rmw.check_name(name, "node name")
        if not name or "/" in name:
            raise ValueError(f"node name {name!r} must be a plain, non-empty name")
        self.session = session
        self.domain_id = domain_id
        self.namespace = "/" + namespace.strip("/") if namespace.strip("/") else "/"
        self.name = name
        self.zid = str(session.zid())
        self._ids = itertools.count(1)
        self._endpoints: list[RosPublisher | RosSubscription] = []
        self.token_key = rmw.node_token(domain_id, self.zid, self.NODE_ID, self.namespace, name)
        self._token = session.liveliness().declare_token(self.token_key)

    def fqn(self, topic: str) -> str:
        return rmw.fully_qualified(self.namespace, topic)

    def publisher(
        self,
        topic: str,
        t: TypeDef,
        qos: rmw.Qos,
        priority: zenoh.Priority = zenoh.Priority.DATA,
        express: bool = False,
    ) -> RosPublisher:
        fqn = self.fqn(topic)
        token = rmw.endpoint_token(
            "MP", self.domain_id, self.zid, self.NODE_ID, next(self._ids), self.namespace,
            self.name, fqn, t, qos,
        )  # fmt: skip
        pub = RosPublisher(
            self.session, rmw.topic_key(self.domain_id, fqn, t), token, qos, priority, express
        )
        self._endpoints.append(pub)
        return pub

    def subscription(
        self,
        topic: str,
        t: TypeDef,
        qos: rmw.Qos,
        on_sample: Callable[[bytes, bytes | None], None],
    ) -> RosSubscription:
        fqn = self.fqn(topic)
        token = rmw.endpoint_token(
            "MS", self.domain_id, self.zid, self.NODE_ID, next(self._ids), self.namespace,
            self.name, fqn, t, qos,
        )  # fmt: skip
        sub = RosSubscription(self.session, rmw.topic_key(self.domain_id, fqn, t), token, on_sample)
        self._endpoints.append(sub)
        return sub

    def tokens(self) -> list[str]:
        """Every liveliness token this node declared: the node's, then its endpoints'."""
        return [self.token_key, *(e.token_key for e in self._endpoints)]

    def close(self) -> None:
        """Undeclare every endpoint, then the node (the session stays open)."""
        for e in reversed(self._endpoints):
            e.undeclare()
        self._endpoints.clear()
        try:
            self._token.undeclare()
        except zenoh.ZError:
            log.debug("undeclare of the node token failed", exc_info=True)
