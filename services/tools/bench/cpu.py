"""Where the CPUs went during a run: the bench's own processes, each service, and the rest.

A benchmark on a shared machine measures the other tenants too. The machine's non-idle CPU
time comes from /proc/stat (user, nice, system, irq, softirq and steal — time the
hypervisor gave to other guests); the bench's own is `getrusage` of this process and of
its reaped children, plus what its live children have used so far (/proc/<pid>/stat, given
as `live_children_s`). The difference is what other processes took: reported with the
results, never subtracted from them.

Per service, the CPU a child used over a window is the utime + stime of every live process
in its process group (each child leads a session of its own, so its group is the service
and anything it started) read from /proc at both ends: `cpu_by_group` once per instant,
`percent_of_core` between two instants. 100 % is one core busy for the whole window.
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Collection, Mapping, Sequence
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


def parse_pid_stat(text: str, ticks_per_s: float) -> tuple[int, float]:
    """(process group id, utime + stime in s) from one /proc/<pid>/stat line."""
    # Fields after the parenthesised command name (which may hold spaces): pgrp is the 5th
    # field of the line, utime and stime the 14th and 15th — the 3rd, 12th and 13th after it.
    rest = text[text.rfind(")") + 2 :].split()
    return int(rest[2]), (int(rest[11]) + int(rest[12])) / ticks_per_s


def _ticks_per_s() -> float:
    return float(os.sysconf("SC_CLK_TCK"))


def process_cpu_s(pid: int) -> float:
    """User + system CPU time (s) of process `pid`, all its threads; 0 if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            text = f.read()
    except OSError:
        return 0.0
    return parse_pid_stat(text, _ticks_per_s())[1]


def cpu_by_group(groups: Collection[int]) -> dict[int, float]:
    """CPU time (s) used so far by the live processes of each process group in `groups`
    (0 for a group with none), from one pass over /proc."""
    out = dict.fromkeys(groups, 0.0)
    ticks = _ticks_per_s()
    try:
        pids = [d for d in os.listdir("/proc") if d.isdigit()]
    except OSError:
        return out
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                text = f.read()
        except OSError:  # exited between the listing and the read
            continue
        pgrp, used_s = parse_pid_stat(text, ticks)
        if pgrp in out:
            out[pgrp] += used_s
    return out


def percent_of_core(
    before: Mapping[str, float], after: Mapping[str, float], wall_s: float
) -> dict[str, float]:
    """Per name: the CPU it used between two readings, in % of one core over `wall_s`.
    Names missing at either end are left out (a service that started or stopped inside
    the window would be misread); clock-tick jitter below zero is clamped."""
    if wall_s <= 0:
        return {}
    return {
        name: max(after[name] - before[name], 0.0) / wall_s * 100.0
        for name in before
        if name in after
    }


def budget_sum(pct: Mapping[str, float], names: Sequence[str]) -> float | None:
    """The sum of `names`' shares, or None when one of them was not measured (a partial sum
    would pass for a whole one)."""
    if any(n not in pct for n in names):
        return None
    return sum(pct[n] for n in names)


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
