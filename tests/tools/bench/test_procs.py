"""The bench's view of its children: the CPU each used, with what it started."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from services.tools.bench.procs import children_cpu_s, cpu_by_child
from services.tools.cell.procs import Children, wait_log
from tests.conftest import wait_until

BEHAVES = "import time\nprint('up and ' + 'running', flush=True)\nwhile True: time.sleep(0.05)\n"
GRANDCHILD_BURNS = (
    "import subprocess, sys, time\n"
    "burn = 'import time\\nend = time.time() + 60\\nwhile time.time() < end: pass\\n'\n"
    "subprocess.Popen([sys.executable, '-c', burn])\n"
    "print('up and ' + 'running', flush=True)\n"
    "while True: time.sleep(0.05)\n"
)


def test_cpu_by_child_counts_what_a_child_started(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        parent = kids.spawn("parent", [sys.executable, "-c", GRANDCHILD_BURNS])
        idle = kids.spawn("idle", [sys.executable, "-c", BEHAVES])
        wait_log(parent, "up and running", 20.0)
        wait_log(idle, "up and running", 20.0)
        assert wait_until(lambda: cpu_by_child(kids)["parent"] >= 0.2, 20.0, poll_s=0.05)
        used = cpu_by_child(kids)
        # the sleeping parent alone would take far less: the burning grandchild is counted
        assert used["parent"] >= 0.2
        assert set(used) == {"parent", "idle"}
        assert children_cpu_s(kids) == pytest.approx(sum(cpu_by_child(kids).values()), abs=0.5)
    assert not parent.alive
