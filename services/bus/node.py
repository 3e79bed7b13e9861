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

import contextlib
import logging
import threading
import time
import traceback
from collections.abc import Callable, Collection, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import zenoh

from services.bus import codec
from services.bus.bounds import MAX_PAYLOAD_BYTES, short
from services.bus.config import NodeConfig
from services.bus.errors import (
    ERROR_CODES,
    ProtocolError,
    RpcError,
    TelerobotError,
    TimedOut,
    Unavailable,
)
from services.bus.events import EventLimiter
from services.bus.keys import ALIVE_PREFIX, ENCODING, EVENTS, QoS, Topic, alive_key, rpc_key
from services.bus.messages import MAX_TEXT, Event, Message

log = logging.getLogger("telerobot.bus")

M = TypeVar("M", bound=Message)
Handler = Callable[[dict[str, Any]], dict[str, Any]]

_ENCODING = zenoh.Encoding(ENCODING)
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
REJECT_REPORT_INTERVAL_S = 1.0
REJECT_EVENTS_PER_S = 5
"""Rejected-input events one node sends per second, over all keys."""
MAX_REJECT_KEYS = 256
"""Keys whose rejections are counted (and rate-limited) one by one; the rest share OTHER."""
OTHER_KEY = "(other keys)"
MAX_EVENT_DATA_BYTES = 16 * 1024
"""An event's data larger than this (packed) is replaced by a short summary."""
CALL_RETRY_S = 0.02
ZENOH_TIMEOUT = b"Timeout"
"""The error reply Zenoh itself gives a `get` whose queryable did not answer in time."""
RESTART_GAP_NS = 250_000_000


