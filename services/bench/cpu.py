"""Where the CPUs went during a run: the bench's own processes, and everything else.

A benchmark on a shared machine measures the other tenants too. The machine's non-idle CPU
time comes from /proc/stat (user, nice, system, irq, softirq and steal — time the
hypervisor gave to other guests); the bench's own is `getrusage` of this process and of
its reaped children, plus what its live children have used so far (/proc/<pid>/stat, given
as `live_children_s`). The difference is what other processes took: reported with the
results, never subtracted from them.
"""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass

#: /proc/stat's `cpu` line: user nice system idle iowait irq softirq steal (guest is already
#: inside user)
_BUSY_FIELDS = (0, 1, 2, 5, 6, 7)
_IDLE_FIELDS = (3, 4)


@dataclass(frozen=True, slots=True)
class CpuSample:
    """CPU times (s) at one instant: machine-wide busy and total, the bench's own, wall."""

    busy_s: float
    total_s: float
    own_s: float
    wall_s: float


@dataclass(frozen=True, slots=True)
class CpuUse:
    """CPU use between two samples. `capacity_s` = CPUs × wall time; shares are of it."""

    wall_s: float
    cpus: int
    capacity_s: float
    machine_busy_s: float
    bench_s: float
    others_s: float

    @property
    def others_share(self) -> float:
        return self.others_s / self.capacity_s if self.capacity_s > 0 else 0.0

    @property
    def bench_share(self) -> float:
        return self.bench_s / self.capacity_s if self.capacity_s > 0 else 0.0

    def as_dict(self) -> dict[str, float | int]:
        return {
            "wall_s": self.wall_s,
            "cpus": self.cpus,
            "machine_busy_s": self.machine_busy_s,
            "bench_s": self.bench_s,
            "others_s": self.others_s,
            "bench_share": self.bench_share,
            "others_share": self.others_share,
        }


def parse_proc_stat(text: str, ticks_per_s: float) -> tuple[float, float]:
    """(busy_s, total_s) from the aggregate `cpu` line of /proc/stat."""
    for line in text.splitlines():
        parts = line.split()
        if parts and parts[0] == "cpu":
            values = [int(x) for x in parts[1:9]]
            values += [0] * (8 - len(values))
            busy = sum(values[i] for i in _BUSY_FIELDS)
            idle = sum(values[i] for i in _IDLE_FIELDS)
            return busy / ticks_per_s, (busy + idle) / ticks_per_s
    raise ValueError("no aggregate cpu line in /proc/stat")


def _own_s() -> float:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def process_cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process `pid`, all its threads; 0 if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            text = f.read()
    except OSError:
        return 0.0
    # Fields after the parenthesised command name (which may hold spaces): utime and stime
    # are the 14th and 15th fields of the line, the 12th and 13th after it.
    rest = text[text.rfind(")") + 2 :].split()
    return (int(rest[11]) + int(rest[12])) / float(os.sysconf("SC_CLK_TCK"))


def sample(live_children_s: float = 0.0) -> CpuSample | None:
    """Now; None where /proc/stat cannot be read (not Linux)."""
    try:
        with open("/proc/stat") as f:
            text = f.read()
        busy, total = parse_proc_stat(text, float(os.sysconf("SC_CLK_TCK")))
    except (OSError, ValueError):
        return None
    return CpuSample(busy, total, _own_s() + live_children_s, time.monotonic())


def usage(a: CpuSample, b: CpuSample, cpus: int) -> CpuUse:
    """What was used between `a` and `b` (the bench's children reaped by `b`). Clock-tick
    granularity can make a tiny negative "others"; it is clamped to zero."""
    wall = b.wall_s - a.wall_s
    busy = b.busy_s - a.busy_s
    own = b.own_s - a.own_s
    return CpuUse(
        wall_s=wall,
        cpus=cpus,
        capacity_s=cpus * wall,
        machine_busy_s=busy,
        bench_s=own,
        others_s=max(busy - own, 0.0),
    )
