"""run_service(): the one main of every service. Common options, a bad configuration exits 2
naming the key, SIGTERM stops cleanly, and what a service opened is closed last first."""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import logging
import os
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.bus.config import LOCAL_ROUTER
from services.bus.lifecycle import CONFIG_EXIT, ServiceContext, Shutdown, run_service
from tests.conftest import Net, free_port, wait_until

#: every service main (and the router's); each must be built on run_service
MAINS = [
    *(
        f"services.{name}.__main__"
        for name in (
            "control.arm",
            "control.force",
            "control.decision",
            "control.master",
            "control.vision",
            "frontends.console",
            "world.workcell",
            "frontends.ros2",
            "tools.record",
            "tools.tasks",
        )
    ),
    "services.bus.router",
]


class Part:
    """Something a service closes; records the order of closes in `log`."""

    def __init__(self, name: str, log: list[str]) -> None:
        self.name = name
        self.log = log

    def close(self) -> None:
        self.log.append(self.name)


@pytest.fixture
def signals() -> Iterator[None]:
    """run_service installs SIGINT/SIGTERM handlers and, on a signal, a last-resort exit
    timer: restore the handlers and cancel the timer, so pytest is left as it was."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()
        for s, h in saved.items():
            signal.signal(s, h)


def own_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--speed", type=float, default=1.0)


def test_common_options_and_the_default_router(signals: None) -> None:
    seen: list[ServiceContext] = []

    def start(ctx: ServiceContext) -> int:
        seen.append(ctx)
        return 0

    argv = ["--speed", "2.5", "--connect", "tcp/127.0.0.1:1234", "--ns", "cell2", "-v"]
    assert run_service("probe", argv, start, add_arguments=own_option) == 0
    assert run_service("probe", [], start) == 0
    flags, defaults = seen
    assert flags.args.speed == 2.5 and flags.args.verbose
    assert flags.node_config.connect == ("tcp/127.0.0.1:1234",)
    assert flags.node_config.ns == "cell2"
    assert flags.deploy == {}
    assert defaults.node_config.connect == (LOCAL_ROUTER,)
    assert defaults.node_config.ns == "" and not defaults.args.verbose


def test_a_bad_configuration_exits_2_naming_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], signals: None
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[zenoh]\nlease_ms = 5000\n")
    closed: list[str] = []
    reached: list[str] = []

    def start(ctx: ServiceContext) -> None:
        ctx.closing(Part("early", closed))
        ctx.open()  # reads [zenoh]: fails before any session opens
        reached.append("open")

    assert run_service("probe", ["--config", str(bad)], start) == CONFIG_EXIT
    err = capsys.readouterr().err
    assert "telerobot probe:" in err and "'zenoh.lease_ms'" in err
    assert err.count("\n") == 1  # one line, no traceback
    assert reached == [] and closed == ["early"]


def test_a_missing_config_file_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], signals: None
) -> None:
    def start(ctx: ServiceContext) -> None:
        _ = ctx.deploy

    assert run_service("probe", ["--config", str(tmp_path / "nope.toml")], start) == 2
    assert "'--config'" in capsys.readouterr().err


def test_a_status_ends_the_service_at_once_and_closes_last_first(signals: None) -> None:
    closed: list[str] = []

    def start(ctx: ServiceContext) -> int:
        ctx.closing(Part("first", closed))
        ctx.closing(Part("second", closed))
        return 3

    assert run_service("probe", [], start) == 3
    assert closed == ["second", "first"]


def test_sigterm_stops_it_cleanly(net: Net, signals: None) -> None:
    """A real session: a peer sees the service's token while it runs and gone after SIGTERM;
    the service is closed before its session."""
    observer = net.node("observer")
    closed: list[str] = []
    up = threading.Event()

    def start(ctx: ServiceContext) -> None:
        node = ctx.open()
        node.announce()

        class Service(Part):
            def close(self) -> None:
                # the session is still open while the service closes (it can hold the arm)
                closed.append(f"service, session open: {not node.closed}")

        ctx.closing(Service("service", closed))
        up.set()

    seen: list[bool] = []

    def terminate() -> None:
        # SIGTERM in any case, so a failure cannot leave the test waiting
        seen.append(up.wait(30.0) and observer.alive.wait("probe", 30.0))
        os.kill(os.getpid(), signal.SIGTERM)

    killer = threading.Thread(target=terminate)
    killer.start()
    status = run_service("probe", ["--connect", net.endpoint, "--mode", "peer"], start)
    killer.join()
    assert seen == [True]
    assert status == 0
    assert closed == ["service, session open: True"]
    assert wait_until(lambda: not observer.alive.is_alive("probe"), 10.0)


def test_a_service_waits_for_a_router_that_is_not_up_yet(
    net: Net, signals: None, caplog: pytest.LogCaptureFixture
) -> None:
    """A client whose router does not answer says so once and tries again; when the router
    comes it connects, says so, and runs (a station switched on before the robot host)."""
    caplog.set_level(logging.INFO, logger="telerobot.probe")
    announced = threading.Event()

    def start(ctx: ServiceContext) -> None:
        ctx.open().announce()
        announced.set()

    def messages() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.name == "telerobot.probe"]

    seen: list[bool] = []

    def router_comes_later() -> None:
        waiting = wait_until(lambda: any("Trying again" in m for m in messages()), 30.0)
        observer = net.node("observer")  # the first node of `net` listens at its endpoint
        seen.extend([bool(waiting), announced.wait(30.0), observer.alive.wait("probe", 30.0)])
        os.kill(os.getpid(), signal.SIGTERM)

    helper = threading.Thread(target=router_comes_later)
    helper.start()
    status = run_service("probe", ["--connect", net.endpoint, "--mode", "client"], start)
    helper.join()
    assert seen == [True, True, True]
    assert status == 0
    said = messages()
    waits = [m for m in said if "Trying again" in m]
    assert len(waits) == 1, said  # one warning, not one per try
    assert f"cannot connect to {net.endpoint}" in waits[0]
    connected = [i for i, m in enumerate(said) if m.startswith(f"connected to {net.endpoint}")]
    assert len(connected) == 1 and connected[0] > said.index(waits[0]), said


def test_a_tool_without_a_router_fails_at_once(
    capsys: pytest.CaptureFixture[str], signals: None
) -> None:
    """A run to completion (await_router=False: `telerobot task`) does not wait: exit 1 and
    the one line that says which endpoint did not answer."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    reached: list[str] = []

    def start(ctx: ServiceContext) -> int:
        ctx.open()
        reached.append("open")
        return 0

    argv = ["--connect", endpoint, "--mode", "client"]
    assert run_service("probe", argv, start, await_router=False) == 1
    err = capsys.readouterr().err
    assert f"telerobot probe: cannot connect to {endpoint}" in err and err.count("\n") == 1
    assert reached == []


