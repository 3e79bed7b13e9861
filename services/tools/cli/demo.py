"""`telerobot demo`: the whole system in simulation with an embedded router, and the console.

Starts the `sim` profile (router, arm, force, decision, vision, console) as child
processes, waits until the console is up and prints its URL. Then it runs one of the
paper's three tasks (`--task 1|2|3`, default 2: stacking; `--task none`: no task): a
scripted operator at a master of its own (id `operator`) drives the arm through the
decision server while the workcell simulation (started here unless one is up) moves the
objects; the run's metrics are printed when it ends (docs/tasks.md). The system keeps
running, so the console's virtual master can take over. Ctrl-C stops everything.

Every line a service prints carries its `[service]` prefix; the demo's own log lines carry
`[demo]`, and no line is ever cut by another. When another Telerobot already runs (its
router holds the port), the demo says so and exits before starting anything: stop it, or
use `--listen tcp/127.0.0.1:PORT` (a second system beside it) or `--ns NS`.
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
import threading
import time
from dataclasses import replace
from typing import IO, Any

from services.bus.config import LOCAL_ROUTER, NodeConfig, load_deploy, section
from services.bus.errors import TelerobotError
from services.bus.lifecycle import Shutdown
from services.bus.node import Node
from services.tools.cell.procs import OUT_LOCK
from services.tools.cli import launcher

#: the console's start-up, imports included, on a loaded 2-core machine (3–13 s each for
#: eight services starting together), with margin
CONSOLE_WAIT_S = 90.0
TASKS = ("1", "2", "3", "none")
_URL = re.compile(r"\[console\] console: (http://\S+)")


class _UrlWatch:
    """The launcher's output, passed through; remembers the URL the console prints (viser
    moves to the next free port when the configured one is taken)."""

    def __init__(self, out: IO[str]) -> None:
        self.out = out
        self.url: str | None = None
        self.seen = threading.Event()

    def write(self, text: str) -> int:
        m = _URL.search(text)
        if m and self.url is None:
            self.url = m.group(1)
            self.seen.set()
        return self.out.write(text)

    def flush(self) -> None:
        self.out.flush()


class _Lines:
    """A text stream that writes whole lines only, under the launcher's output lock: the
    demo's own prints and logs never cut a service's line (nor one another's). Each thread
    gathers its partial line apart."""

    def __init__(self, out: IO[str]) -> None:
        self.out = out
        self._partial = threading.local()

    def write(self, text: str) -> int:
        buf = getattr(self._partial, "text", "") + text
        head, sep, tail = buf.rpartition("\n")
        self._partial.text = tail
        if sep:
            with OUT_LOCK:
                self.out.write(head + sep)
                self.out.flush()
        return len(text)

    def flush(self) -> None:
        self.out.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.out, name)


def demo_node_config(deploy: dict[str, Any], overrides: launcher.Overrides) -> NodeConfig:
    """The demo's own sessions (and the task's): the profile's `[zenoh]` table (loopback
    listeners in the sim profile) with the `--listen/--ns` overrides the services got."""
    base = section(NodeConfig, {"connect": [LOCAL_ROUTER], **deploy.get("zenoh", {})}, "zenoh")
    cfg = replace(base, mode="peer" if base.mode == "router" else base.mode)
    if overrides.listen:
        cfg = replace(cfg, connect=(launcher.dialable(overrides.listen),))
    if overrides.ns:
        cfg = replace(cfg, ns=overrides.ns)
    return cfg


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot demo", description=__doc__)
    p.add_argument("--profile", default="sim", help="a profile in deploy/ (default: sim)")
    p.add_argument(
        "--task",
        choices=TASKS,
        default="2",
        help="the task the scripted operator performs: 1 tool pose, 2 stacking (default), "
        "3 bottled liquid, none",
    )
    p.add_argument("--json", action="store_true", help="print the task's metrics as JSON")
    launcher.add_override_args(p)
    args = p.parse_args(argv)
    profile = launcher.resolve_profile(args.profile)
    overrides = launcher.Overrides(
        listen=args.listen,
        ns=args.ns,
        model=args.model,
        driver=args.driver,
        robot_ip=args.robot_ip,
    )
    deploy = load_deploy(profile)
    port = int(deploy.get("console", {}).get("port", 8080))
    node_cfg = demo_node_config(deploy, overrides)
    ups = deploy.get("up", {}).get("services", [])
    taken = launcher.taken_router_endpoints(deploy, overrides) if "router" in ups else []
    if taken and not overrides.ns:
        # before anything starts: no service of ours joins the other system
        print(f"telerobot demo: {launcher.already_running(taken)}", file=sys.stderr, flush=True)
        return 1
    real_out = sys.stdout
    sys.stdout = _Lines(real_out)
    logging.basicConfig(
        stream=sys.stdout,
        level=logging.INFO,
        format="[demo] %(asctime)s %(levelname)-7s %(name)s: %(message)s",
        force=True,
    )
    try:
        return _run(args, profile, overrides, node_cfg, port, real_out)
    finally:
        sys.stdout = real_out


def _run(
    args: argparse.Namespace,
    profile: Any,
    overrides: launcher.Overrides,
    node_cfg: NodeConfig,
    port: int,
    real_out: IO[str],
) -> int:
    stop = Shutdown()
    status: list[int] = []
    watch = _UrlWatch(real_out)
    out: Any = watch  # a text stream as far as the launcher is concerned

    def launch() -> None:
        status.append(launcher.run(profile, out=out, stop=stop, overrides=overrides))

    runner = threading.Thread(target=launch, name="launcher")
    runner.start()
    up = False
    with Node("demo", node_cfg) as node:
        deadline = time.monotonic() + CONSOLE_WAIT_S
        while runner.is_alive() and not stop.is_set() and time.monotonic() < deadline:
            if node.alive.wait("console", 0.5):
                up = True
                break
        if up:
            watch.seen.wait(5.0)
            url = watch.url or f"http://127.0.0.1:{port}"
            bar = "=" * 60
            task = "" if args.task == "none" else f"  task {args.task}: starting (metrics follow)\n"
            print(
                f"\n{bar}\n  Telerobot simulation is up.\n"
                f"  console: {url}\n"
                f"{task}"
                f"  inspect: .venv/bin/telerobot topic list | alive | call decision status\n"
                f"  Ctrl-C stops everything.\n{bar}\n",
                flush=True,
            )
        elif runner.is_alive() and not stop.is_set():
            print(
                f"telerobot demo: the console did not come up within {CONSOLE_WAIT_S:.0f} s; "
                "stopping everything (see the logs above)",
                file=sys.stderr,
                flush=True,
            )
            stop.set()
            runner.join()
            return 1
    if up and args.task != "none" and not stop.is_set():
        run_task(int(args.task), node_cfg, stop, args.json)
    runner.join()
    return status[0] if status else 1


def run_task(task: int, node_cfg: NodeConfig, stop: Shutdown, as_json: bool) -> None:
    """Run `task` against the running profile, print its metrics, keep the workcell
    simulation up until `stop`."""
    from services.tools.tasks.__main__ import print_report
    from services.tools.tasks.system import Connected

    try:
        with Connected(node_cfg, abort=stop) as run:
            report = run.run(task)
            print_report(report, as_json)
            print(
                "\ntelerobot demo: task done; the system keeps running (Ctrl-C stops)", flush=True
            )
            stop.wait()
    except TelerobotError as e:
        print(f"telerobot demo: task {task} could not run: {e}", file=sys.stderr, flush=True)
