"""Process lifecycle: one `run_service()` for every service's main, and SIGINT/SIGTERM as a
stop flag, so every service runs its `finally`."""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from types import FrameType
from typing import TYPE_CHECKING, Any, Protocol

from services.bus.config import LOCAL_ROUTER, NodeConfig, add_node_args, load_deploy, node_config
from services.bus.errors import AlreadyRunning, ConfigError, ConnectFailed
from services.bus.sched import claim_cpu_share

if TYPE_CHECKING:  # zenoh is imported when a session opens: `--help` stays instant
    from services.bus.node import Node

#: services of which a cell runs one (a master: one per id): a second refuses to start
SINGLETONS = frozenset({"arm", "decision", "force", "vision", "workcell", "ros2"})

#: the exit status of a process whose configuration is wrong; `telerobot up` does not
#: restart a child that exits with it (a restart cannot mend a bad key)
CONFIG_EXIT = 2

#: after a stop signal, a process that has not exited by then dumps every thread's stack
#: to stderr and exits (status 1): an exit hang is reported, never left running.
EXIT_GRACE_S = 15.0

#: how often a main thread waiting on `Shutdown` wakes so a pending signal handler can run
SIGNAL_CHECK_S = 0.25

#: how often a service whose router does not answer yet tries again (`ServiceContext.open`)
ROUTER_RETRY_S = 1.0
#: how often it says again that it is still waiting (a wrong login looks the same)
ROUTER_REPEAT_S = 30.0


class Shutdown:
    """Set on SIGINT or SIGTERM (installed from the main thread). `wait()` sleeps until then.

    Services poll `is_set()` in their loops and leave through their `finally` blocks, which
    hold the arm and close the Zenoh session. A signal also arms a last-resort timer: a
    process still there `grace_s` (default `EXIT_GRACE_S`) later prints every thread's
    stack and exits. A process whose orderly stop takes longer by design (the launcher
    stops its children one by one) raises `grace_s` before any signal can come.
    """

    def __init__(self, install: bool = True, grace_s: float = EXIT_GRACE_S) -> None:
        self._event = threading.Event()
        self.signal: int | None = None
        self.grace_s = grace_s
        if install and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._handle)
            signal.signal(signal.SIGTERM, self._handle)

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.signal = signum
        if not self._event.is_set():
            faulthandler.dump_traceback_later(self.grace_s, exit=True)
        self._event.set()

    def set(self) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Sleep until set (True) or `timeout_s` (False), waking every `SIGNAL_CHECK_S`: a
        signal the kernel hands to another thread (a Zenoh runtime thread, say) only flags
        CPython, and the handler runs when the main thread next executes bytecode, which a
        lock wait never does until it ends."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            left = SIGNAL_CHECK_S if deadline is None else deadline - time.monotonic()
            if self._event.wait(max(0.0, min(left, SIGNAL_CHECK_S))):
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False


