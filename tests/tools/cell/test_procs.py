"""Child processes: always stopped (SIGTERM first, SIGKILL for one that ignores it), their
output in a log, prefixed on a stream or read line by line, restarted, frozen, and waited
on."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest

from services.tools.cell.procs import Child, ChildFailed, Children, wait_alive, wait_log
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
    assert not polite.alive and not stubborn.alive
    assert kids.stop("never-started") is None
    assert "up and running" in (tmp_path / "polite.log").read_text()


def test_context_exit_stops_every_child(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        children = [kids.spawn(f"c{i}", [sys.executable, "-c", BEHAVES]) for i in range(3)]
    assert not any(c.alive for c in children)


def test_a_dead_child_is_reported_with_its_log(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        child = kids.spawn("crash", [sys.executable, "-c", "print('boom'); raise SystemExit(3)"])
        assert child.wait(20.0) is not None
        with pytest.raises(ChildFailed, match="crash exited with 3"):
            kids.check()
        with pytest.raises(ChildFailed, match="boom"):
            wait_log(child, "never printed", 5.0)


def test_wait_alive_fails_fast_on_a_dead_child(tmp_path: Path) -> None:
    with Children(tmp_path) as kids:
        child = kids.spawn("crash", [sys.executable, "-c", "raise SystemExit(4)"])
        assert child.wait(20.0) is not None
        with pytest.raises(ChildFailed, match="crash exited with 4"):
            wait_alive(kids, lambda name, timeout_s: False, "crash", 30.0)
    with Children(tmp_path) as kids, pytest.raises(TimeoutError, match="alive/x never"):
        wait_alive(kids, lambda name, timeout_s: False, "x", 0.0)
    with Children(tmp_path) as kids:
        wait_alive(kids, lambda name, timeout_s: name == "x", "x", 0.0)


def test_a_restart_appends_to_the_log_and_output_is_this_starts(tmp_path: Path) -> None:
    say = "import sys; print('run', sys.argv[1], flush=True)"
    child = Child("once", [sys.executable, "-c", say, "x"], log_dir=tmp_path)
    assert child.returncode is None and child.stop() is None and child.wait(0.0) is None
    child.start()
    assert child.wait(20.0) == 0
    child.start()
    assert child.wait(20.0) == 0
    assert child.starts == 2
    assert child.output() == "run x\n"
    whole = child.tail(10, every_start=True).splitlines()
    assert [ln.split(":")[0] for ln in whole if ln.startswith("---")] == [
        "--- start 1",
        "--- start 2",
    ]
    assert whole.count("run x") == 2


def test_a_running_child_cannot_be_started_twice(tmp_path: Path) -> None:
    child = Child("busy", [sys.executable, "-c", BEHAVES], log_dir=tmp_path).start()
    try:
        with pytest.raises(RuntimeError, match="already running"):
            child.start()
    finally:
        assert child.stop() == -15


def test_freeze_stops_a_child_of_our_group_and_thaw_resumes_it(tmp_path: Path) -> None:
    ticks = "import time\nwhile True:\n    print('tick', flush=True)\n    time.sleep(0.01)\n"
    child = Child("ticker", [sys.executable, "-c", ticks], log_dir=tmp_path, own_group=False)
    child.start()
    try:
        assert wait_until(lambda: "tick" in child.output(), 20.0)
        child.freeze()
        assert wait_until(lambda: _state(child.pid) == "T", 5.0, what="the child stopped")
        child.thaw()
        assert wait_until(lambda: _state(child.pid) != "T", 5.0, what="the child running")
    finally:
        child.kill()
    assert child.returncode == -9


def _state(pid: int) -> str:
    """The process state letter of /proc/<pid>/stat (T: stopped)."""
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rpartition(")")[2].split()[0]


def test_prefixed_output_names_the_child_and_keeps_its_last_line(tmp_path: Path) -> None:
    out = io.StringIO()
    code = "print('hello'); print('bad key: arm.port', flush=True); print()"
    child = Child("arm", [sys.executable, "-c", code], out=out).start()
    assert child.wait(20.0) == 0
    child.join_output()
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("[arm] started pid ") and lines[0].endswith("(start #1)")
    assert lines[1:3] == ["[arm] hello", "[arm] bad key: arm.port"]
    assert child.last_line == "bad key: arm.port"


def test_a_child_writes_to_a_log_or_a_stream_never_both(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="exactly one"):
        Child("x", ["true"])
    with pytest.raises(ValueError, match="exactly one"):
        Child("x", ["true"], log_dir=tmp_path, out=io.StringIO())
    with pytest.raises(ValueError, match="exactly one"):
        Child("x", ["true"], out=io.StringIO(), lines=True)
    with pytest.raises(ValueError, match="lines=True"):
        Child("x", ["true"], log_dir=tmp_path, errors_apart=True)


def test_lines_are_awaited_in_order_and_standard_error_kept_apart() -> None:
    code = (
        "import sys\n"
        "print('one'); print('two', flush=True)\n"
        "print('oops', file=sys.stderr, flush=True)\n"
        "print('three')\n"
    )
    child = Child("lines", [sys.executable, "-c", code], lines=True, errors_apart=True).start()
    try:
        assert child.expect("two", 20.0) == "two"
        assert child.expect(lambda s: s == "one", 20.0) == "one"  # read already: still found
        assert child.rest(20.0) == ["one", "two", "three"]
        assert child.wait(20.0) == 0
        with pytest.raises(AssertionError, match="ended"):
            child.expect("four", 20.0)  # the output has ended: at once, not at the deadline
    finally:
        child.stop()
    assert child.errors == ["oops"]


def test_a_line_that_never_comes_fails_at_the_deadline_and_names_what_came() -> None:
    child = Child("quiet", [sys.executable, "-c", BEHAVES], lines=True).start()
    try:
        child.expect("up and running", 20.0)
        with pytest.raises(AssertionError, match=r"no line matching 'never'.*up and running"):
            child.expect("never", 0.5)
    finally:
        assert child.stop() == -15
    assert child.proc is not None and child.proc.stdout is not None
    assert child.proc.stdout.closed
