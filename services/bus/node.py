"""A service's presence on the bus: one Zenoh session with typed streams and methods.

Rules it enforces so services do not have to remember them (ZENOH_NOTES.md):
- the session is always closed (`with Node(...)`): a process with callbacks and an open
  session never exits;
- subscriber callbacks only decode and store (latest-wins) or hand over; they never block;
- a method call waits for the service's liveliness token before its first `get`, and an
  empty reply set is `Unavailable`, never success;
- every rejected payload is counted and reported as a `rejected` Event, at most one a
  second per key and `REJECT_EVENTS_PER_S` per service, each saying how many were
  suppressed; a payload above its topic's `max_bytes` (or call arguments above
  `MAX_PAYLOAD_BYTES`) is refused before it is decoded, and no reply, event or log line
  repeats more than `bounds.MAX_ECHO_CHARS` of it; what the node remembers per key is
  bounded, so a flood of distinct keys cannot grow memory.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import traceback
from collections.abc import Callable, Collection, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any, TypeVar

import zenoh

from services.bus import codec, rpc
from services.bus.bounds import short
from services.bus.config import NodeConfig
from services.bus.errors import (
    AlreadyRunning,
    ConnectFailed,
    ProtocolError,
    RpcError,
    TelerobotError,
    Unavailable,
)
from services.bus.events import EventLimiter
from services.bus.intake import Intake
from services.bus.keys import ALIVE_PREFIX, EVENTS, Topic, alive_key
from services.bus.messages import MAX_TEXT, Event, Message
from services.bus.rpc import Handler, PendingCall
from services.bus.streams import (
    Latest,
    Publisher,
    Subscription,
    newer,
    payload_bytes,
)

log = logging.getLogger("telerobot.bus")

M = TypeVar("M", bound=Message)

REJECT_REPORT_INTERVAL_S = 1.0
REJECT_EVENTS_PER_S = 5
"""Rejected-input events one node sends per second, over all keys."""
MAX_REJECT_KEYS = 256
"""Keys whose rejections are counted (and rate-limited) one by one; the rest share OTHER."""
OTHER_KEY = "(other keys)"
MAX_EVENT_DATA_BYTES = 16 * 1024
"""An event's data larger than this (packed) is replaced by a short summary."""


def open_session(config: NodeConfig) -> zenoh.Session:
    """`zenoh.open`, with a failure turned into one clear line (ConnectFailed): which
    endpoints, the cause without Zenoh's source location, and what to check."""
    try:
        return zenoh.open(config.to_zenoh())
    except zenoh.ZError as e:
        cause = str(e).split("  at ")[0].strip().rstrip("!")
        where = ", ".join(config.connect) or "(no endpoint)"
        raise ConnectFailed(
            f"cannot connect to {where}: {short(cause, 120)}. Is the router up "
            "(`telerobot router`, or `telerobot up` which starts one)? Is the endpoint "
            "right, and does the router accept this login (user/password, certificate: "
            "--zenoh-config)?"
        ) from None


CLAIM_PREFIX = "robot/claim"
"""Where a starting singleton shows itself while it asks who runs (Node.claim)."""
CLAIM_TIMEOUT_S = 1.0
"""How long a start-up waits for Zenoh's answer to "who holds alive/<service>"."""