class Publisher(Generic[M]):
    """A typed publisher: `put(msg)` validates, encodes and sends with the topic's QoS."""

    def __init__(self, session: zenoh.Session, topic: Topic[M]) -> None:
        self.topic = topic
        self._pub = session.declare_publisher(topic.key, encoding=_ENCODING, **_QOS[topic.qos])
        self.sent = 0

    def put(self, msg: M) -> None:
        self._pub.put(codec.encode(msg))
        self.sent += 1

    def put_bytes(self, payload: bytes) -> None:
        """Send an already-encoded payload (replay, fuzzing)."""
        self._pub.put(payload)
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
    """

    def __init__(self, node: Node, topic: Topic[M], watch: bool = True) -> None:
        self.topic = topic
        self._node = node
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
                self.topic.key, zenoh.handlers.RingChannel(1)
            )
        elif not on and self._sub is not None:
            sub, self._sub = self._sub, None
            with contextlib.suppress(zenoh.ZError):  # the session is closing
                sub.undeclare()

    def read(self) -> tuple[M, int] | None:
        """(newest message, its arrival on time.monotonic_ns()) or None if none yet."""
        sub = self._sub
        try:
            sample = sub.try_recv() if sub is not None else None
        except zenoh.ZError:  # the session is closing
            sample = None
        now_mono = time.monotonic_ns()
        previous, self._read_ns = self._read_ns, now_mono
        if sample is not None:
            now_wall = time.time_ns()
            try:
                msg = codec.decode(self.topic.type, _payload(sample.payload, self.topic.max_bytes))
            except ProtocolError as e:
                self.rejected += 1
                self._node.report_rejected(str(sample.key_expr), str(e))
            else:
                self.received += 1
                if _newer(msg, self._msg):
                    age_ns = min(max(now_wall - int(getattr(msg, "t_ns", now_wall)), 0), 10**12)
                    self._msg, self._rx_ns = msg, max(previous, now_mono - age_ns)
        return None if self._msg is None else (self._msg, self._rx_ns)


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
        self.session = zenoh.open(self.config.to_zenoh())
        self._lock = threading.Lock()
        self._closed = False
        self._token: Any = None
        self._decls: list[Any] = []
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

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._rpc_pool.shutdown(wait=False, cancel_futures=True)
        try:
            self.session.close()
        except zenoh.ZError:
            log.debug("session close failed", exc_info=True)

    @property
    def closed(self) -> bool:
        return self._closed

    # --- streams ---------------------------------------------------------------------
    def publisher(self, topic: Topic[M]) -> Publisher[M]:
        pub = Publisher(self.session, topic)
        self._decls.append(pub)
        return pub

    def subscribe(
        self, topic: Topic[M], on_message: Callable[[M], None] | None = None, key: str | None = None
    ) -> Subscription[M]:
        """Subscribe to a typed stream.

        Valid messages update `latest` (latest-wins topics keep the highest `seq`; see
        `_newer`); every valid message is passed to `on_message`. Bad payloads are counted
        and reported, never raised.
        `on_message` runs on Zenoh's thread: store or hand over, do not block.
        """
        sub: Subscription[M] = Subscription(topic)
        keyexpr = key or topic.key

        def callback(sample: zenoh.Sample) -> None:
            try:
                msg = codec.decode(topic.type, _payload(sample.payload, topic.max_bytes))
            except ProtocolError as e:
                with sub._cond:
                    sub.rejected += 1
                    sub.last_error = str(e)
                self.report_rejected(str(sample.key_expr), str(e))
                return
            with sub._cond:
                if not topic.latest_wins or _newer(msg, sub.latest):
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

        sub._sub = self.session.declare_subscriber(keyexpr, callback)
        self._subs.append(sub)
        return sub

    def batches(
        self, topic: Topic[M], on_batch: Callable[[tuple[M, ...]], None], depth: int = 64
    ) -> None:
        """React to a stream on arrival, in batches when the reader falls behind.

        Zenoh keeps up to `depth` samples in a ring (the oldest dropped beyond that) and a
        thread of ours wakes on each arrival, takes every sample waiting, and calls
        `on_batch` once with the valid ones in arrival order. A reader slower than the
        stream thus handles what accumulated at once instead of queuing behind Zenoh's
        callback thread (where a backlog grows without bound and pushes back on the
        publisher). For streams whose newest message supersedes the older ones
        (commands relative to an engagement). Bad payloads are counted and reported."""
        sub = self.session.declare_subscriber(topic.key, zenoh.handlers.RingChannel(depth))
        self._decls.append(sub)

        def decode(sample: zenoh.Sample) -> M | None:
            try:
                return codec.decode(topic.type, _payload(sample.payload, topic.max_bytes))
            except ProtocolError as e:
                self.report_rejected(str(sample.key_expr), str(e))
                return None

        def run() -> None:
            while not self._closed:
                try:
                    first = sub.recv()  # blocks (the GIL released) until a sample arrives
                except Exception:  # the subscriber was undeclared: the node is closing
                    return
                samples = [first]
                for _ in range(depth):
                    try:
                        more = sub.try_recv()
                    except Exception:
                        more = None
                    if more is None:
                        break
                    samples.append(more)
                msgs = tuple(m for m in map(decode, samples) if m is not None)
                if not msgs:
                    continue
                try:
                    on_batch(msgs)
                except Exception:  # a handler bug is reported, the stream keeps flowing
                    log.exception("handler for %s failed", topic.key)
                    self.event(
                        "error",
                        f"handler for {topic.key} failed",
                        {"traceback": traceback.format_exc(limit=5)},
                    )

        threading.Thread(target=run, name=f"{self.name}-{topic.key}", daemon=True).start()

    def latest(self, topic: Topic[M], watch: bool = True) -> Latest[M]:
        """The newest message of `topic`, decoded when read (see `Latest`); `watch=False`:
        not subscribed until `watch(True)`."""
        handle = Latest(self, topic, watch)
        self._decls.append(handle)
        return handle

    def subscribe_raw(self, keyexpr: str, on_sample: Callable[[zenoh.Sample], None]) -> Any:
        """An untyped subscription (introspection tools). Keep the returned handle."""
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

    # --- methods ---------------------------------------------------------------------
    def serve(
        self,
        service: str,
        methods: Mapping[str, Handler],
        inline: Collection[str] = (),
        first: Mapping[str, Callable[[], None]] | None = None,
    ) -> None:
        """Serve `robot/<service>/rpc/<method>` for each handler.

        A handler takes the decoded argument map and returns the reply map. Handlers named in
        `inline` never block (no I/O, no waiting, only short locks): they run in Zenoh's
        callback, which saves the hand-over to a worker (the floor of a call). Every other
        handler runs on a worker thread, so a `"wait": true` motion or a nested call can
        block until done. `first[method]`, if given, runs before the arguments are read or
        checked (an e-stop latches whatever its call carries). Arguments above
        MAX_PAYLOAD_BYTES are refused unread. `ProtocolError` → `bad_request`, `RpcError` →
        its code, anything else → `internal` (and an event); a reply's message is short.
        """
        table = dict(methods)
        unknown = (set(inline) | set(first or {})) - set(table)
        if unknown:
            raise ValueError(f"inline or first-action methods not served: {sorted(unknown)}")
        direct = frozenset(inline)
        before = dict(first or {})
        prefix = rpc_key(service, "")

        def run(query: zenoh.Query, method: str) -> None:
            try:
                handler = table.get(method)
                if handler is None:
                    raise RpcError(
                        "bad_request",
                        f"no method {short(method, 64)!r} on {service} "
                        f"(methods: {', '.join(sorted(table))})",
                    )
                act = before.get(method)
                if act is not None:
                    act()  # before anything can fail: an e-stop latches whatever it carries
                payload = query.payload
                args = codec.unpack(_payload(payload, MAX_PAYLOAD_BYTES)) if payload else {}
                if args is None:
                    args = {}
                if not isinstance(args, dict):
                    raise ProtocolError("args", "expected a msgpack map of arguments")
                result = handler(args)
                query.reply(query.key_expr, codec.pack(result), encoding=_ENCODING)
            except (ProtocolError, RpcError) as e:
                code = e.code if isinstance(e, RpcError) else "bad_request"
                msg = short(e.message if isinstance(e, RpcError) else str(e))
                if code == "bad_request":
                    self.report_rejected(str(query.key_expr), msg)
                query.reply_err(codec.pack({"error": code, "message": msg}), encoding=_ENCODING)
            except Exception as e:  # any bug becomes an `internal` reply, never a dead service
                log.exception("method %s/%s failed", service, short(method, 64))
                self.event(
                    "error",
                    short(f"{service}.{method} failed: {e}"),
                    {"method": short(method, 64), "traceback": traceback.format_exc(limit=8)},
                )
                query.reply_err(
                    codec.pack({"error": "internal", "message": short(e)}), encoding=_ENCODING
                )
            finally:
                query.drop()

        def callback(query: zenoh.Query) -> None:
            method = str(query.key_expr)[len(prefix) :]
            if "/" in method and method.split("/", 1)[0] in table:
                method = method.split("/", 1)[0]
            if method in direct or method not in table:
                run(query, method)  # never blocks; an unknown method is answered at once
                return
            try:
                self._rpc_pool.submit(run, query, method)
            except RuntimeError:  # pool shut down: the node is closing
                query.drop()

        self._decls.append(self.session.declare_queryable(rpc_key(service, "**"), callback))

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
        puma and force at the same time.
        """
        deadline = time.monotonic() + timeout_s
        if not self.alive.wait(service, timeout_s):
            raise Unavailable(f"service {service!r} is not alive (no alive/{service} token)")
        payload = codec.pack(dict(args or {}))
        key = rpc_key(service, method)
        replies = self.session.get(key, payload=payload, encoding=_ENCODING, timeout=timeout_s)
        return PendingCall(self, service, key, payload, deadline, replies)

    def _call_retry(
        self, service: str, key: str, payload: bytes, deadline: float
    ) -> dict[str, Any]:
        """The `get` loop after a first attempt saw no reply (pitfall 5). No reply from a
        service that is gone is `Unavailable`; from one still alive at the deadline,
        `TimedOut` (what was asked may still be under way)."""
        while True:
            if not self.alive.is_alive(service):
                raise Unavailable(f"no reply from {key}: the service is gone")
            if time.monotonic() >= deadline:
                raise TimedOut(f"{key}: timed out with no reply; it may still be running")
            time.sleep(min(CALL_RETRY_S, max(deadline - time.monotonic(), 0.0)))
            left = deadline - time.monotonic()
            replies = list(
                self.session.get(key, payload=payload, encoding=_ENCODING, timeout=max(left, 0.05))
            )
            if replies:
                return _reply_map(replies[0], key)


