"""`python -m services.tasks`: run one of the paper's three tasks and print its metrics.

By default it joins a running system (`telerobot up sim`, or `telerobot demo`'s) through the
Zenoh flags, starts the workcell simulation unless one is up, and drives the arm with a
scripted operator at a master of its own (id `operator`). `--headless` runs everything in
this process on a private network instead. See docs/tasks.md.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, load_deploy, node_config
from services.bus.errors import TelerobotError
from services.bus.lifecycle import Shutdown, setup_logging
from services.cli.introspect import LOCAL_ROUTER
from services.tasks.metrics import TaskReport


def print_report(report: TaskReport, as_json: bool, with_log: bool = False) -> None:
    """The report as JSON or as a table (then, with `with_log`, the operator's log)."""
    if as_json:
        print(report.to_json(), flush=True)
        return
    print(report.table(), flush=True)
    if with_log:
        print("\n".join(["operator:", *report.log]), flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.tasks", description=__doc__)
    p.add_argument("--task", type=int, choices=(1, 2, 3), default=2, help="which task (default 2)")
    p.add_argument("--headless", action="store_true", help="run the whole system in-process")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument(
        "--verbose", "-v", action="store_true", help="debug logging; print the operator's log"
    )
    add_node_args(p)
    args = p.parse_args(argv)
    setup_logging("tasks", args.verbose)
    from services.tasks.system import Connected, run_headless

    stop = Shutdown()
    try:
        if args.headless:
            report = run_headless(args.task, abort=stop)
        else:
            cfg = node_config(args, load_deploy(args.config), connect=(LOCAL_ROUTER,))
            with Connected(cfg, abort=stop) as run:
                report = run.run(args.task)
    except TelerobotError as e:
        print(f"tasks: {e}", file=sys.stderr)
        return 2
    print_report(report, args.json, with_log=args.verbose)
    return 0 if report.success else 1


if __name__ == "__main__":
    sys.exit(main())
