"""Live introspection in the spirit of the ros2 CLI: `topic list|echo|hz`, `call`, `alive`.

Every command opens a peer node (default: connect to the local router at
tcp/127.0.0.1:7447), declares no liveliness token, and closes its session on exit.

Zenoh, numpy and the codec are imported inside the commands, after argparse has parsed and
the arguments are validated: `--help` and a bad JSON argument answer at once
(tests/tools/cli/test_cli_startup.py holds this).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import defaultdict, deque
from typing import TYPE_CHECKING, Any, TextIO

from services.bus.bounds import short
from services.bus.config import LOCAL_ROUTER, NodeConfig, add_node_args, node_config
from services.bus.lifecycle import Shutdown

if TYPE_CHECKING:
    import zenoh

    from services.bus.node import AliveSet, Node

#: `topic echo` says it is still waiting when nothing came within this (s)
HINT_AFTER_S = 3.0
#: after a first instance of a role shows up, how long more tokens may still be arriving (s)
RESOLVE_SETTLE_S = 0.3
POLL_S = 0.05


def tool_config(args: argparse.Namespace) -> NodeConfig:
    """Tools default to a peer that connects to the local router and listens on loopback
    only (Zenoh's default listener is every interface: a tool need not be reachable)."""
    return node_config(args, connect=(LOCAL_ROUTER,), listen=("tcp/127.0.0.1:0",))


LINK_WAIT_S = 3.0
"""How long a tool waits for a router or peer to be linked before saying none is."""


def tool_node(args: argparse.Namespace, cfg: NodeConfig | None = None) -> Node:
    """The tool's session, linked to a router or a peer, or ConnectFailed saying none is
    reachable (a peer session opens without anyone to talk to, and would print nothing)."""
    from services.bus.errors import ConnectFailed
    from services.bus.node import Node

    cfg = cfg or tool_config(args)
    node = Node("cli", cfg)
    deadline = time.monotonic() + LINK_WAIT_S
    info = node.session.info
    while not (info.routers_zid() or info.peers_zid()):
        if time.monotonic() >= deadline:
            node.close()
            where = ", ".join(cfg.connect) or "(no endpoint)"
            raise ConnectFailed(
                f"no Zenoh router or peer reachable at {where} within {LINK_WAIT_S:g} s: is "
                "the router up (`telerobot router`, or `telerobot up`)? Is --connect right?"
            )
        time.sleep(0.02)  # polling Zenoh's link table: it has no event for a new link
    return node


def decode_sample(key: str, payload: bytes) -> Any:
    """Decode a payload for people: typed and validated when the key is a contract topic."""
    from services.bus.zenoh_cli_codec import readable

    return readable(key, payload)


def _strip_ns(key: str, ns: str) -> str:
    return key[len(ns) + 1 :] if ns and key.startswith(ns + "/") else key


def _say(text: str) -> None:
    """A message for the person at the terminal: stderr, so stdout stays JSON lines."""
    print(f"telerobot: {text}", file=sys.stderr, flush=True)


def cmd_echo(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    from services.bus.zenoh_cli_codec import readable  # here, not in the first callback

    stop = Shutdown()
    done = threading.Event()
    lock = threading.Lock()
    count = 0
    wildcard = "*" in args.key

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal count
        key = str(sample.key_expr)
        body = readable(key, sample.payload.to_bytes())
        if wildcard and isinstance(body, dict):
            body = {"_key": key, **body}
        with lock:
            if done.is_set():
                return
            out.write(json.dumps(body, ensure_ascii=False) + "\n")
            out.flush()
            count += 1
            if args.count and count >= args.count:
                done.set()

    start = time.monotonic()
    hinted = args.hint_after <= 0
    with tool_node(args) as node:
        # history: a cached sample (robot/arm/description) is echoed too, as it would be
        # to any late subscriber of the contract
        node.subscribe_raw(args.key, on_sample, history=True)
        deadline = start + args.timeout if args.timeout else None
        while not (done.is_set() or stop.is_set()):
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                break
            if not hinted and now - start >= args.hint_after:
                hinted = True
                with lock:
                    silent = count == 0
                if silent:
                    _say(
                        f"no sample on {args.key} yet… still listening (is its publisher up? "
                        "`telerobot alive`, `telerobot topic list`; Ctrl-C to stop)"
                    )
            done.wait(POLL_S)
    with lock:
        got = count
    if got == 0 and not stop.is_set():
        _say(f"no sample on {args.key} in {args.timeout:g} s")
        return 1
    return 0 if (not args.count or got >= args.count) else 1


def _hz_row(key: str, times: deque[float], lock: threading.Lock, window: float, total: int) -> str:
    now = time.monotonic()
    with lock:
        recent = [t for t in times if now - t <= window]
    rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 else 0.0
    row = {
        "key": key,
        "rate_hz": round(rate, 2),
        "samples": len(recent),
        "window_s": window,
        "total": total,
    }
    return json.dumps(row) + "\n"


def cmd_hz(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """Reports the rate every `--window` s; ends after `--duration` s, `--count` samples
    or `--reports` reports, whichever comes first (or on Ctrl-C)."""

    stop = Shutdown()
    times: deque[float] = deque(maxlen=100_000)
    lock = threading.Lock()
    enough = threading.Event()
    total = 0

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal total
        with lock:
            times.append(time.monotonic())
            total += 1
            if args.count and total >= args.count:
                enough.set()

    def row() -> str:
        with lock:
            n = total
        return _hz_row(args.key, times, lock, args.window, n)

    start = time.monotonic()
    end = start + args.duration if args.duration > 0 else float("inf")
    with tool_node(args) as node:
        node.subscribe_raw(args.key, on_sample)
        reports = 0
        next_report = start + args.window
        while not stop.is_set():
            now = time.monotonic()
            if enough.is_set() or now >= end:
                if next_report - args.window < now - POLL_S:  # a partial window left
                    out.write(row())
                break
            if now >= next_report:
                out.write(row())
                out.flush()
                reports += 1
                next_report += args.window
                if args.reports and reports >= args.reports:
                    break
            enough.wait(min(POLL_S, max(min(next_report, end) - now, 0.0)))
    out.flush()
    with lock:
        got = total
    if got == 0 and not stop.is_set():
        _say(f"no sample on {args.key} in {time.monotonic() - start:.1f} s")
        return 1
    return 0


def cmd_list(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    from services.bus import keys

    counts: dict[str, int] = defaultdict(int)
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            counts[str(sample.key_expr)] += 1

    cfg = tool_config(args)
    with tool_node(args, cfg) as node:
        node.subscribe_raw("**", on_sample)
        Shutdown().wait(args.duration)
    rows = []
    for key in sorted(counts):
        plain = _strip_ns(key, cfg.ns)
        topic = keys.topic_for(plain)
        rows.append(
            {
                "key": key,
                "type": topic.type.name if topic else "?",
                "rate_hz": round(counts[key] / args.duration, 1),
            }
        )
    if args.json:
        out.write(json.dumps(rows) + "\n")
    else:
        # columns as wide as the longest key (the ROS bridge's run to ~190 characters)
        width = max([28, *(len(r["key"]) for r in rows)])
        out.write(f"{'KEY':<{width}} {'TYPE':<16} {'RATE (Hz)':>9}\n")
        for r in rows:
            out.write(f"{r['key']:<{width}} {r['type']:<16} {r['rate_hz']:>9}\n")
    return 0


class Ambiguous(Exception):
    """A role name that several live instances share."""

    def __init__(self, name: str, instances: list[str]) -> None:
        super().__init__(
            f"{name!r} has several live instances: {', '.join(instances)}; name one, e.g. "
            f"`telerobot call {instances[0]} …`"
        )
        self.instances = instances


def resolve_service(alive: AliveSet, name: str, timeout_s: float) -> str | None:
    """The live service to call for `name`: `name` itself when its token is up, else the
    single live instance `name/<id>` (a master's service is `master/<id>`, PROTOCOL.md §5).

    Returns None when nothing matches within `timeout_s`; raises `Ambiguous` when several
    instances match. Tokens arrive one peer at a time, so after a first instance shows up
    it waits `RESOLVE_SETTLE_S` more for others.
    """
    changed = threading.Event()
    alive.on_change(lambda _name, _up: changed.set())
    deadline = time.monotonic() + timeout_s
    settle_until: float | None = None
    while True:
        changed.clear()
        names = alive.names()
        if name in names:
            return name
        instances = sorted(n for n in names if n.startswith(name + "/"))
        now = time.monotonic()
        if instances and settle_until is None:
            settle_until = min(now + RESOLVE_SETTLE_S, deadline)
        if settle_until is not None and now >= settle_until:
            if len(instances) > 1:
                raise Ambiguous(name, instances)
            return instances[0]
        if now >= deadline:
            return None
        changed.wait(min(POLL_S, (settle_until or deadline) - now))


def _error(out: TextIO, code: str, message: str) -> None:
    out.write(json.dumps({"error": code, "message": message}, ensure_ascii=False) + "\n")
    out.flush()


def cmd_call(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    try:
        call_args = json.loads(args.args) if args.args else {}
    except json.JSONDecodeError as e:
        _error(out, "bad_request", f"arguments: {e}")
        return 1
    if not isinstance(call_args, dict):
        _error(out, "bad_request", "arguments must be a JSON object")
        return 1
    cfg = tool_config(args)

    from services.bus.errors import RpcError, TimedOut, Unavailable

    with tool_node(args, cfg) as node:
        start = time.monotonic()
        try:
            service = resolve_service(node.alive, args.service, args.timeout)
        except Ambiguous as e:
            _error(out, "bad_request", str(e))
            return 1
        if service is None:
            up = ", ".join(sorted(node.alive.names())) or "none"
            _error(
                out,
                "unavailable",
                f"service {args.service!r} is not alive (no alive/{args.service} token "
                f"within {args.timeout:g} s); alive: {up}",
            )
            return 2
        left = max(args.timeout - (time.monotonic() - start), 0.5)
        try:
            reply = node.call(service, args.method, call_args, timeout_s=left)
        except KeyboardInterrupt:
            return _interrupted(node, service, args.method, out)
        except RpcError as e:
            _error(out, e.code, e.message)
            return 1
        except TimedOut as e:
            _error(out, "timed_out", f"{service}: {e}; query its status before retrying")
            return 2
        except Unavailable as e:
            _error(out, "unavailable", str(e))
            return 2
    from services.bus import codec

    indent = 2 if getattr(args, "pretty", False) else None
    out.write(json.dumps(codec.jsonable(reply), ensure_ascii=False, indent=indent) + "\n")
    return 0


MOTIONS = frozenset({"move_joints", "move_pose", "move_relative", "home", "initialize"})
"""Methods that start a motion: Ctrl-C on a call of one stops it (`stop` of the same
service); a `task` is cancelled (`task {"name": "cancel"}`)."""
INTERRUPTED_EXIT = 130


def _interrupted(node: Any, service: str, method: str, out: TextIO) -> int:
    """Ctrl-C during a call: what it started is stopped, and the answer says so plainly."""
    import signal

    if method not in MOTIONS and method != "task":
        _error(out, "interrupted", f"Ctrl-C: stopped waiting for {service} {method}")
        return INTERRUPTED_EXIT
    stop, stop_args = ("task", {"name": "cancel"}) if method == "task" else ("stop", {})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C: same answer
    try:
        node.call(service, stop, stop_args, timeout_s=2.0)
    except Exception as e:  # any failure is reported, with the way out
        _error(
            out,
            "interrupted",
            f"Ctrl-C: the {method} may still be moving: {stop} failed ({short(str(e))}); "
            f"stop it with `telerobot call {service} stop` or the e-stop",
        )
        return INTERRUPTED_EXIT
    finally:
        signal.signal(signal.SIGINT, previous)
    _error(out, "interrupted", f"Ctrl-C: the {method} was stopped ({service} {stop})")
    return INTERRUPTED_EXIT


def cmd_alive(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:

    with tool_node(args) as node:
        # A liveliness get right after connecting reaches only the peers linked so far
        # (ZENOH_NOTES pitfall 5) and missed half the tokens of a peer mesh; a history
        # subscriber keeps collecting for the whole timeout, peers found by gossip included.
        alive = node.alive
        Shutdown().wait(args.timeout)
        names = sorted(alive.names())
    if args.json:
        out.write(json.dumps(names) + "\n")
    else:
        for n in names:
            out.write(n + "\n")
    return 0


def _positive(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def _non_negative(text: str) -> float:
    v = float(text)
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text}")
    return v


def _count(text: str) -> int:
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text}")
    return v


def add_parsers(sub: Any) -> None:
    """Register `topic`, `call` and `alive` on the top-level subparsers."""
    topic = sub.add_parser("topic", help="inspect streams: list, echo, hz")
    tsub = topic.add_subparsers(dest="topic_cmd", required=True, metavar="list|echo|hz")
    p = tsub.add_parser("list", help="keys seen, with their rates")
    p.add_argument(
        "--duration", type=_positive, default=2.0, metavar="S", help="seconds to listen (2)"
    )
    p.add_argument("--json", action="store_true", help="one JSON array instead of a table")
    add_node_args(p)
    p.set_defaults(func=cmd_list)

    p = tsub.add_parser(
        "echo",
        help="decoded payloads as JSON lines (bytes summarized)",
        description="Print each sample on KEY as one JSON line (stdout); messages for "
        "people go to stderr. Runs until Ctrl-C, --count or --timeout.",
    )
    p.add_argument("key", help="key expression, e.g. robot/force or 'robot/**'")
    p.add_argument(
        "--count", "-n", type=_count, default=0, metavar="N", help="stop after N samples"
    )
    p.add_argument(
        "--timeout",
        type=_non_negative,
        default=0.0,
        metavar="S",
        help="give up after S seconds (exit 1 if nothing or fewer than --count came; 0: never)",
    )
    p.add_argument(
        "--hint-after",
        type=_non_negative,
        default=HINT_AFTER_S,
        metavar="S",
        help=f"say so on stderr when nothing came within S seconds ({HINT_AFTER_S:g}; 0: never)",
    )
    add_node_args(p)
    p.set_defaults(func=cmd_echo)

    p = tsub.add_parser(
        "hz",
        help="the delivered rate of a key",
        description="Report the rate of KEY every --window seconds as JSON lines; ends after "
        "--duration seconds, --count samples or --reports reports (exit 1 if none came).",
    )
    p.add_argument("key", help="key expression, e.g. robot/force")
    p.add_argument(
        "--window", type=_positive, default=1.0, metavar="S", help="report every S seconds (1)"
    )
    p.add_argument(
        "--duration",
        type=_non_negative,
        default=5.0,
        metavar="S",
        help="stop after S seconds (5; 0: until Ctrl-C)",
    )
    p.add_argument(
        "--count", "-n", type=_count, default=0, metavar="N", help="stop after N samples"
    )
    p.add_argument("--reports", type=_count, default=0, metavar="N", help="stop after N reports")
    add_node_args(p)
    p.set_defaults(func=cmd_hz)

    p = sub.add_parser(
        "call",
        help="call a method: telerobot call decision status '{}'",
        description="Call SERVICE's METHOD (PROTOCOL.md §4) and print the reply as JSON. A role "
        "with one live instance may be named by its role: `call master status` calls "
        "master/<id>. Exit 0: reply; 1: error reply or bad arguments; 2: no reply.",
    )
    p.add_argument("service", help="service name: decision, arm, force, master, master/<id>, …")
    p.add_argument("method", help="method name, e.g. status")
    p.add_argument("args", nargs="?", default="{}", help="arguments as a JSON object ({})")
    p.add_argument("--pretty", action="store_true", help="indent the reply (2 spaces)")
    p.add_argument(
        "--timeout",
        type=_positive,
        default=5.0,
        metavar="S",
        help="wait S seconds for the service and its reply (5)",
    )
    add_node_args(p)
    p.set_defaults(func=cmd_call)

    p = sub.add_parser("alive", help="which services are up (liveliness tokens)")
    p.add_argument(
        "--timeout", type=_positive, default=1.0, metavar="S", help="seconds to collect tokens (1)"
    )
    p.add_argument("--json", action="store_true", help="one JSON array instead of lines")
    add_node_args(p)
    p.set_defaults(func=cmd_alive)
