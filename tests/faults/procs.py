"""Services as separate processes, for the fault suite: a router and the real services in
simulation, each spawned with `subprocess` (never forked), killed in `finally`.

Every process is `python -m services.tools.cli.main <svc> --connect tcp/127.0.0.1:PORT --listen
tcp/127.0.0.1:0`: the router is on a free loopback port of this test only, and a peer's own
listener (which Zenoh would otherwise open on every interface) stays on loopback. Output
goes to a log file per process so a failing test can show what the process said.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from tests.conftest import free_port, wait_until

REPO = Path(__file__).resolve().parents[2]
LOOPBACK_LISTEN = "tcp/127.0.0.1:0"
"""A peer's own listener: loopback, any free port (peers mesh through it)."""
STOP_TIMEOUT_S = 10.0


class Proc:
    """One child process: `argv` run from the repository, output in `log_path`.

    `start()` may be called again after the process ended (a restart reuses the argv and
    appends to the same log). Signals go to this child's pid only.
    """

    def __init__(self, name: str, argv: Sequence[str], log_dir: Path) -> None:
        self.name = name
        self.argv = list(argv)
        self.log_path = log_dir / f"{name}.log"
        self.popen: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self) -> Proc:
        if self.alive:
            raise RuntimeError(f"{self.name} is already running (pid {self.pid})")
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        with self.log_path.open("ab") as log:
            log.write(f"--- start {self.starts + 1}: {' '.join(self.argv)}\n".encode())
            log.flush()
            self.popen = subprocess.Popen(
                self.argv, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env=env
            )
        self.starts += 1
        return self

    @property
    def pid(self) -> int:
        if self.popen is None:
            raise RuntimeError(f"{self.name} was never started")
        return self.popen.pid

    @property
    def alive(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    @property
    def returncode(self) -> int | None:
        return None if self.popen is None else self.popen.poll()

    def signal(self, sig: int) -> None:
        if self.alive:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        """SIGKILL (a crash: no `finally` runs) and reap."""
        if self.popen is None:
            return
        if self.popen.poll() is None:
            self.thaw()  # a stopped process dies on SIGKILL too, but reap it promptly
            self.popen.kill()
        self.popen.wait(timeout=STOP_TIMEOUT_S)

    def terminate(self) -> int | None:
        """SIGTERM (an orderly stop), SIGKILL if it does not end in time; its exit code."""
        if self.popen is None:
            return None
        if self.popen.poll() is None:
            self.thaw()
            self.popen.terminate()
            try:
                self.popen.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(timeout=STOP_TIMEOUT_S)
        return self.popen.returncode

    def freeze(self) -> None:
        """SIGSTOP: the process, its threads and its Zenoh session stop dead."""
        self.signal(signal.SIGSTOP)

    def thaw(self) -> None:
        self.signal(signal.SIGCONT)

    def log_tail(self, lines: int = 30) -> str:
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return ""
        return "\n".join(text.splitlines()[-lines:])


def service_argv(service: str, endpoint: str, *extra: str) -> list[str]:
    """`telerobot <service>` as a peer connected to the router at `endpoint`."""
    return [
        sys.executable,
        "-m",
        "services.tools.cli.main",
        service,
        "--connect",
        endpoint,
        "--listen",
        LOOPBACK_LISTEN,
        *extra,
    ]


def router_argv(endpoint: str) -> list[str]:
    return [sys.executable, "-m", "services.tools.cli.main", "router", "--listen", endpoint]


class Cell:
    """A router on a free loopback port and named service processes around it.

    `add(name, service, *args)` declares a process (not started); `close()` kills every
    process this cell started, router last.
    """

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        log_dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.router = Proc("router", router_argv(self.endpoint), log_dir)
        self.procs: dict[str, Proc] = {}

    def start_router(self, timeout_s: float = 30.0) -> None:
        """Start (or restart) the router and wait until its port accepts connections."""
        self.router.start()
        if not wait_until(lambda: port_open(self.port), timeout_s, 0.05):
            raise RuntimeError(f"the router is not listening\n{self.router.log_tail()}")

    def add(self, name: str, service: str, *extra: str) -> Proc:
        proc = Proc(name, service_argv(service, self.endpoint, *extra), log_dir=self.log_dir)
        self.procs[name] = proc
        return proc

    def add_argv(self, name: str, argv: Sequence[str]) -> Proc:
        proc = Proc(name, argv, log_dir=self.log_dir)
        self.procs[name] = proc
        return proc

    def __getitem__(self, name: str) -> Proc:
        return self.procs[name]

    def crashed(self) -> dict[str, int | None]:
        """Processes that were started and have ended (name → exit code)."""
        return {
            n: p.returncode for n, p in self.procs.items() if p.popen is not None and not p.alive
        }

    def logs(self, lines: int = 20) -> str:
        procs = [self.router, *self.procs.values()]
        parts = [f"== {p.name} ==\n{p.log_tail(lines)}" for p in procs]
        return "\n".join(parts)

    def close(self) -> None:
        for proc in [*reversed(self.procs.values()), self.router]:
            with contextlib.suppress(OSError, subprocess.TimeoutExpired):
                proc.kill()


def port_open(port: int) -> bool:
    """Whether something accepts TCP connections on 127.0.0.1:port."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0
