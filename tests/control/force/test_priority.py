"""The five SensorThreadPriority levels on a real thread, and what is reported when refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.control.force.priority import (
    NICE_OF_LEVEL,
    PRIORITY_LEVELS,
    apply_thread_priority,
    level_of,
    read_thread_priority,
    supported,
)

REPO = Path(__file__).resolve().parents[3]
linux_only = pytest.mark.skipif(not supported(), reason="per-thread priority is Linux-only")


@pytest.mark.parametrize(
    ("policy", "nice", "level"),
    [
        ("SCHED_FIFO", 0, "highest"),
        ("SCHED_OTHER", -20, "highest"),
        ("SCHED_OTHER", -10, "highest"),
        ("SCHED_OTHER", -7, "above_normal"),
        ("SCHED_OTHER", -5, "above_normal"),
        ("SCHED_OTHER", -3, "normal"),
        ("SCHED_OTHER", 0, "normal"),
        ("SCHED_OTHER", 3, "below_normal"),
        ("SCHED_OTHER", 5, "below_normal"),
        ("SCHED_OTHER", 10, "lowest"),
        ("SCHED_OTHER", 19, "lowest"),
    ],
)
def test_applied_level_is_the_best_promise_kept(policy: str, nice: int, level: str) -> None:
    assert level_of(policy, nice) == level  # type: ignore[arg-type]


@pytest.fixture
def idle_thread() -> Iterator[int]:
    """A thread parked on an Event; yields its Linux task id."""
    stop = threading.Event()
    ready = threading.Event()
    tid: list[int] = []

    def park() -> None:
        tid.append(threading.get_native_id())
        ready.set()
        stop.wait()

    t = threading.Thread(target=park, daemon=True)
    t.start()
    ready.wait()
    yield tid[0]
    stop.set()
    t.join()


@linux_only
@pytest.mark.parametrize("level", ["lowest", "below_normal", "normal"])
def test_raising_nice_is_always_permitted(idle_thread: int, level: str) -> None:
    me = threading.get_native_id()
    my_nice = os.getpriority(os.PRIO_PROCESS, me)
    report = apply_thread_priority(idle_thread, level)  # type: ignore[arg-type]
    policy, nice, _ = read_thread_priority(idle_thread)
    assert (report.policy, report.nice) == (policy, nice)
    assert (policy, nice) == ("SCHED_OTHER", NICE_OF_LEVEL[level])  # type: ignore[index]
    assert report.applied == level
    assert report.reason == ""
    assert os.getpriority(os.PRIO_PROCESS, me) == my_nice  # that thread only


@linux_only
def test_every_level_reports_what_the_kernel_applied(idle_thread: int) -> None:
    for level in (*PRIORITY_LEVELS, "normal"):
        report = apply_thread_priority(idle_thread, level)
        policy, nice, rt = read_thread_priority(idle_thread)
        assert (report.policy, report.nice, report.rt_priority) == (policy, nice, rt)
        assert report.applied == level_of(policy, nice)
        assert report.requested == level
        if report.applied != level:
            assert report.reason  # a refusal is always explained


@linux_only
@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to try SCHED_FIFO as granted")
def test_highest_is_sched_fifo_when_permitted(idle_thread: int) -> None:
    report = apply_thread_priority(idle_thread, "highest")
    assert report.policy == "SCHED_FIFO"
    assert os.sched_getscheduler(idle_thread) == os.SCHED_FIFO
    assert report.applied == "highest"
    back = apply_thread_priority(idle_thread, "normal")
    assert os.sched_getscheduler(idle_thread) == os.SCHED_OTHER
    assert (back.applied, back.nice) == ("normal", 0)


UNPRIVILEGED = """
import json, os, threading
from services.control.force.priority import apply_thread_priority
if os.geteuid() == 0:  # become nobody, after the imports (root's Python is not readable)
    os.setgroups([])
    os.setgid(65534)
    os.setuid(65534)
out = {}
def work():
    tid = threading.get_native_id()
    for level in ("highest", "lowest", "normal"):
        out[level] = apply_thread_priority(tid, level).as_dict()
t = threading.Thread(target=work)
t.start()
t.join()
print(json.dumps(out))
"""


@linux_only
def test_unprivileged_refusals_are_reported() -> None:
    """As an ordinary user: no SCHED_FIFO, no nice below 0, no way back from `lowest`."""
    proc = subprocess.run(
        [sys.executable, "-c", UNPRIVILEGED],
        cwd=REPO,
        env={"PYTHONPATH": str(REPO), "PYTHONDONTWRITEBYTECODE": "1", "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    hi = out["highest"]
    assert hi["requested"] == "highest"
    assert hi["policy"] == "SCHED_OTHER"
    assert "SCHED_FIFO refused" in hi["reason"]
    assert hi["applied"] == level_of("SCHED_OTHER", hi["nice"])
    assert out["lowest"]["applied"] == "lowest" and out["lowest"]["nice"] == 10
    back = out["normal"]
    assert back["requested"] == "normal"
    assert back["applied"] == level_of("SCHED_OTHER", back["nice"])
    if back["nice"] > 0:  # RLIMIT_NICE (0 by default) forbids coming back
        assert back["applied"] != "normal" and "refused" in back["reason"]