def test_a_stop_while_waiting_for_the_router_ends_cleanly(
    signals: None, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="telerobot.probe")
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    def start(ctx: ServiceContext) -> None:
        ctx.open()

    def stop_once_waiting() -> None:
        wait_until(lambda: any("Trying again" in r.getMessage() for r in caplog.records), 30.0)
        os.kill(os.getpid(), signal.SIGTERM)

    helper = threading.Thread(target=stop_once_waiting)
    helper.start()
    status = run_service("probe", ["--connect", endpoint, "--mode", "client"], start)
    helper.join()
    assert status == 0
    said = [r.getMessage() for r in caplog.records if r.name == "telerobot.probe"]
    assert said[-1] == "probe stopped before its router answered", said


def test_a_signal_delivered_to_another_thread_still_stops_the_wait(signals: None) -> None:
    """The kernel may hand a process-directed SIGTERM to any thread (a Zenoh runtime thread,
    say). CPython then only flags it; the main thread, asleep in `Shutdown.wait()`, must
    still wake and run the handler. A rescuer sets the flag after 20 s so a regression
    fails instead of hanging."""
    stop = Shutdown()
    other_ready = threading.Event()
    release = threading.Event()
    rescued: list[bool] = []

    def other() -> None:
        other_ready.set()
        release.wait(30.0)

    def rescue() -> None:
        if not stop.wait(20.0):
            rescued.append(True)
            stop.set()

    t = threading.Thread(target=other)
    t.start()
    assert other_ready.wait(10.0)
    threading.Thread(target=rescue, daemon=True).start()
    assert t.ident is not None
    signal.pthread_kill(t.ident, signal.SIGTERM)
    assert stop.wait() is True
    release.set()
    t.join()
    assert rescued == []
    assert stop.signal == signal.SIGTERM


@pytest.mark.parametrize("name", MAINS)
def test_every_main_has_the_common_options(
    name: str, capsys: pytest.CaptureFixture[str], signals: None
) -> None:
    module = importlib.import_module(name)
    with pytest.raises(SystemExit) as e:
        module.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for option in ("--config", "--connect", "--listen", "--mode", "--ns", "--verbose"):
        assert option in out, f"{name}: no {option}"
