"""The bench's child processes: the router and the real services, spawned and always stopped.

Children are started with `subprocess` (fork + exec: never a bare fork of a process that has
opened Zenoh, ZENOH_NOTES.md pitfall 3), each in a session of its own with its output in
`<logs>/<name>.log`. `stop()` and `close()` send SIGTERM to the child's process group, wait,
then SIGKILL: no child survives the bench, whatever ends it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from services.tools.bench.cpu import cpu_by_group

STOP_TIMEOUT_S = 5.0
POLL_S = 0.02


class ChildFailed(RuntimeError):
    """A child exited while the bench still needed it (see its log)."""


@dataclass
class Child:
    """One running child: its name, argv, process and log file."""

    name: str
    argv: list[str]
    proc: subprocess.Popen[bytes]
    log_path: Path
    log: IO[bytes]
    log_start: int = 0
    """Offset in the log where this run's own output begins (after the bench's header)."""

    def alive(self) -> bool:
        return self.proc.poll() is None

    def output(self) -> str:
        """What this run of the child has written so far."""
        self.log.flush()
        try:
            with self.log_path.open("rb") as f:
                f.seek(self.log_start)
                return f.read().decode(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 20) -> str:
        """The last lines of the child's output (for error messages)."""
        return "\n".join(self.output().splitlines()[-lines:])


def telerobot_argv(command: str, *args: str) -> list[str]:
    """`python -m services.tools.cli.main COMMAND ARGS…` with this interpreter."""
    return [sys.executable, "-m", "services.tools.cli.main", command, *args]


class Children:
    """The bench's children. Use as a context manager: leaving it stops every child."""

    def __init__(self, logs_dir: Path) -> None:
        self.logs_dir = logs_dir
        self.children: dict[str, Child] = {}
        logs_dir.mkdir(parents=True, exist_ok=True)

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def spawn(self, name: str, argv: list[str]) -> Child:
        """Start `argv` as child `name` (a running child of that name is stopped first)."""
        if name in self.children:
            self.stop(name)
        log_path = self.logs_dir / f"{name}.log"
        log = log_path.open("ab")
        log.write(f"--- {' '.join(argv)}\n".encode())
        log.flush()
        start = log.tell()
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        try:
            proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
            )
        except OSError:
            log.close()
            raise
        child = Child(name, argv, proc, log_path, log, start)
        self.children[name] = child
        return child

    def cpu_by_child(self) -> dict[str, float]:
        """CPU time (s) each running child has used so far, with anything it started (its
        process group). A reaped child's time is in the bench's own
        `getrusage(RUSAGE_CHILDREN)` instead, so it is left out here."""
        live = {name: c.proc.pid for name, c in self.children.items() if c.alive()}
        used = cpu_by_group(live.values())
        return {name: used[pid] for name, pid in live.items()}

    def cpu_s(self) -> float:
        """CPU time (s) the running children have used so far (see `cpu_by_child`)."""
        return sum(self.cpu_by_child().values())

    def check(self, *names: str) -> None:
        """Raise ChildFailed if one of `names` (default: every child) has exited."""
        for name in names or tuple(self.children):
            child = self.children.get(name)
            if child is not None and not child.alive():
                raise ChildFailed(
                    f"{name} exited with {child.proc.returncode}; last lines of "
                    f"{child.log_path}:\n{child.tail()}"
                )

    def stop(self, name: str, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """SIGTERM the child's process group, wait up to `timeout_s`, then SIGKILL; its exit
        status (None if it was never started)."""
        child = self.children.pop(name, None)
        if child is None:
            return None
        try:
            return _terminate(child.proc, timeout_s)
        finally:
            child.log.close()

    def close(self) -> None:
        """Stop every child, the last started first (services before the router)."""
        for name in reversed(list(self.children)):
            self.stop(name)


def _terminate(proc: subprocess.Popen[bytes], timeout_s: float) -> int:
    _signal_group(proc, signal.SIGTERM)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        _signal_group(proc, signal.SIGKILL)
        return proc.wait()


def _signal_group(proc: subprocess.Popen[bytes], sig: int) -> None:
    if proc.poll() is not None:
        return
    # The child leads its own session (start_new_session), so its group id is its pid:
    # this reaches the child and anything it started, and nothing else.
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, sig)


def wait_log(child: Child, marker: str, timeout_s: float) -> None:
    """Block until `marker` appears in the child's log (e.g. the router's "router up")."""
    deadline = time.monotonic() + timeout_s
    while True:
        if marker in child.output():
            return
        if not child.alive():
            raise ChildFailed(f"{child.name} exited before {marker!r}:\n{child.tail()}")
        if time.monotonic() >= deadline:
            raise TimeoutError(f"{child.name}: no {marker!r} after {timeout_s:g} s")
        time.sleep(POLL_S)


def wait_alive(
    kids: Children, alive: Callable[[str, float], bool], name: str, timeout_s: float
) -> None:
    """Block until `alive(name, timeout)` (a liveliness wait, e.g. `node.alive.wait`) says
    `alive/<name>` is up; raise ChildFailed as soon as a child exits, TimeoutError after
    `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not alive(name, 0.5):
        kids.check()
        if time.monotonic() > deadline:
            raise TimeoutError(f"alive/{name} never appeared within {timeout_s:g} s")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
