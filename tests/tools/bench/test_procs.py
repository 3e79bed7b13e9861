"""Children are always stopped: SIGTERM first, SIGKILL for one that ignores it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from services.tools.bench.procs import ChildFailed, Children, wait_alive, wait_log
from tests.conftest import wait_until

IGNORES_TERM = (
    "import signal, sys, time\n"
    "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    "print('up and ' + 'running', flush=True)\n"
    "while True: time.sleep(0.05)\n"
)
BEHAVES = "import time\nprint('up and ' + 'running', flush=True)\nwhile True: time.sleep(0.05)\n"


def test_stop_terminates_and_kills_the_stubborn(tmp_path: Path) -> None:
    kids = Children(tmp_path)
    polite = kids.spawn("polite", [sys.executable, "-c", BEHAVES])
    stubborn = kids.spawn("stubborn", [sys.executable, "-c", IGNORES_TERM])
    wait_log(polite, "up and running", 20.0)
    wait_log(stubborn, "up and running", 20.0)
    assert kids.stop("polite") == -15  # SIGTERM
    assert kids.stop("stubborn", timeout_s=0.3) == -9  # ignored SIGTERM, so SIGKILL
    assert polite.proc.poll() is not None and stubborn.proc.poll() is not None
    assert kids.stop("never-started") is None
    assert "up and running" in (tmp_path / "polite.log").read_text()


def test_context_exit_stops_every_child(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        procs = [kids.spawn(f"c{i}", [sys.executable, "-c", BEHAVES]).proc for i in range(3)]
    assert all(p.poll() is not None for p in procs)


def test_a_dead_child_is_reported_with_its_log(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        child = kids.spawn("crash", [sys.executable, "-c", "print('boom'); raise SystemExit(3)"])
        child.proc.wait(timeout=20.0)
        with pytest.raises(ChildFailed, match="crash exited with 3"):
            kids.check()
        with pytest.raises(ChildFailed, match="boom"):
            wait_log(child, "never printed", 5.0)


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
        assert wait_until(lambda: kids.cpu_by_child()["parent"] >= 0.2, 20.0, poll_s=0.05)
        used = kids.cpu_by_child()
        # the sleeping parent alone would take far less: the burning grandchild is counted
        assert used["parent"] >= 0.2
        assert set(used) == {"parent", "idle"}
        assert kids.cpu_s() == pytest.approx(sum(kids.cpu_by_child().values()), abs=0.5)
    assert parent.proc.poll() is not None


def test_wait_alive_fails_fast_on_a_dead_child(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        child = kids.spawn("crash", [sys.executable, "-c", "raise SystemExit(4)"])
        child.proc.wait(timeout=20.0)
        with pytest.raises(ChildFailed, match="crash exited with 4"):
            wait_alive(kids, lambda name, timeout_s: False, "crash", 30.0)
    with Children(tmp_path) as kids, pytest.raises(TimeoutError, match="alive/x never"):
        wait_alive(kids, lambda name, timeout_s: False, "x", 0.0)
    with Children(tmp_path) as kids:
        wait_alive(kids, lambda name, timeout_s: name == "x", "x", 0.0)
