"""Measure the force service's CPU: per sample (the sampling thread) and for the process.

Not a test (pytest does not collect it). Run from a worktree:

    nice -n 10 .venv/bin/python -m tests.control.force.measure_cpu --seconds 10

This process runs `ForceService` (sim sensor, 1 kHz, the default config) on a Zenoh peer
listening on a free loopback port; a child process connects to it, publishes `robot/state`
at 100 Hz (an idle arm's rate: the arm at qn) and subscribes to `robot/force`, so every
sample is really sent. Reported:

- `sample_cpu_us`: CPU time of the sampling thread (/proc/self/task/<tid>/stat) per sample;
- `process_cpu_pct`: CPU time of this whole process (`os.times()`) over the wall time, in
  % of one core (the Zenoh runtime's threads included), and per sample
  (`process_cpu_us_per_sample`: comparable when a loaded machine cuts the rate);
- `kernel_us`: per-sample cost of the acquire step alone (sim read, eq. 4, compensation,
  bias, the sample's bytes), timed in a tight loop on this thread; `put_us`: the Zenoh put;
- `sleep_floor_us`: CPU per tick of an empty Python loop sleeping to 1 ms deadlines, taken
  just before, the floor under `sample_cpu_us` on this machine at this load;
- `threads_pct`: CPU per thread name (Zenoh's tx/rx runtime threads beside "python");
- the sampler's own counters (samples, overruns, late_max_us) and the load average, since
  the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import Any

from services.bus.node import Node
from services.control.force.config import ForceConfig
from services.control.force.service import ForceService
from tests.conftest import Net

CHILD = r"""
import sys, time, threading
from services.bus import keys
from services.bus.config import NodeConfig
from services.bus.messages import RobotState, vec
from services.bus.node import Node
from services.control.arm.puma560 import DEFAULT_eMt, Puma560, qn

endpoint, seconds = sys.argv[1], float(sys.argv[2])
kin = Puma560()
oMt, oMe = kin.fk_tool(qn, DEFAULT_eMt), kin.fk_flange(qn)
got = [0]
with Node("measure", NodeConfig(mode="peer", connect=(endpoint,))) as n:
    n.subscribe(keys.FORCE, lambda s: got.__setitem__(0, got[0] + 1))
    pub = n.publisher(keys.STATE)
    end = time.monotonic() + seconds
    seq = 0
    while time.monotonic() < end:
        seq += 1
        pub.put(RobotState(seq=seq, t_ns=time.time_ns(), status="ready", q=vec(qn),
            tool_p=vec(oMt.translation), tool_R=vec(oMt.rotation),
            flange_p=vec(oMe.translation), flange_R=vec(oMe.rotation), engage=0, cmd_seq=0))
        time.sleep(0.01)
print(got[0])
"""

CLK_TCK = os.sysconf("SC_CLK_TCK")


def thread_cpu_s(tid: int) -> float:
    """User + system CPU seconds of one thread of this process."""
    with open(f"/proc/self/task/{tid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def threads_cpu_s() -> dict[str, float]:
    """CPU seconds of every thread of this process, by thread name (summed per name)."""
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                name = f.read().strip()
            cpu = thread_cpu_s(int(tid))
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + cpu
    return out


def process_cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def kernel_us(svc: ForceService, n: int = 20_000) -> float:
    """Per-sample cost of acquire + encode, in a tight loop (sampling stopped)."""
    core = svc.core
    encode = getattr(svc, "encode_sample", None)
    t0 = time.thread_time_ns()
    for _ in range(n):
        s = core._acquire()
        if s is not None and encode is not None:
            encode(s)
    return (time.thread_time_ns() - t0) / n / 1e3


def put_us(svc: ForceService, n: int = 5_000) -> float:
    """Per-sample cost of the Zenoh put of one sample's bytes, in a tight loop."""
    sample = svc.core.latest
    assert sample is not None
    publish = svc._publish
    t0 = time.thread_time_ns()
    for _ in range(n):
        publish(sample)
    return (time.thread_time_ns() - t0) / n / 1e3


def sleep_floor_us(n: int = 2_000) -> float:
    """CPU per tick of an empty loop sleeping to 1 ms deadlines: the floor of any 1 kHz
    Python thread on this machine now (timer wake-up, GIL, cold caches)."""
    t0 = time.thread_time_ns()
    deadline = time.perf_counter_ns()
    for _ in range(n):
        deadline += 1_000_000
        remaining = deadline - time.perf_counter_ns()
        if remaining > 0:
            time.sleep(remaining / 1e9)
    return (time.thread_time_ns() - t0) / n / 1e3


def measure(seconds: float) -> dict[str, Any]:
    floor = sleep_floor_us()
    net = Net()
    node = Node("force", net.config(listen=True))
    svc = ForceService(node, ForceConfig(seed=1))
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, net.endpoint, str(seconds + 2.0)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 20.0
        while svc.core.latest is None:  # the first robot/state gives the sim sensor a pose
            if time.monotonic() > deadline:
                raise RuntimeError("no force sample within 20 s")
            time.sleep(0.05)
        time.sleep(1.0)  # past start-up (imports, link set-up); not synchronisation
        tid = svc.core.sampler.native_id
        st0 = svc.core.sampler.stats()
        by0 = threads_cpu_s()
        th0, pr0, w0 = thread_cpu_s(tid), process_cpu_s(), time.monotonic()
        time.sleep(seconds)
        th1, pr1, w1 = thread_cpu_s(tid), process_cpu_s(), time.monotonic()
        by1 = threads_cpu_s()
        st1 = svc.core.sampler.stats()
        n = st1.samples - st0.samples
        out: dict[str, Any] = {
            "seconds": round(w1 - w0, 2),
            "samples": n,
            "rate_hz": round(n / (w1 - w0), 1),
            "overruns": st1.overruns - st0.overruns,
            "late_max_us": round(st1.late_max_us, 1),
            "sample_cpu_us": round((th1 - th0) / max(n, 1) * 1e6, 1),
            "process_cpu_pct": round((pr1 - pr0) / (w1 - w0) * 100.0, 1),
            "process_cpu_us_per_sample": round((pr1 - pr0) / max(n, 1) * 1e6, 1),
            "sleep_floor_us": round(floor, 1),
            "loadavg": os.getloadavg(),
            "threads_pct": {
                k: round((v - by0.get(k, 0.0)) / (w1 - w0) * 100.0, 1)
                for k, v in sorted(by1.items(), key=lambda kv: -kv[1] + by0.get(kv[0], 0.0))
                if v - by0.get(k, 0.0) > 0.0
            },
        }
        svc.core.rpc_sensor_stop({})
        svc.core.sensor.open()
        out["kernel_us"] = round(kernel_us(svc), 1)
        out["put_us"] = round(put_us(svc), 1)
        svc.core.sensor.close()
    finally:
        svc.close()
        node.close()
        received, _ = child.communicate(timeout=30)
    out["received_by_child"] = int(received.strip() or 0)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=10.0)
    args = p.parse_args()
    print(json.dumps(measure(args.seconds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
