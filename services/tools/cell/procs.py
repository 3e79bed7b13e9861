"""Child processes: the router and the services run as real processes, always stopped.

Children are started with `subprocess` (fork + exec: never a bare fork of a process that has
opened Zenoh, ZENOH_NOTES.md pitfall 3), with `PYTHONUNBUFFERED=1`. A `Child`'s output goes
to a log file, `<log_dir>/<name>.log` (one header line per start; `output()` is this
start's), or, given `out`, line by line to a shared stream prefixed with its name (`telerobot
up`), or, with `lines=True`, to the caller line by line: `expect()` waits for a line with a
deadline, `rest()` for the end (the tests; standard error apart in `errors` with
`errors_apart=True`). `start()` may be called again once it has ended: a restart reuses the
argv and appends to the same log.

By default a child leads a session of its own and every signal goes to its process group:
it reaches the child and anything it started, and nothing else. `own_group=False` keeps it
in ours and signals its pid only (the fault suite freezes one process). `stop()` sends
SIGTERM, waits, then SIGKILL; `Children` holds a run's children by name and stops every one
when it is left, the last started first: no child survives whatever ends the run.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import io
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO

STOP_TIMEOUT_S = 5.0
POLL_S = 0.02

#: held while a whole line is written: children's pump threads and the launcher's (or the
#: demo's) own output share one stream, and a line must never be cut by another's.
OUT_LOCK = threading.RLock()
_PR_SET_PDEATHSIG = 1
_LIBC = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM it if its parent dies, even by SIGKILL, so a
    killed `up` never leaves services (and an arm proxy) running on their own. Linux only;
    the call is a plain syscall, safe between fork and exec."""
    _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


class ChildFailed(RuntimeError):
    """A child exited while the run still needed it (see its log)."""


def telerobot_argv(command: str, *args: str) -> list[str]:
    """`python -m services.tools.cli.main COMMAND ARGS…` with this interpreter."""
    return [sys.executable, "-m", "services.tools.cli.main", command, *args]