def setup_logging(name: str, verbose: bool = False) -> logging.Logger:
    """One log format for every service: time, level, service, message."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format=f"%(asctime)s %(levelname)-7s {name}: %(message)s",
    )
    return logging.getLogger(f"telerobot.{name}")


class Closeable(Protocol):
    def close(self) -> None: ...


@dataclass(frozen=True)
class ServiceContext:
    """What `run_service()` hands a service's `start`: its parsed arguments, the deployment
    file, the node configuration, the stop flag, its logger, and the sessions it opens.

    `deploy` and `node_config` are read when first asked for (a main that opens no session
    of its own never reads `[zenoh]`); a bad value raises ConfigError naming the key.
    Everything opened through `open()` or registered with `closing()` is closed when the
    service ends, last registered first: a service registered after its node is closed
    (holding the arm) before that node's session closes. With `await_router`, a session
    whose router does not answer is tried again until it does or the service is stopped.
    """

    name: str
    args: argparse.Namespace
    stop: Shutdown
    log: logging.Logger
    _stack: contextlib.ExitStack
    _connect: tuple[str, ...]
    await_router: bool = True

    @cached_property
    def deploy(self) -> dict[str, Any]:
        """The deployment TOML named by `--config` (empty without one)."""
        return load_deploy(getattr(self.args, "config", None))

    @cached_property
    def node_config(self) -> NodeConfig:
        """The node's configuration: the service's default router < `[zenoh]` < flags."""
        return node_config(self.args, self.deploy, connect=self._connect)

    def open(
        self,
        cfg: NodeConfig | None = None,
        name: str = "",
        instance: str = "",
        singleton: bool | None = None,
    ) -> Node:
        """Open a session (`cfg`, default `node_config`) as `name` (default the service's),
        closed when the service ends. A singleton (by default the services of `SINGLETONS`,
        and a master by its id) first makes sure no other one runs in the cell
        (`Node.claim`: `AlreadyRunning` otherwise) and then reports later contenders."""
        name = name or self.name
        node = self._stack.enter_context(self._node(name, cfg or self.node_config, instance))
        if singleton if singleton is not None else (name in SINGLETONS or name == "master"):
            node.claim()
            node.watch_claims()
        return node

    def _node(self, name: str, cfg: NodeConfig, instance: str) -> Node:
        """A Node; while its router does not answer (ConnectFailed), one warning, then a try
        every `ROUTER_RETRY_S` (`await_router`): a station started before the robot host, or
        a service that starts before its launcher's router listens, waits for it rather
        than exiting. ConnectFailed if the service is stopped meanwhile."""
        from services.bus.node import Node

        since = 0.0  # when the first try failed
        said = 0.0
        while True:
            try:
                node = Node(name, cfg, instance=instance)
            except ConnectFailed as e:
                if not self.await_router or self.stop.is_set():
                    raise
                now = time.monotonic()
                since = since or now
                if now - said >= ROUTER_REPEAT_S:
                    waited = f" (waiting for {now - since:.0f} s)" if said else ""
                    self.log.warning("%s Trying again every %.0f s%s.", e, ROUTER_RETRY_S, waited)
                    said = now
                if self.stop.wait(ROUTER_RETRY_S):
                    raise
                continue
            if since:
                self.log.info(
                    "connected to %s after %.0f s",
                    ", ".join(cfg.connect),
                    time.monotonic() - since,
                )
            return node

    def closing(self, service: Closeable) -> None:
        """Close `service` when the service ends (before the sessions opened earlier)."""
        self._stack.callback(service.close)


def service_parser(
    name: str,
    description: str | None = None,
    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
    prog: str | None = None,
    verbose_help: str = "debug logging",
) -> argparse.ArgumentParser:
    """A service's command line: its own options (`add_arguments`), then the Zenoh flags
    every service shares (`add_node_args`: `--config`, `--connect`, `--listen`, `--mode`,
    `--ns`, …) and `--verbose`."""
    p = argparse.ArgumentParser(prog=prog or f"telerobot {name}", description=description)
    if add_arguments is not None:
        add_arguments(p)
    add_node_args(p)
    p.add_argument("--verbose", "-v", action="store_true", help=verbose_help)
    return p


def run_service(
    name: str,
    argv: list[str] | None,
    start: Callable[[ServiceContext], int | None],
    *,
    description: str | None = None,
    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
    prog: str | None = None,
    connect: tuple[str, ...] = (LOCAL_ROUTER,),
    verbose_help: str = "debug logging",
    await_router: bool = True,
) -> int:
    """The main of every service: parse the command line (`service_parser`), set up logging
    and SIGINT/SIGTERM, then call `start(ctx)`.

    `start` reads its configuration (`ctx.deploy`, `ctx.args`), opens its sessions with
    `ctx.open()` and registers what must be closed with `ctx.closing()`. When it returns
    None the service runs until SIGINT/SIGTERM; an int ends it at once with that status
    (a tool that runs to completion, or a start-up refusal). Either way everything
    registered is closed, last first. A bad configuration anywhere ends the process with
    status 2 (`CONFIG_EXIT`) and one line on stderr naming the key. `connect` is where the
    node connects when neither the deployment nor the flags say (the local router).
    `await_router`: a service waits for a router that does not answer yet (False: a tool
    that runs to completion fails at once, exit 1, saying so).
    """
    p = service_parser(name, description, add_arguments, prog, verbose_help)
    args = p.parse_args(argv)
    log = setup_logging(name, args.verbose)
    claim_cpu_share()  # a busy host's other sessions must not starve the control loops
    stop = Shutdown()
    try:
        with contextlib.ExitStack() as stack:
            ctx = ServiceContext(name, args, stop, log, stack, connect, await_router)
            status = start(ctx)
            if status is not None:
                return status
            stop.wait()
    except ConfigError as e:
        print(f"telerobot {name}: {e}", file=sys.stderr, flush=True)
        return CONFIG_EXIT
    except AlreadyRunning as e:
        print(f"telerobot {name}: {e}", file=sys.stderr, flush=True)
        return CONFIG_EXIT
    except ConnectFailed as e:
        if stop.is_set():  # stopped while it waited for its router: nothing ran
            log.info("%s stopped before its router answered", name)
            return 0
        print(f"telerobot {name}: {e}", file=sys.stderr, flush=True)
        return 1
    log.info("%s stopped", name)
    return 0
