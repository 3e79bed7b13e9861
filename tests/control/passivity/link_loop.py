"""The whole bilateral loop split over a link: the robot side in one process, the operator in
another (a helper for tests/control/passivity/test_link_loop.py; not a test module).

    python -m tests.control.passivity.link_loop robot ENDPOINT PASSIVITY WATCHDOG_MS
    python -m tests.control.passivity.link_loop operator ENDPOINT PASSIVITY RATE_HZ

The robot side (puma, force, decision and a recording console, `full_loop.build`) listens on
ENDPOINT, puts the arm above the table and prints `ready`; it then reads `start T_NS` (when
the operator began) and `stop HOLD_FROM_S HOLD_TO_S` on its standard input and prints the
run's `full_loop.metrics` as one JSON line. The operator side (a master station with the
simulated haptic operator, engaged at once) connects to ENDPOINT, prints `start T_NS`, runs
the press–hold–release and prints its port's final figures as one JSON line. Run inside
two network namespaces, everything between them crosses the link.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace

from services.bus.config import NodeConfig
from services.bus.node import Node
from services.control.master.config import MasterConfig
from services.control.master.haptic_sim import SimHapticMaster
from services.control.master.service import MasterService
from tests.conftest import Net
from tests.control.passivity import full_loop as fl

APPROACH_S, HOLD_S, RELEASE_S = 2.0, 4.0, 1.0
DEPTH_M = 0.1
LEASE_MS = 2000
"""The longest link lease the contract allows (PROTOCOL.md §5). The default 1 s does not
outlast a TCP retransmission at 700 ms round trip: the master's liveliness token lapses and
the decision holds (measured)."""


class LinkNet(Net):
    """`Net` with the longest lease."""

    def config(self, listen: bool = False) -> NodeConfig:
        return replace(super().config(listen), lease_ms=LEASE_MS)


def robot(endpoint: str, passivity: bool, watchdog_ms: float) -> None:
    net = LinkNet()
    net.endpoint = endpoint  # the first node (the puma's) listens on the link
    loop = fl.build(net, passivity=passivity, watchdog_ms=watchdog_ms, state_stale_ms=watchdog_ms)
    try:
        print("ready", flush=True)
        start = sys.stdin.readline().split()
        assert start and start[0] == "start", start
        loop.t_start_ns = int(start[1])
        stop = sys.stdin.readline().split()
        assert stop and stop[0] == "stop", stop
        m = fl.metrics(loop, float(stop[1]), float(stop[2]))
        with loop.trace.lock:
            m["puma_cmds"] = float(loop.trace.puma_cmds)
            events = list(loop.trace.events)
        tdpa = loop.decision.passivity
        if tdpa is not None:
            m["slave_recovered_j"] = tdpa.pc.recovered_j
            m["slave_clipped_j"] = tdpa.pc.clipped_j
        print(json.dumps({"metrics": m, "events": events[-20:]}), flush=True)
    finally:
        loop.close()
        net.close()


def operator(endpoint: str, passivity: bool, rate_hz: float) -> None:
    node = Node(
        "master", NodeConfig(mode="peer", connect=(endpoint,), lease_ms=LEASE_MS), instance="op"
    )
    try:
        assert node.alive.wait("decision", 30.0), node.alive.names()
        cfg = MasterConfig(
            master_id="op", device="haptic_sim", passivity=passivity, rate_hz=rate_hz
        )
        device = SimHapticMaster(
            depth_m=DEPTH_M, approach_s=APPROACH_S, hold_s=HOLD_S, release_s=RELEASE_S
        )
        t0 = time.time_ns()
        station = MasterService(node, cfg, device=device)
        print(f"start {t0}", flush=True)
        end = t0 + int((APPROACH_S + HOLD_S + RELEASE_S + 0.5) * 1e9)
        try:
            fl.wait_until(lambda: time.time_ns() >= end, APPROACH_S + HOLD_S + RELEASE_S + 5.0)
            tdpa = station.passivity
            out = {"master_ticks": float(station.ticks)}
            if tdpa is not None:
                out |= {
                    "master_in_j": tdpa.pc.observer.e_in,
                    "master_out_j": tdpa.pc.observer.e_out,
                    "slave_in_seen_j": tdpa.pc.remote.e_in,
                }
            print(json.dumps(out), flush=True)
        finally:
            station.close()
    finally:
        node.close()


def main(argv: list[str]) -> None:
    role, endpoint, passivity = argv[0], argv[1], argv[2] == "1"
    if role == "robot":
        robot(endpoint, passivity, float(argv[3]))
    elif role == "operator":
        operator(endpoint, passivity, float(argv[3]))
    else:
        raise SystemExit(f"unknown role {role!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