class AliveSet:
    """The liveliness tokens under `alive/**`, kept current by a liveliness subscriber."""

    def __init__(self, session: zenoh.Session) -> None:
        self._cond = threading.Condition()
        self._alive: set[str] = set()
        self._listeners: list[Callable[[str, bool], None]] = []
        self._sub = session.liveliness().declare_subscriber(
            f"{ALIVE_PREFIX}/**", self._on_sample, history=True
        )

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        name = key[len(ALIVE_PREFIX) + 1 :]
        up = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            (self._alive.add if up else self._alive.discard)(name)
            self._cond.notify_all()
            listeners = list(self._listeners)
        for cb in listeners:
            try:
                cb(name, up)
            except Exception:  # a listener's bug must not kill Zenoh's callback thread
                log.exception("alive listener failed")

    def names(self) -> set[str]:
        with self._cond:
            return set(self._alive)

    def is_alive(self, name: str) -> bool:
        with self._cond:
            return name in self._alive

    def wait(self, name: str, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while name not in self._alive:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def on_change(self, cb: Callable[[str, bool], None]) -> None:
        """Call `cb(name, alive)` on every change (from Zenoh's thread: keep it short)."""
        with self._cond:
            self._listeners.append(cb)


class Node:
    """One service's Zenoh session. Use as a context manager; `close()` is idempotent.

    `name` is the service name used for events and for the liveliness token
    `alive/<name>[/<instance>]`, which `announce()` declares once the service's
    queryables are up (so a caller that sees the token can call at once).
    """

    def __init__(
        self,
        name: str,
        config: NodeConfig | None = None,
        instance: str | None = None,
        rpc_workers: int = 8,
    ) -> None:
        self.name = name
        self.instance = instance
        self.config = config or NodeConfig()
        self.session = open_session(self.config)
        self._lock = threading.Lock()
        self._closed = False
        self._token: Any = None
        self._decls: list[Any] = []
        self._intakes: list[Intake[Any, Any]] = []
        self._subs: list[Subscription[Any]] = []
        self._event_pub: Publisher[Event] | None = None
        self._event_seq = 0
        self._alive: AliveSet | None = None
        self._rpc_pool = ThreadPoolExecutor(rpc_workers, thread_name_prefix=f"{name}-rpc")
        self._reject_limiter = EventLimiter(REJECT_REPORT_INTERVAL_S, REJECT_EVENTS_PER_S)
        self._reject_suppressed = 0
        self.rejected: dict[str, int] = {}

    # --- lifecycle -------------------------------------------------------------------
    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def announce(self) -> None:
        """Declare the liveliness token: the service is up and serving."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(
                alive_key(self.name, self.instance)
            )

    def claim(self, timeout_s: float = CLAIM_TIMEOUT_S) -> None:
        """Be the only one of this service in the cell (its namespace), or raise
        `AlreadyRunning` naming the one that is: a second decision or arm beside the running
        one would answer calls and publish robot/state in its stead. Asks Zenoh who holds
        `alive/<service>` (a liveliness query: the tokens of every reachable session), and
        meanwhile shows a claim token `robot/claim/<service>/<who>`, which the holder reports
        as an event (`watch_claims`). Call before touching hardware, announce after."""
        key = alive_key(self.name, self.instance)
        who = f"{os.getpid()}@{socket.gethostname()}"[:64].replace("/", "_").replace("*", "_")
        claim = self.session.liveliness().declare_token(f"{CLAIM_PREFIX}/{key[6:]}/{who}")
        try:
            holders = [
                str(r.ok.key_expr)
                for r in self.session.liveliness().get(key, timeout=timeout_s)
                if r.ok is not None
            ]
        finally:
            claim.undeclare()
        if holders:
            raise AlreadyRunning(
                f"{key[6:]} already runs in this cell ({key} is held by another process): "
                "stop that one first, or start this one in another namespace (--ns)"
            )

    def watch_claims(self) -> None:
        """Report, as an `error` event, every other process that tried to start as this
        service in the cell and was refused (`claim`)."""
        prefix = f"{CLAIM_PREFIX}/{alive_key(self.name, self.instance)[6:]}/"

        def on_claim(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            who = str(sample.key_expr)[len(prefix) :]
            log.warning("another %s (%s) tried to start in this cell: refused", self.name, who)
            self.event(
                "error",
                f"another {self.name} ({short(who, 64)}) tried to start in this cell: it was "
                "refused; this one keeps the cell",
                {"code": "already_running", "contender": short(who, 64)},
            )

        self._decls.append(self.session.liveliness().declare_subscriber(prefix + "*", on_claim))

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for intake in self._intakes:
            intake.close()
        self._rpc_pool.shutdown(wait=False, cancel_futures=True)
        try:
            self.session.close()
        except zenoh.ZError:
            log.debug("session close failed", exc_info=True)

    @property
    def closed(self) -> bool:
        return self._closed

    # --- streams ---------------------------------------------------------------------
    def publisher(self, topic: Topic[M], cache: int = 0) -> Publisher[M]:
        """A typed publisher; `cache` > 0 keeps that many samples for late subscribers with
        `history` (streams.Publisher)."""
        pub = Publisher(self.session, topic, cache)
        self._decls.append(pub)
        return pub

    def subscribe(
        self,
        topic: Topic[M],
        on_message: Callable[[M], None] | None = None,
        key: str | None = None,
        history: bool = False,
    ) -> Subscription[M]:
        """Subscribe to a typed stream.

        Valid messages update `latest` (latest-wins topics keep the highest `seq`; see
        `newer`); every valid message is passed to `on_message`. Bad payloads are counted
        and reported, never raised. `history`: also get what a cached publisher kept (the
        arm's description), now and from a publisher that appears later.
        `on_message` runs on Zenoh's thread: store or hand over, do not block.
        """
        sub: Subscription[M] = Subscription(topic)
        keyexpr = key or topic.key

        def callback(sample: zenoh.Sample) -> None:
            try:
                msg = codec.decode(topic.type, payload_bytes(sample.payload, topic.max_bytes))
            except ProtocolError as e:
                with sub._cond:
                    sub.rejected += 1
                    sub.last_error = str(e)
                self.report_rejected(str(sample.key_expr), str(e))
                return
            with sub._cond:
                if not topic.latest_wins or newer(msg, sub.latest):
                    sub.latest = msg
                sub.received += 1
                sub._cond.notify_all()
            if on_message is not None:
                try:
                    on_message(msg)
                except Exception:  # a handler bug is reported, the stream keeps flowing
                    log.exception("handler for %s failed", keyexpr)
                    self.event(
                        "error",
                        f"handler for {keyexpr} failed",
                        {"traceback": traceback.format_exc(limit=5)},
                    )

        if history:
            sub._sub = zenoh.ext.declare_advanced_subscriber(
                self.session,
                keyexpr,
                callback,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
            )
        else:
            sub._sub = self.session.declare_subscriber(keyexpr, callback)
        self._subs.append(sub)
        return sub

    def batches(
        self, topic: Topic[M], on_batch: Callable[[tuple[M, ...]], None], depth: int = 64
    ) -> Intake[zenoh.Sample, M]:
        """React to a stream on arrival, in batches when the reader falls behind (intake.py).

        While the reader keeps up, each sample is handled at once in Zenoh's callback (no
        thread to wake); one that arrives while the reader is busy, or queued in Zenoh behind
        the last, is stored (up to `depth`, the oldest dropped) and a thread of ours takes
        what piled up in one call, so the delay stays bounded instead of growing behind a
        slow reader. `on_batch` gets the valid messages in arrival order and must not block:
        it may run on Zenoh's thread. For streams whose newest message supersedes the older
        ones (commands relative to an engagement). Bad payloads are counted and reported."""

        def decode(sample: zenoh.Sample) -> M | None:
            try:
                return codec.decode(topic.type, payload_bytes(sample.payload, topic.max_bytes))
            except ProtocolError as e:
                self.report_rejected(str(sample.key_expr), str(e))
                return None

        def on_error() -> None:
            log.exception("handler for %s failed", topic.key)
            self.event(
                "error",
                f"handler for {topic.key} failed",
                {"traceback": traceback.format_exc(limit=5)},
            )

        intake: Intake[zenoh.Sample, M] = Intake(
            f"{self.name}-{topic.key}", decode, on_batch, on_error, depth
        )
        self._intakes.append(intake)
        self._decls.append(self.session.declare_subscriber(topic.key, intake.on_sample))
        return intake

    def latest(
        self, topic: Topic[M], watch: bool = True, each: Callable[[M], None] | None = None
    ) -> Latest[M]:
        """The newest message of `topic`, decoded when read (see `Latest`); `watch=False`:
        not subscribed until `watch(True)`; `each`: every message queued since the previous
        read is handed to it when read."""
        handle = Latest(self, topic, watch, each)
        self._decls.append(handle)
        return handle

    def subscribe_raw(
        self, keyexpr: str, on_sample: Callable[[zenoh.Sample], None], history: bool = False
    ) -> Any:
        """An untyped subscription (introspection tools). Keep the returned handle.
        `history`: also what cached publishers kept (robot/arm/description)."""
        handle: Any
        if history:
            handle = zenoh.ext.declare_advanced_subscriber(
                self.session,
                keyexpr,
                on_sample,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True),
            )
        else:
            handle = self.session.declare_subscriber(keyexpr, on_sample)
        self._decls.append(handle)
        return handle

    # --- events ----------------------------------------------------------------------
    def event(self, kind: str, message: str, data: Mapping[str, Any] | None = None) -> Event:
        """Publish an Event on `robot/events` from this service."""
        body = dict(data) if data else None
        if body is not None and not _small(body):
            body = {"truncated": True, "summary": short(body)}
        with self._lock:
            self._event_seq += 1
            ev = Event(
                seq=self._event_seq,
                t_ns=time.time_ns(),
                source=self.name,
                kind=short(kind, 64),
                message=message[:MAX_TEXT],
                data=body,
            )
            if not self._closed:
                try:
                    # Declared here, not above: after close() declaring raises ZError, and
                    # a late callback's event must be dropped, not crash its thread.
                    if self._event_pub is None:
                        self._event_pub = self.publisher(EVENTS)
                    self._event_pub.put(ev)
                except (zenoh.ZError, ProtocolError):
                    log.warning("could not publish event %s: %s", kind, message, exc_info=True)
        return ev

    def report_rejected(self, where: str, reason: str) -> None:
        """Count a rejected input and publish a `rejected` event: at most one a second per
        key and REJECT_EVENTS_PER_S a second in all; the next event says how many were
        suppressed. Only a short prefix of `where` and `reason` is ever repeated."""
        where, reason = short(where), short(reason)
        now = time.monotonic()
        with self._lock:
            if where not in self.rejected and len(self.rejected) >= MAX_REJECT_KEYS:
                where = OTHER_KEY
            n = self.rejected[where] = self.rejected.get(where, 0) + 1
            if self._reject_limiter.allow(where, now) is None:
                self._reject_suppressed += 1
                return
            suppressed, self._reject_suppressed = self._reject_suppressed, 0
        log.warning("rejected input on %s: %s", where, reason)
        self.event(
            "rejected",
            f"rejected input on {where}: {reason}",
            {"key": where, "reason": reason, "count": n, "suppressed": suppressed},
        )

    # --- methods (services/bus/rpc.py) -------------------------------------------------
    def serve(
        self,
        service: str,
        methods: Mapping[str, Handler],
        inline: Collection[str] = (),
        first: Mapping[str, Callable[[], None]] | None = None,
        inline_try: Mapping[str, Callable[[dict[str, Any]], dict[str, Any] | None]] | None = None,
    ) -> None:
        """Serve `robot/<service>/rpc/<method>` for each handler (`rpc.serve` says how:
        `inline`, `first` and `inline_try`, and what each error replies)."""
        queryable = rpc.serve(self, self._rpc_pool, service, methods, inline, first, inline_try)
        self._decls.append(queryable)

    @property
    def alive(self) -> AliveSet:
        """The set of services whose liveliness token is up (created on first use)."""
        with self._lock:
            if self._alive is None:
                self._alive = AliveSet(self.session)
            return self._alive

    def call(
        self,
        service: str,
        method: str,
        args: Mapping[str, Any] | None = None,
        timeout_s: float = 2.0,
    ) -> dict[str, Any]:
        """Call a method: the reply map, or `RpcError` with the contract's code.

        Waits (within `timeout_s`) for `alive/<service>` before the first `get`; no reply
        at all raises `Unavailable`.
        """
        return self.call_start(service, method, args, timeout_s).result()

    def call_start(
        self,
        service: str,
        method: str,
        args: Mapping[str, Any] | None = None,
        timeout_s: float = 2.0,
    ) -> PendingCall:
        """Send a call and return at once; `result()` waits for the reply (as `call`).

        Calls started one after the other run concurrently: the decision's `status` asks
        arm and force at the same time.
        """
        return rpc.call_start(self, service, method, args, timeout_s)


def _small(data: dict[str, Any]) -> bool:
    """Whether an event's data packs to at most MAX_EVENT_DATA_BYTES."""
    try:
        return len(codec.pack(data)) <= MAX_EVENT_DATA_BYTES
    except (TypeError, ValueError, OverflowError):
        return False


@contextmanager
def opened(name: str, config: NodeConfig | None = None) -> Iterator[Node]:
    """`with opened("tool") as node:` — a Node that is always closed."""
    node = Node(name, config)
    try:
        yield node
    finally:
        node.close()


__all__ = [
    "AliveSet",
    "Latest",
    "Node",
    "PendingCall",
    "Publisher",
    "RpcError",
    "Subscription",
    "TelerobotError",
    "Unavailable",
    "opened",
]
