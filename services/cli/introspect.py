"""Live introspection in the spirit of the ros2 CLI: `topic list|echo|hz`, `call`, `alive`.

Every command opens a peer node (default: connect to the local router at
tcp/127.0.0.1:7447), declares no liveliness token, and closes its session on exit.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import defaultdict, deque
from typing import Any, TextIO

import zenoh

from services.bus import codec, keys
from services.bus.config import NodeConfig, add_node_args, node_config
from services.bus.errors import ProtocolError, RpcError, Unavailable
from services.bus.lifecycle import Shutdown
from services.bus.node import Node

LOCAL_ROUTER = "tcp/127.0.0.1:7447"


def tool_config(args: argparse.Namespace) -> NodeConfig:
    """Tools default to a peer that connects to the local router."""
    return node_config(args, connect=(LOCAL_ROUTER,))


def decode_sample(key: str, payload: bytes) -> Any:
    """Decode a payload for people: typed and validated when the key is a contract topic."""
    topic = keys.topic_for(key)
    try:
        if topic is not None:
            return codec.jsonable(codec.decode(topic.type, payload))
        return codec.jsonable(codec.unpack(payload))
    except ProtocolError as e:
        try:
            text = payload.decode("utf-8")
        except UnicodeDecodeError:
            text = f"<{len(payload)} bytes>"
        return {"_rejected": str(e), "_raw": text[:200]}


def _strip_ns(key: str, ns: str) -> str:
    return key[len(ns) + 1 :] if ns and key.startswith(ns + "/") else key


def cmd_echo(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    stop = Shutdown()
    done = threading.Event()
    lock = threading.Lock()
    count = 0
    wildcard = "*" in args.key

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal count
        key = str(sample.key_expr)
        body = decode_sample(key, sample.payload.to_bytes())
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

    with Node("cli", tool_config(args)) as node:
        node.subscribe_raw(args.key, on_sample)
        deadline = time.monotonic() + args.timeout if args.timeout else None
        while not (done.is_set() or stop.is_set()):
            if deadline is not None and time.monotonic() >= deadline:
                break
            done.wait(0.1)
    return 0 if (not args.count or count >= args.count) else 1


def cmd_hz(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    stop = Shutdown()
    times: deque[float] = deque(maxlen=100_000)
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            times.append(time.monotonic())

    with Node("cli", tool_config(args)) as node:
        node.subscribe_raw(args.key, on_sample)
        reports = 0
        while not stop.is_set() and (not args.reports or reports < args.reports):
            if stop.wait(args.window):
                break
            now = time.monotonic()
            with lock:
                recent = [t for t in times if now - t <= args.window]
            rate = (len(recent) - 1) / (recent[-1] - recent[0]) if len(recent) > 1 else 0.0
            out.write(
                json.dumps(
                    {
                        "key": args.key,
                        "rate_hz": round(rate, 2),
                        "samples": len(recent),
                        "window_s": args.window,
                    }
                )
                + "\n"
            )
            out.flush()
            reports += 1
    return 0


def cmd_list(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    counts: dict[str, int] = defaultdict(int)
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            counts[str(sample.key_expr)] += 1

    cfg = tool_config(args)
    with Node("cli", cfg) as node:
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
        out.write(f"{'KEY':<28} {'TYPE':<16} {'RATE (Hz)':>9}\n")
        for r in rows:
            out.write(f"{r['key']:<28} {r['type']:<16} {r['rate_hz']:>9}\n")
    return 0


def cmd_call(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    try:
        call_args = json.loads(args.args) if args.args else {}
    except json.JSONDecodeError as e:
        out.write(json.dumps({"error": "bad_request", "message": f"arguments: {e}"}) + "\n")
        return 1
    if not isinstance(call_args, dict):
        out.write(
            json.dumps({"error": "bad_request", "message": "arguments must be a JSON object"})
            + "\n"
        )
        return 1
    with Node("cli", tool_config(args)) as node:
        try:
            reply = node.call(args.service, args.method, call_args, timeout_s=args.timeout)
        except RpcError as e:
            out.write(json.dumps({"error": e.code, "message": e.message}) + "\n")
            return 1
        except Unavailable as e:
            out.write(json.dumps({"error": "unavailable", "message": str(e)}) + "\n")
            return 2
    out.write(json.dumps(codec.jsonable(reply), ensure_ascii=False) + "\n")
    return 0


def cmd_alive(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    with Node("cli", tool_config(args)) as node:
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


def add_parsers(sub: Any) -> None:
    """Register `topic`, `call` and `alive` on the top-level subparsers."""
    topic = sub.add_parser("topic", help="inspect streams: list, echo, hz")
    tsub = topic.add_subparsers(dest="topic_cmd", required=True)
    p = tsub.add_parser("list", help="keys seen, with their rates")
    p.add_argument("--duration", type=float, default=2.0, help="seconds to listen")
    p.add_argument("--json", action="store_true")
    add_node_args(p)
    p.set_defaults(func=cmd_list)
    p = tsub.add_parser("echo", help="decoded payloads as JSON lines (bytes summarized)")
    p.add_argument("key")
    p.add_argument("--count", "-n", type=int, default=0, help="stop after N samples")
    p.add_argument("--timeout", type=float, default=0.0, help="give up after S seconds")
    add_node_args(p)
    p.set_defaults(func=cmd_echo)
    p = tsub.add_parser("hz", help="the delivered rate of a key")
    p.add_argument("key")
    p.add_argument("--window", type=float, default=1.0)
    p.add_argument("--reports", type=int, default=0, help="stop after N reports")
    add_node_args(p)
    p.set_defaults(func=cmd_hz)

    p = sub.add_parser("call", help="call a method: telerobot call puma status '{}'")
    p.add_argument("service")
    p.add_argument("method")
    p.add_argument("args", nargs="?", default="{}", help="arguments as a JSON object")
    p.add_argument("--timeout", type=float, default=5.0)
    add_node_args(p)
    p.set_defaults(func=cmd_call)

    p = sub.add_parser("alive", help="which services are up (liveliness tokens)")
    p.add_argument("--timeout", type=float, default=1.0)
    p.add_argument("--json", action="store_true")
    add_node_args(p)
    p.set_defaults(func=cmd_alive)
