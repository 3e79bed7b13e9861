"""CPU accounting: /proc/stat parsing, the split between the bench and the others."""

from __future__ import annotations

import os
import sys

import pytest

from services.tools.bench import cpu
from services.tools.bench.cpu_phases import cpu_figures
from services.tools.bench.notes import busy_note
from services.tools.bench.report import document, machine, table

STAT = """cpu  1000 10 200 5000 40 0 30 20 0 0
cpu0 500 5 100 2500 20 0 15 10 0 0
intr 123
"""


def test_parse_proc_stat() -> None:
    busy, total = cpu.parse_proc_stat(STAT, 100.0)
    # busy: user 1000 + nice 10 + system 200 + irq 0 + softirq 30 + steal 20
    assert busy == pytest.approx(12.60)
    assert total == pytest.approx(12.60 + 50.40)  # + idle 5000 + iowait 40
    with pytest.raises(ValueError):
        cpu.parse_proc_stat("intr 1\n", 100.0)


def test_usage_splits_the_machine_between_the_bench_and_the_others() -> None:
    a = cpu.CpuSample(busy_s=100.0, total_s=1000.0, own_s=1.0, wall_s=10.0)
    b = cpu.CpuSample(busy_s=112.0, total_s=1020.0, own_s=8.0, wall_s=20.0)
    u = cpu.usage(a, b, cpus=2)
    assert (u.wall_s, u.capacity_s, u.machine_busy_s, u.bench_s, u.others_s) == (
        10.0,
        20.0,
        12.0,
        7.0,
        5.0,
    )
    assert u.others_share == 0.25 and u.bench_share == 0.35
    # tick granularity: the bench may appear to use more than the machine did
    c = cpu.CpuSample(busy_s=100.5, total_s=1001.0, own_s=2.0, wall_s=11.0)
    assert cpu.usage(a, c, cpus=2).others_s == 0.0


def test_process_cpu_s_reads_this_process() -> None:
    x = 0
    for i in range(2_000_000):  # burn a little CPU so the tick counter moves
        x += i
    assert cpu.process_cpu_s(os.getpid()) > 0.0
    assert cpu.process_cpu_s(2**22 + 12345) == 0.0  # no such process


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/stat is Linux")
def test_sample_on_linux() -> None:
    s = cpu.sample(live_children_s=1.5)
    assert s is not None and s.own_s >= 1.5 and s.total_s >= s.busy_s > 0


def _use(others_share: float) -> dict[str, float | int]:
    return {"cpus": 2, "others_share": others_share, "bench_share": 0.5}


def test_busy_note_names_the_contended_phases() -> None:
    quiet = {"run": _use(0.05), "phases": {"force_alone": _use(0.05)}}
    assert busy_note(quiet) is None
    shared = {
        "run": _use(0.2),
        "phases": {"force_alone": _use(0.05), "video_vga": _use(0.42), "rpc": _use(0.16)},
    }
    note = busy_note(shared)
    assert note is not None
    assert "other processes took 20% of the 2 CPUs over the run" in note
    assert "during: video_vga 42%, rpc 16%;" in note
    assert "force_alone" not in note


def test_table_header_reports_the_cpu_split() -> None:
    settings = {"quick": False, "phase_s": 20.0, "cpu": {"run": _use(0.07), "phases": {}}}
    text = table(document({}, machine(), settings))
    assert (
        "other processes took 7% of the CPUs during the run (the bench and its services 50%)"
        in text
    )
    assert "phases of 20.0 s; arm model puma560." in text


def test_parse_pid_stat_reads_group_and_times_past_an_odd_name() -> None:
    # comm may hold spaces and parentheses: fields are counted after the last ")"
    line = "4242 (py (x) y) S 1 777 777 0 -1 4194560 10 0 0 0 250 50 3 4 20 0 9 0 1 2 3\n"
    assert cpu.parse_pid_stat(line, 100.0) == (777, pytest.approx(3.0))


def test_cpu_by_group_sums_this_process_group() -> None:
    x = 0
    for i in range(2_000_000):  # burn a little CPU so the tick counter moves
        x += i
    group = os.getpgrp()
    own = cpu.process_cpu_s(os.getpid())  # read first: CPU time only grows
    got = cpu.cpu_by_group([group, 2**22 + 12345])
    assert got[group] >= own > 0.0
    assert got[2**22 + 12345] == 0.0  # no such group


def test_percent_of_core_and_budget_sum() -> None:
    before = {"a": 1.0, "b": 2.0, "gone": 5.0}
    after = {"a": 1.5, "b": 1.99, "new": 1.0}  # b: tick jitter below zero
    pct = cpu.percent_of_core(before, after, wall_s=2.0)
    assert pct == {"a": pytest.approx(25.0), "b": 0.0}
    assert cpu.percent_of_core(before, after, wall_s=0.0) == {}
    assert cpu.budget_sum(pct, ["a", "b"]) == pytest.approx(25.0)
    assert cpu.budget_sum(pct, ["a", "gone"]) is None  # a partial sum is no sum


def test_cpu_figures_budget_sums_and_missing_services() -> None:
    names = ("router", "arm", "force", "decision", "vision", "console")  # the physics in arm
    before = dict.fromkeys(names, 100.0)
    after = {n: 100.0 + 0.1 * (i + 1) for i, n in enumerate(names)}  # 10 %, 20 %, … over 10 s
    fig = cpu_figures(before, after, bench_s=0.5, wall_s=10.0)
    assert fig["services"]["router"] == pytest.approx(1.0)
    assert fig["core_pct"] == pytest.approx(1.0 + 2.0 + 3.0 + 4.0)
    assert fig["sim_pct"] == pytest.approx(21.0)
    assert fig["bench_pct"] == pytest.approx(5.0)
    assert fig["na"] == {} and fig["window_s"] == 10.0
    del after["console"]  # stopped inside the window
    fig = cpu_figures(before, after, bench_s=0.0, wall_s=10.0)
    assert fig["core_pct"] == pytest.approx(10.0) and fig["sim_pct"] is None
    assert fig["na"]["sim_pct"] == "not running through the whole window: console"
    assert "console" in fig["na"] and "console" not in fig["services"]
