"""The method-call phase: decision and arm calls over the bus, the bare-Zenoh get→reply
floor and the XML-RPC baseline, all replying with arm's status map."""

from __future__ import annotations

from typing import Any

from services.bus import codec
from services.bus.errors import Unavailable
from services.bus.node import Node
from services.tools.bench import floor, stats
from services.tools.bench.baselines import xmlrpc_round_trips
from services.tools.bench.commands import CALL_TIMEOUT_S
from services.tools.bench.options import BenchOptions, RunResult, Say
from services.tools.bench.probes import time_calls
from services.tools.bench.report import ms_text
from services.tools.cell.procs import Children, wait_log


def _arm_status(node: Node, attempts: int = 3) -> dict[str, Any]:
    """The arm's status map (the XML-RPC baseline replies with it), retried on a lost reply."""
    lost = Unavailable("arm status: no attempt made")
    for _ in range(attempts):
        try:
            return node.call("arm", "status", {}, CALL_TIMEOUT_S)
        except Unavailable as e:
            lost = e
    raise lost


# --- method calls -------------------------------------------------------------------------


def phase_rpc(
    kids: Children, node: Node, endpoint: str, opts: BenchOptions, res: RunResult, say: Say
) -> None:
    n = opts.rpc_calls
    for key, service, method in (
        ("rpc_decision_status", "decision", "status"),
        ("rpc_decision_supervisor", "decision", "supervisor"),
        ("rpc_arm_status", "arm", "status"),
    ):
        say(f"[{key}] {n} calls of robot/{service}/rpc/{method} …")
        times = time_calls(node, service, method, n)
        res.phases[key] = {**stats.summarize(times.ms).as_dict(), "failures": times.failures}
        failed = sum(times.failures.values())
        say(
            f"    p50 {ms_text(res.phases[key]['p50'])} p99 {ms_text(res.phases[key]['p99'])}"
            + (f", {failed} failed: {times.failures}" if failed else "")
        )
        if failed:
            res.notes.append(
                f"{key}: {failed} of {n} calls failed ({times.failures}); only the answered "
                "ones are timed."
            )
    reply = _arm_status(node)
    say(f"[baseline_zenoh_query] {n} bare-Zenoh gets of a queryable replying arm's status map …")
    reply_file = opts.logs_dir / "floor-reply.msgpack"
    reply_file.write_bytes(codec.pack(reply))
    server = kids.spawn("zenoh-floor-rpc", floor.serve_argv(endpoint, reply_file))
    try:
        wait_log(server, floor.SERVING, opts.startup_timeout_s)
        got = floor.time_gets(node.session, n)
    finally:
        kids.stop("zenoh-floor-rpc")
    res.phases["baseline_zenoh_query"] = {
        "latency_ms": stats.summarize(got.ms).as_dict(),
        "calls": n,
        "failures": got.failures,
        "reply_bytes": len(codec.pack(reply)),
    }
    lat = res.phases["baseline_zenoh_query"]["latency_ms"]
    say(f"    p50 {ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}")
    say(f"[baseline_xmlrpc] {n} XML-RPC calls returning arm's status map …")
    rtt = xmlrpc_round_trips(reply, n)
    res.phases["baseline_xmlrpc"] = {"latency_ms": stats.summarize(rtt).as_dict(), "calls": n}
    lat = res.phases["baseline_xmlrpc"]["latency_ms"]
    say(f"    p50 {ms_text(lat['p50'])} p99 {ms_text(lat['p99'])}")