class PendingCall:
    """A method call under way (`Node.call_start`); `result()` gives its reply once."""

    def __init__(
        self, node: Node, service: str, key: str, payload: bytes, deadline: float, replies: Any
    ) -> None:
        self._node = node
        self._service = service
        self._key = key
        self._payload = payload
        self._deadline = deadline
        self._replies = replies

    def result(self) -> dict[str, Any]:
        """The reply map, or `RpcError` with the contract's code; `Unavailable` when no
        reply came before the deadline."""
        replies = list(self._replies)
        if replies:
            return _reply_map(replies[0], self._key)
        # Pitfall 5: right after (re)connecting a get may see no queryable yet. Retry while
        # the service is alive and time is left; otherwise it is absent.
        return self._node._call_retry(self._service, self._key, self._payload, self._deadline)


def _small(data: dict[str, Any]) -> bool:
    """Whether an event's data packs to at most MAX_EVENT_DATA_BYTES."""
    try:
        return len(codec.pack(data)) <= MAX_EVENT_DATA_BYTES
    except (TypeError, ValueError, OverflowError):
        return False


def _payload(payload: zenoh.ZBytes, max_bytes: int) -> bytes:
    """The payload's bytes, or ProtocolError when it is larger than `max_bytes` (it is not
    even copied out of Zenoh then)."""
    n = len(payload)
    if n > max_bytes:
        raise ProtocolError("payload", f"{n} bytes is more than the {max_bytes} allowed")
    return payload.to_bytes()


def _reply_map(reply: zenoh.Reply, key: str) -> dict[str, Any]:
    if reply.ok is not None:
        data = codec.unpack(reply.ok.payload.to_bytes())
        if not isinstance(data, dict):
            raise RpcError("internal", f"{key} replied with a non-map")
        return data
    err = reply.err
    try:
        body = codec.unpack(err.payload.to_bytes()) if err is not None else None
    except ProtocolError:
        body = None
    if isinstance(body, dict) and body.get("error") in ERROR_CODES:
        raise RpcError(body["error"], str(body.get("message", "")))
    raw = err.payload.to_bytes() if err is not None else b""
    if raw == ZENOH_TIMEOUT:
        raise TimedOut(f"{key}: timed out with no reply; it may still be running")
    raise RpcError("internal", f"{key}: {short(raw.decode('utf-8', 'replace'))}")


def _newer(msg: Message, newest: Message | None) -> bool:
    """Latest-wins: a higher `seq` replaces; so does a lower one sent well after the newest,
    which is a restarted publisher counting from 1 again, not a stale sample."""
    if newest is None:
        return True
    seq, t_ns = getattr(msg, "seq", 0), getattr(msg, "t_ns", 0)
    return bool(
        seq > getattr(newest, "seq", 0) or t_ns - getattr(newest, "t_ns", 0) > RESTART_GAP_NS
    )


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