class Child:
    """One child process: `argv`, its output in `log_dir/<name>.log`, prefixed on `out`, or
    read line by line (`lines=True`; `errors_apart`: standard error in `errors`, not among
    the lines).

    cwd: where it runs (default ours). env: variables added to ours. stdin: as
    `subprocess.Popen` takes it (default inherited). own_group: a session of its own,
    signals to its process group (else to its pid). die_with_parent: SIGTERM it when this
    process dies (Linux). stop_timeout_s: how long `stop()` waits after SIGTERM, and
    `kill()` after SIGKILL.
    """

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        *,
        log_dir: Path | None = None,
        out: IO[str] | None = None,
        lines: bool = False,
        errors_apart: bool = False,
        cwd: Path | None = None,
        env: dict[str, str] | None = None,
        stdin: int | None = None,
        own_group: bool = True,
        die_with_parent: bool = False,
        stop_timeout_s: float = STOP_TIMEOUT_S,
    ) -> None:
        if (log_dir is not None) + (out is not None) + lines != 1:
            raise ValueError("a child's output goes to log_dir, to out or to lines (exactly one)")
        if errors_apart and not lines:
            raise ValueError("errors_apart is for a child read line by line (lines=True)")
        self.name = name
        self.argv = list(argv)
        self.log_path = log_dir / f"{name}.log" if log_dir is not None else None
        self.out = out
        self.cwd = cwd
        self.env = env or {}
        self.stdin = stdin
        self.own_group = own_group
        self.die_with_parent = die_with_parent
        self.stop_timeout_s = stop_timeout_s
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0
        self.started_at = 0.0
        self.log_start = 0
        """Offset in the log where this start's own output begins (after its header)."""
        #: the last non-empty line the child printed (prefixed output only; a configuration
        #: error names its key there)
        self.last_line = ""
        self.read_lines = lines
        self.errors_apart = errors_apart
        #: the lines `expect()` and `rest()` have read so far, in order (`lines=True`)
        self.lines: list[str] = []
        #: standard error's lines as they come (`errors_apart`): diagnostics for a failure
        self.errors: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._pump: threading.Thread | None = None
        self._pumps: list[threading.Thread] = []

    def start(self) -> Child:
        """Start it (again, if it has ended)."""
        if self.alive:
            raise RuntimeError(f"{self.name} is already running (pid {self.pid})")
        stdout: int | IO[bytes] = subprocess.PIPE
        with contextlib.ExitStack() as opened:
            if self.log_path is not None:
                log = opened.enter_context(self.log_path.open("ab"))
                log.write(f"--- start {self.starts + 1}: {' '.join(self.argv)}\n".encode())
                log.flush()
                self.log_start = log.tell()
                stdout = log  # the child writes its own copy; ours is closed at once
            self.proc = subprocess.Popen(
                self.argv,
                stdin=self.stdin,
                stdout=stdout,
                stderr=subprocess.PIPE if self.errors_apart else subprocess.STDOUT,
                cwd=self.cwd,
                env={**os.environ, "PYTHONUNBUFFERED": "1", **self.env},
                start_new_session=self.own_group,
                preexec_fn=_die_with_parent if self.die_with_parent else None,
            )
        self.starts += 1
        self.started_at = time.monotonic()
        if self.out is not None:
            self._pump = self._pumping(self.proc.stdout, self._copy)
            self.say(f"started pid {self.pid} (start #{self.starts})")
        elif self.read_lines:  # this start's lines only
            self.lines, self.errors, lines = [], [], queue.Queue[str | None]()
            self._queue = lines
            self._pumps = [self._pumping(self.proc.stdout, lines.put, lambda: lines.put(None))]
            if self.errors_apart:
                self._pumps.append(self._pumping(self.proc.stderr, self.errors.append))
        return self

    @staticmethod
    def _pumping(
        pipe: IO[bytes] | None,
        each: Callable[[str], object],
        done: Callable[[], object] | None = None,
    ) -> threading.Thread:
        """A thread that hands each line of `pipe` to `each`, then calls `done`."""

        def pump() -> None:
            assert pipe is not None
            # Closed at the child's end of output, not left to the collector.
            with io.TextIOWrapper(pipe, errors="replace") as stream:
                for line in stream:
                    each(line.rstrip("\n"))
            if done is not None:
                done()

        thread = threading.Thread(target=pump, daemon=True)
        thread.start()
        return thread

    def _copy(self, text: str) -> None:
        if text.strip():
            self.last_line = text.strip()
        self.say(text)

    def say(self, text: str) -> None:
        """A line on the shared output, prefixed with the child's name (prefixed output)."""
        if self.out is None:
            return
        # One lock for every child: their pump threads share one output stream.
        with OUT_LOCK:
            self.out.write(f"[{self.name}] {text}\n")
            self.out.flush()

    def join_output(self) -> None:
        """Let the pump copy what the ended child wrote last (prefixed output)."""
        if self._pump is not None:
            self._pump.join(timeout=2.0)

    def expect(self, pred: Callable[[str], bool] | str, timeout_s: float) -> str:
        """The first line so far or to come that satisfies `pred` (or starts with it), read
        within `timeout_s` (`lines=True`); AssertionError, with the lines, if none comes or
        the child's output ends first. Lines already read count too: children print in their
        own order."""
        test = pred if callable(pred) else (lambda s, p=pred: s.startswith(p))
        for line in self.lines:
            if test(line):
                return line
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(
                    f"no line matching {pred!r} from {self.argv[:4]}: {self.lines} {self.errors}"
                )
            try:
                got = self._queue.get(timeout=left)
            except queue.Empty:
                continue
            if got is None:
                self._queue.put(None)
                raise AssertionError(f"{self.argv[:4]} ended: {self.lines} {self.errors}")
            self.lines.append(got)
            if test(got):
                return got

    def so_far(self) -> list[str]:
        """Every line printed until now, without waiting (`lines=True`): what to show when
        a test gives up on something else."""
        while True:
            try:
                line = self._queue.get_nowait()
            except queue.Empty:
                return self.lines
            if line is None:
                self._queue.put(None)
                return self.lines
            self.lines.append(line)

    def rest(self, timeout_s: float) -> list[str]:
        """Every line, once the child has closed its output within `timeout_s`
        (`lines=True`); AssertionError if it is still writing."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self._queue.get(timeout=max(deadline - time.monotonic(), 0.01))
            except queue.Empty as e:
                raise AssertionError(f"{self.argv[:4]} still writing: {self.lines}") from e
            if line is None:
                self._queue.put(None)
                return self.lines
            self.lines.append(line)

    @property
    def pid(self) -> int:
        if self.proc is None:
            raise RuntimeError(f"{self.name} was never started")
        return self.proc.pid

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        """Its exit status; None while it runs or if it was never started."""
        return None if self.proc is None else self.proc.poll()

    def signal(self, sig: int) -> None:
        """Send `sig` to its process group (or its pid, `own_group=False`) if it runs."""
        if not self.alive:
            return
        with contextlib.suppress(ProcessLookupError):
            if self.own_group:
                # It leads its own session (start_new_session), so its group id is its pid.
                os.killpg(self.pid, sig)
            else:
                os.kill(self.pid, sig)

    def freeze(self) -> None:
        """SIGSTOP: the process, its threads and its Zenoh session stop dead."""
        self.signal(signal.SIGSTOP)

    def thaw(self) -> None:
        self.signal(signal.SIGCONT)

    def wait(self, timeout_s: float) -> int | None:
        """Its exit status once it has ended, None if it still runs after `timeout_s`."""
        return self._waited(timeout_s)

    def _waited(self, timeout_s: float) -> int | None:
        # `stop()` and `kill()` wait through this, whatever a subclass's `wait` does.
        if self.proc is None:
            return None
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def kill(self) -> None:
        """SIGKILL (a crash: no `finally` runs) and reap it, waiting up to `stop_timeout_s`
        (a process in uninterruptible sleep is left to end later, never waited on for good:
        the children after it must be stopped too)."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.thaw()  # a stopped process dies on SIGKILL too, but reap it promptly
            self.signal(signal.SIGKILL)
        self._waited(self.stop_timeout_s)

    def stop(self, timeout_s: float | None = None) -> int | None:
        """SIGTERM (an orderly stop), SIGKILL if it has not ended within `timeout_s`
        (default `stop_timeout_s`); its exit status (None if it was never started)."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.thaw()
            self.signal(signal.SIGTERM)
            if self._waited(self.stop_timeout_s if timeout_s is None else timeout_s) is None:
                self.kill()
        if self.read_lines:
            for pump in self._pumps:
                pump.join(timeout=self.stop_timeout_s)
            for pipe in (self.proc.stdout, self.proc.stderr):
                if pipe is not None:  # closed here, never left to the collector (a warning)
                    pipe.close()
        return self.proc.returncode

    def output(self) -> str:
        """What this start of the child has written so far (log file output)."""
        if self.log_path is None:
            return ""
        try:
            with self.log_path.open("rb") as f:
                f.seek(self.log_start)
                return f.read().decode(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 20, *, every_start: bool = False) -> str:
        """The last lines of this start's output, or of the whole log with the header of
        each start (`every_start`), for error messages."""
        if every_start and self.log_path is not None:
            try:
                text = self.log_path.read_text(errors="replace")
            except OSError:
                return ""
        else:
            text = self.output()
        return "\n".join(text.splitlines()[-lines:])


class Children:
    """A run's children by name, their output in `logs_dir`. Use as a context manager:
    leaving it stops every child."""

    def __init__(self, logs_dir: Path) -> None:
        self.logs_dir = logs_dir
        self.children: dict[str, Child] = {}
        logs_dir.mkdir(parents=True, exist_ok=True)

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def spawn(self, name: str, argv: list[str]) -> Child:
        """Start `argv` as child `name` (a running child of that name is stopped first),
        its standard input closed."""
        if name in self.children:
            self.stop(name)
        child = Child(name, argv, log_dir=self.logs_dir, stdin=subprocess.DEVNULL).start()
        self.children[name] = child
        return child

    def check(self, *names: str) -> None:
        """Raise ChildFailed if one of `names` (default: every child) has exited."""
        for name in names or tuple(self.children):
            child = self.children.get(name)
            if child is not None and not child.alive:
                raise ChildFailed(
                    f"{name} exited with {child.returncode}; last lines of "
                    f"{child.log_path}:\n{child.tail()}"
                )

    def stop(self, name: str, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """SIGTERM the child's process group, wait up to `timeout_s`, then SIGKILL; its exit
        status (None if it was never started)."""
        child = self.children.pop(name, None)
        return None if child is None else child.stop(timeout_s)

    def close(self) -> None:
        """Stop every child, the last started first (services before the router)."""
        for name in reversed(list(self.children)):
            self.stop(name)


def wait_log(child: Child, marker: str, timeout_s: float) -> None:
    """Block until `marker` appears in the child's log (e.g. the router's "router up")."""
    deadline = time.monotonic() + timeout_s
    while True:
        if marker in child.output():
            return
        if not child.alive:
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
