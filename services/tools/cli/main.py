"""`telerobot`: one command for the router, the launcher, every service and introspection.

Service subcommands (`telerobot arm …`) are dispatched to `services.<name>.__main__` and
imported only when used; the introspection commands import Zenoh only once their arguments
are parsed and checked, so `--help`, `--version` and a bad `call` argument answer at once.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from services.bus.errors import ConfigError, ConnectFailed

#: subcommand → module with `main(argv) -> int`
COMMANDS: dict[str, tuple[str, str]] = {
    "router": ("services.bus.router", "the embedded Zenoh router"),
    "up": ("services.tools.cli.launcher", "start a profile's services as child processes"),
    "arm": (
        "services.control.arm.__main__",
        "the arm service (any arm model: PUMA 560 by default, FR3, UR5e)",
    ),
    "force": ("services.control.force.__main__", "the force sensor service"),
    "decision": ("services.control.decision.__main__", "the DecisionServer (supervisor)"),
    "master": ("services.control.master.__main__", "the master station"),
    "haply-fake": (
        "services.control.master.devices.haply.fake",
        "a fake Haply Inverse Service (no device)",
    ),
    "vision": ("services.control.vision.__main__", "the stereo vision service"),
    "console": ("services.frontends.console.__main__", "the web console"),
    "bench": ("services.tools.cli.bench", "measure the system against the paper's figures"),
    "record": ("services.tools.record.__main__", "record a session to MCAP"),
    "replay": ("services.tools.record.replay", "replay an MCAP recording"),
    "report": ("services.tools.record.report", "summarize an MCAP recording"),
    "demo": ("services.tools.cli.demo", "run a task scenario with the console"),
    "workcell": (
        "services.world.workcell.__main__",
        "the simulated workcell (objects, gripper, bottle)",
    ),
    "tasks": ("services.tools.tasks.__main__", "run the paper's evaluation tasks (1, 2, 3)"),
    "ros2": (
        "services.frontends.ros2.__main__",
        "show the system to ROS 2 (rmw_zenoh), no ROS needed",
    ),
}


def _available() -> dict[str, tuple[str, str]]:
    out = {}
    for name, (module, help_) in COMMANDS.items():
        if importlib.util.find_spec(module.rsplit(".", 1)[0]) is None:
            continue
        try:
            if importlib.util.find_spec(module) is None:
                continue
        except ModuleNotFoundError:
            continue
        out[name] = (module, help_)
    return out


def version() -> str:
    """The installed package's version (the source tree's when not installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("telerobot")
    except PackageNotFoundError:
        return "unknown (not installed)"


class _Version(argparse.Action):
    """`--version`, reading the package metadata only when asked."""

    def __init__(self, option_strings: list[str], dest: str, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser: argparse.ArgumentParser, *_args: object) -> None:
        print(f"telerobot {version()}")
        parser.exit()


def build_parser(commands: dict[str, tuple[str, str]]) -> argparse.ArgumentParser:
    """The top-level parser: the service subcommands (parsed by their own modules) and the
    introspection commands. Builds without importing Zenoh, numpy or any service."""
    from services.tools.cli import introspect

    p = argparse.ArgumentParser(prog="telerobot", description=__doc__)
    p.add_argument("--version", action=_Version, help="print the version and exit")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for name, (_module, help_) in commands.items():
        sub.add_parser(name, help=help_, add_help=False)
    introspect.add_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = _available()
    if argv and argv[0] in commands:
        module = importlib.import_module(commands[argv[0]][0])
        try:
            return int(module.main(argv[1:]) or 0)
        except ConfigError as e:
            print(f"telerobot {argv[0]}: {e}", file=sys.stderr)
            return 2
        except ConnectFailed as e:
            print(f"telerobot {argv[0]}: {e}", file=sys.stderr)
            return 1
    args = build_parser(commands).parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as e:
        print(f"telerobot: {e}", file=sys.stderr)
        return 2
    except ConnectFailed as e:
        print(f"telerobot {argv[0] if argv else ''}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
