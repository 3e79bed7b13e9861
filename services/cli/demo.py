"""`telerobot demo`: the whole system in simulation with an embedded router, and the console.

Starts the `sim` profile (router, puma, force, decision, vision, console) as child
processes, waits until the console is up and prints its URL. Then it runs one of the
paper's three tasks (`--task 1|2|3`, default 2: stacking; `--task none`: no task): a
scripted operator at a master of its own (id `operator`) drives the arm through the
decision server while the workcell simulation (started here unless one is up) moves the
objects; the run's metrics are printed when it ends (docs/tasks.md). The system keeps
running, so the console's virtual master can take over. Ctrl-C stops everything.
"""

from __future__ import annotations

import argparse
import re
import sys
import threading

from services.bus.config import NodeConfig, load_deploy
from services.bus.errors import TelerobotError
from services.bus.lifecycle import Shutdown
from services.bus.node import Node
from services.cli import launcher

CONSOLE_WAIT_S = 60.0
TASKS = ("1", "2", "3", "none")
_URL = re.compile(r"\[console\] console: (http://\S+)")


class _UrlWatch:
    """The launcher's output, passed through; remembers the URL the console prints (viser
    moves to the next free port when the configured one is taken)."""

    def __init__(self) -> None:
        self.url: str | None = None
        self.seen = threading.Event()

    def write(self, text: str) -> int:
        m = _URL.search(text)
        if m and self.url is None:
            self.url = m.group(1)
            self.seen.set()
        return sys.stdout.write(text)

    def flush(self) -> None:
        sys.stdout.flush()


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
    args = p.parse_args(argv)
    profile = launcher.resolve_profile(args.profile)
    deploy = load_deploy(profile)
    port = int(deploy.get("console", {}).get("port", 8080))
    stop = Shutdown()
    status: list[int] = []
    watch = _UrlWatch()
    runner = threading.Thread(
        target=lambda: status.append(launcher.run(profile, out=watch, stop=stop)),  # type: ignore[arg-type]
        name="launcher",
    )
    runner.start()
    connect = tuple(deploy.get("zenoh", {}).get("connect", ["tcp/127.0.0.1:7447"]))
    node_cfg = NodeConfig(mode="peer", connect=connect)
    up = False
    with Node("demo", node_cfg) as node:
        if node.alive.wait("console", CONSOLE_WAIT_S):
            up = True
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
        elif not stop.is_set():
            print(
                "telerobot demo: the console did not come up; see the logs above",
                file=sys.stderr,
                flush=True,
            )
    if up and args.task != "none" and not stop.is_set():
        run_task(int(args.task), node_cfg, stop, args.json)
    runner.join()
    return status[0] if status else 1


def run_task(task: int, node_cfg: NodeConfig, stop: Shutdown, as_json: bool) -> None:
    """Run `task` against the running profile, print its metrics, keep the workcell
    simulation up until `stop`."""
    from services.tasks.__main__ import print_report
    from services.tasks.system import Connected

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
