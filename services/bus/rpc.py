"""Methods on the bus: a service's queryables and the calls that reach them.

`serve` declares `robot/<service>/rpc/**` for a table of handlers (inline ones in Zenoh's
callback, the rest on a worker; arguments above MAX_PAYLOAD_BYTES refused unread; every
error a reply with the contract's code, never a dead service); `call_start` sends a call
and `PendingCall.result` waits for its one reply, retrying the `get` while the service is
alive (ZENOH_NOTES.md pitfall 5), so an empty reply set is `Unavailable`, never success.
`Node.serve`, `Node.call` and `Node.call_start` are the doors services use.
"""

from __future__ import annotations

import logging
import time
import traceback
from collections.abc import Callable, Collection, Mapping
from concurrent.futures import Executor
from typing import TYPE_CHECKING, Any

import zenoh

from services.bus import codec
from services.bus.bounds import MAX_PAYLOAD_BYTES, short
from services.bus.errors import ERROR_CODES, ProtocolError, RpcError, TimedOut, Unavailable
from services.bus.keys import rpc_key
from services.bus.streams import ZENOH_ENCODING, payload_bytes

if TYPE_CHECKING:
    from services.bus.node import Node

log = logging.getLogger("telerobot.bus")

Handler = Callable[[dict[str, Any]], dict[str, Any]]

CALL_RETRY_S = 0.02
ZENOH_TIMEOUT = b"Timeout"
"""The error reply Zenoh itself gives a `get` whose queryable did not answer in time."""


def serve(
    node: Node,
    pool: Executor,
    service: str,
    methods: Mapping[str, Handler],
    inline: Collection[str] = (),
    first: Mapping[str, Callable[[], None]] | None = None,
    inline_try: Mapping[str, Callable[[dict[str, Any]], dict[str, Any] | None]] | None = None,
) -> zenoh.Queryable:
    """Serve `robot/<service>/rpc/<method>` for each handler on `node`'s session, workers
    from `pool`; the queryable, which the node undeclares when it closes.

    A handler takes the decoded argument map and returns the reply map. Handlers named in
    `inline` never block (no I/O, no waiting, only short locks): they run in Zenoh's
    callback, which saves the hand-over to a worker (the floor of a call). Every other
    handler runs on a worker thread, so a `"wait": true` motion or a nested call can
    block until done. `first[method]`, if given, runs before the arguments are read or
    checked (an e-stop latches whatever its call carries). `inline_try[method]`, for a
    method that usually answers from what it keeps: tried first in Zenoh's callback; it
    never blocks, and returns None when it would have to wait, and then `methods[method]`
    answers on a worker. Arguments above MAX_PAYLOAD_BYTES are refused unread.
    `ProtocolError` → `bad_request`, `RpcError` → its code, anything else → `internal`
    (and an event); a reply's message is short.
    """
    table = dict(methods)
    tries = dict(inline_try or {})
    unknown = (set(inline) | set(first or {}) | set(tries)) - set(table)
    if unknown:
        raise ValueError(f"inline or first-action methods not served: {sorted(unknown)}")
    if set(tries) & set(first or {}):
        raise ValueError("a method with a first action cannot have an inline try")
    direct = frozenset(inline)
    before = dict(first or {})
    prefix = rpc_key(service, "")

    def run(query: zenoh.Query, method: str, attempt: bool = False) -> bool:
        """Answer `query`; False (nothing sent) when the inline try would wait."""
        answered = True
        try:
            handler = tries[method] if attempt else table.get(method)
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
            args = codec.unpack(payload_bytes(payload, MAX_PAYLOAD_BYTES)) if payload else {}
            if args is None:
                args = {}
            if not isinstance(args, dict):
                raise ProtocolError("args", "expected a msgpack map of arguments")
            result = handler(args)
            if result is None:  # only an inline try: the worker answers
                answered = False
                return False
            query.reply(query.key_expr, codec.pack(result), encoding=ZENOH_ENCODING)
        except (ProtocolError, RpcError) as e:
            code = e.code if isinstance(e, RpcError) else "bad_request"
            msg = short(e.message if isinstance(e, RpcError) else str(e))
            if code == "bad_request":
                node.report_rejected(str(query.key_expr), msg)
            query.reply_err(codec.pack({"error": code, "message": msg}), encoding=ZENOH_ENCODING)
        except Exception as e:  # any bug becomes an `internal` reply, never a dead service
            log.exception("method %s/%s failed", service, short(method, 64))
            node.event(
                "error",
                short(f"{service}.{method} failed: {e}"),
                {"method": short(method, 64), "traceback": traceback.format_exc(limit=8)},
            )
            query.reply_err(
                codec.pack({"error": "internal", "message": short(e)}), encoding=ZENOH_ENCODING
            )
        finally:
            if answered:
                query.drop()
        return True

    def callback(query: zenoh.Query) -> None:
        method = str(query.key_expr)[len(prefix) :]
        if "/" in method and method.split("/", 1)[0] in table:
            method = method.split("/", 1)[0]
        if method in direct or method not in table:
            run(query, method)  # never blocks; an unknown method is answered at once
            return
        if method in tries and run(query, method, attempt=True):
            return  # answered from what the service keeps
        try:
            pool.submit(run, query, method)
        except RuntimeError:  # pool shut down: the node is closing
            query.drop()

    return node.session.declare_queryable(rpc_key(service, "**"), callback)


def call_start(
    node: Node,
    service: str,
    method: str,
    args: Mapping[str, Any] | None = None,
    timeout_s: float = 2.0,
) -> PendingCall:
    """Send a call from `node` and return at once; `result()` waits for the reply (as
    `Node.call`).

    Calls started one after the other run concurrently: the decision's `status` asks
    arm and force at the same time.
    """
    deadline = time.monotonic() + timeout_s
    if not node.alive.wait(service, timeout_s):
        raise Unavailable(f"service {service!r} is not alive (no alive/{service} token)")
    payload = codec.pack(dict(args or {}))
    key = rpc_key(service, method)
    replies = node.session.get(key, payload=payload, encoding=ZENOH_ENCODING, timeout=timeout_s)
    return PendingCall(node, service, key, payload, deadline, replies)


def _call_retry(
    node: Node, service: str, key: str, payload: bytes, deadline: float
) -> dict[str, Any]:
    """The `get` loop after a first attempt saw no reply (pitfall 5). No reply from a
    service that is gone is `Unavailable`; none from one still alive at the deadline is
    `Unavailable` too, saying the call never reached it (an ACL, a missing method):
    only Zenoh's own timeout reply means it was delivered and may still be running
    (`TimedOut`)."""
    while True:
        if not node.alive.is_alive(service):
            raise Unavailable(f"no reply from {key}: the service is gone")
        if time.monotonic() >= deadline:
            # Every get ended with no reply at all: no queryable of it was reached.
            raise Unavailable(
                f"{key}: {service} is alive but the call never reached it, so nothing "
                "ran: the router's access control may not let this login call it, or "
                f"{service} has no such method"
            )
        time.sleep(min(CALL_RETRY_S, max(deadline - time.monotonic(), 0.0)))
        left = deadline - time.monotonic()
        replies = list(
            node.session.get(key, payload=payload, encoding=ZENOH_ENCODING, timeout=max(left, 0.05))
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
        return _call_retry(self._node, self._service, self._key, self._payload, self._deadline)


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
