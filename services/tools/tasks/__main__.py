"""`python -m services.tools.tasks`: run one of the paper's three tasks and print its metrics.

By default it joins a running system (`telerobot up sim`, or `telerobot demo`'s) through the
Zenoh flags, starts the workcell simulation unless one is up, and drives the arm with a
scripted operator at a master of its own (id `operator`). `--headless` runs everything in
this process on a private network instead. See docs/tasks.md.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.errors import TelerobotError
from services.bus.lifecycle import ServiceContext, run_service
from services.tools.tasks.metrics import TaskReport


def print_report(report: TaskReport, as_json: bool, with_log: bool = False) -> None:
    """The report as JSON or as a table (then, with `with_log`, the operator's log)."""
    if as_json:
        print(report.to_json(), flush=True)
        return
    print(report.table(), flush=True)
    if with_log:
        print("\n".join(["operator:", *report.log]), flush=True)


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", type=int, choices=(1, 2, 3), default=2, help="which task (default 2)")
    p.add_argument("--headless", action="store_true", help="run the whole system in-process")
    p.add_argument(
        "--model",
        default=None,
        help="with --headless: the arm model (puma560, fr3, ur5e or an arm's TOML; default "
        "puma560); a running system has its own",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")


def start(ctx: ServiceContext) -> int:
    """Run the task (joining the running system, or `--headless` in this process), print
    its report; status 0 when it succeeded, 1 when not, 2 when it could not run."""
    from services.control.arm.model import DEFAULT_MODEL
    from services.tools.tasks.system import Connected, run_headless

    args = ctx.args
    try:
        if args.headless:
            report = run_headless(args.task, abort=ctx.stop, model=args.model or DEFAULT_MODEL)
        else:
            with Connected(ctx.node_config, abort=ctx.stop) as run:
                report = run.run(args.task)
    except TelerobotError as e:
        print(f"tasks: {e}", file=sys.stderr)
        return 2
    print_report(report, args.json, with_log=args.verbose)
    return 0 if report.success else 1


def main(argv: list[str] | None = None) -> int:
    return run_service(
        "tasks",
        argv,
        start,
        description=__doc__,
        add_arguments=arguments,
        prog="python -m services.tools.tasks",
        verbose_help="debug logging; print the operator's log",
        await_router=False,  # a run to completion: no router is an error at once
    )


if __name__ == "__main__":
    sys.exit(main())
