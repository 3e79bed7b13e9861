"""Services as separate processes, for the fault suite: a router and the real services in
simulation, each a `services.tools.cell.procs.Child` (spawned, never forked), killed in
`finally`.

Every process is `python -m services.tools.cli.main <svc> --connect tcp/127.0.0.1:PORT --listen
tcp/127.0.0.1:0`: the router is on a free loopback port of this test only, and a peer's own
listener (which Zenoh would otherwise open on every interface) stays on loopback. Output
goes to a log file per process so a failing test can show what the process said.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path

from services.tools.cell.ports import port_open
from services.tools.cell.procs import Child, telerobot_argv
from tests.conftest import free_port, wait_until

REPO = Path(__file__).resolve().parents[2]
LOOPBACK_LISTEN = "tcp/127.0.0.1:0"
"""A peer's own listener: loopback, any free port (peers mesh through it)."""
STOP_TIMEOUT_S = 10.0


def service_argv(service: str, endpoint: str, *extra: str) -> list[str]:
    """`telerobot <service>` as a peer connected to the router at `endpoint`."""
    return telerobot_argv(service, "--connect", endpoint, "--listen", LOOPBACK_LISTEN, *extra)


def router_argv(endpoint: str) -> list[str]:
    return telerobot_argv("router", "--listen", endpoint)


def proc(name: str, argv: Sequence[str], log_dir: Path) -> Child:
    """A child run from the repository, in our process group (signals reach its pid only),
    given `STOP_TIMEOUT_S` to stop; not started."""
    return Child(
        name, argv, log_dir=log_dir, cwd=REPO, own_group=False, stop_timeout_s=STOP_TIMEOUT_S
    )


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
        self.router = proc("router", router_argv(self.endpoint), log_dir)
        self.procs: dict[str, Child] = {}

    def start_router(self, timeout_s: float = 30.0) -> None:
        """Start (or restart) the router and wait until its port accepts connections."""
        self.router.start()
        if not wait_until(lambda: port_open(self.port), timeout_s, 0.05):
            raise RuntimeError(f"the router is not listening\n{self.router.tail(every_start=True)}")

    def add(self, name: str, service: str, *extra: str) -> Child:
        return self.add_argv(name, service_argv(service, self.endpoint, *extra))

    def add_argv(self, name: str, argv: Sequence[str]) -> Child:
        child = proc(name, argv, self.log_dir)
        self.procs[name] = child
        return child

    def __getitem__(self, name: str) -> Child:
        return self.procs[name]

    def crashed(self) -> dict[str, int | None]:
        """Processes that were started and have ended (name → exit code)."""
        return {
            n: p.returncode for n, p in self.procs.items() if p.proc is not None and not p.alive
        }

    def logs(self, lines: int = 20) -> str:
        procs = [self.router, *self.procs.values()]
        parts = [f"== {p.name} ==\n{p.tail(lines, every_start=True)}" for p in procs]
        return "\n".join(parts)

    def close(self) -> None:
        for child in [*reversed(self.procs.values()), self.router]:
            with contextlib.suppress(OSError):
                child.kill()
