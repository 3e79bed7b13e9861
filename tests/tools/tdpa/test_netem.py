"""The energy exchange over a real bad link: network namespaces whose traffic is delayed,
jittered and dropped by the kernel's `tc netem` where it has one, else by the userspace delay
line (services/tools/tdpa/delayline.py, in a namespace between the two; it keeps each
direction in order where netem would reorder under jitter).

The robot side (in its namespace) echoes every `robot/passivity/master` it receives as a
`robot/passivity/slave` carrying the same `e_in` and `t_ns`; the operator side (in the other)
publishes a growing `e_in` at 200 Hz and measures, on its own clock, how late each echo
comes back. With 100 ms round trip, 10 % jitter and 1 % loss each way, the echoes must come
back no sooner than the link allows, and the energy the master receives must never go back
(latest-wins keeps the newest), as `RemoteEnergy` assumes. Skipped with the reason where the
namespaces cannot be made (not root, no iproute2, neither netem nor /dev/net/tun, refused).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys

import pytest

from services.tools.tdpa.netem import ROBOT_IP, LinkShape, in_ns, netem_link, unavailable
from tests.bus.test_router import spawned
from tests.conftest import free_port

pytestmark = [pytest.mark.system, pytest.mark.timeout(90)]

RTT_MS = 100.0

ROBOT = r"""
import sys, time
from dataclasses import replace
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.node import Node
endpoint, run_s = sys.argv[1], float(sys.argv[2])
with Node("robot", NodeConfig(mode="peer", listen=(endpoint,))) as node:
    pub = node.publisher(keys.PASSIVITY_SLAVE)
    node.subscribe(keys.PASSIVITY_MASTER, lambda m: pub.put(replace(m, side="slave")))
    node.announce()
    print("ready", flush=True)
    time.sleep(run_s)
"""

OPERATOR = r"""
import json, sys, time, threading
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import PassivityState
from services.bus.node import Node
endpoint, n = sys.argv[1], int(sys.argv[2])
rtts, seen = [], []
lock = threading.Lock()
def echo(m):
    with lock:
        rtts.append((time.time_ns() - m.t_ns) / 1e6)
        seen.append(m.e_in)
with Node("operator", NodeConfig(mode="peer", connect=(endpoint,))) as node:
    pub = node.publisher(keys.PASSIVITY_MASTER)
    latest = node.latest(keys.PASSIVITY_SLAVE)
    node.subscribe(keys.PASSIVITY_SLAVE, echo)
    assert node.alive.wait("robot", 20), node.alive.names()
    newest = []
    for k in range(1, n + 1):
        pub.put(PassivityState(seq=k, t_ns=time.time_ns(), master="m1", engage=1, side="master",
                               enabled=True, e_in=k * 1e-3, e_out=0.0, dissipated_j=0.0,
                               gain=0.0, active_steps=0))
        got = latest.read()
        if got is not None:
            newest.append(got[0].e_in)
        time.sleep(0.005)
    time.sleep(0.5)
    with lock:
        print(json.dumps({"rtts": rtts, "seen": seen, "newest": newest}), flush=True)
"""


def test_energy_exchange_over_a_netem_link() -> None:
    reason = unavailable()
    if reason:
        pytest.skip(reason)
    port = free_port()
    endpoint = f"tcp/{ROBOT_IP}:{port}"
    try:
        ctx = netem_link(LinkShape(round_trip_ms=RTT_MS, jitter=0.1, loss=0.01))
        link = ctx.__enter__()
    except RuntimeError as e:
        pytest.skip(f"network namespace setup refused: {e}")
    try:
        argv = in_ns(link.robot, sys.executable, "-c", ROBOT, endpoint, "30")
        with spawned(argv, merge_stderr=False) as robot:
            assert robot.expect(lambda _: True).strip() == "ready", robot.errors
            done = subprocess.run(
                in_ns(link.operator, sys.executable, "-c", OPERATOR, endpoint, "400"),
                capture_output=True,
                text=True,
                timeout=60,
                check=False,
            )
        assert done.returncode == 0, done.stderr[-2000:]
        out = json.loads(done.stdout.strip().splitlines()[-1])
    finally:
        ctx.__exit__(None, None, None)
    rtts, newest = out["rtts"], out["newest"]
    assert len(rtts) > 200  # most came back (1 % loss each way, TCP retransmits)
    assert min(rtts) >= 0.75 * RTT_MS  # never sooner than the link allows (jitter 10 %)
    assert statistics.median(rtts) < RTT_MS + 100.0
    assert newest == sorted(newest)  # the energy the master uses never goes back
    assert newest[-1] > 0.0
