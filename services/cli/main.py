"""`telerobot`: one command for the router, the launcher, every service and introspection.

Service subcommands (`telerobot puma …`) are dispatched to `services.<name>.__main__` and
imported only when used, so `telerobot topic echo` starts without loading Pinocchio or cv2.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from services.bus.errors import ConfigError

#: subcommand → module with `main(argv) -> int`
COMMANDS: dict[str, tuple[str, str]] = {
    "router": ("services.bus.router", "the embedded Zenoh router"),
    "up": ("services.cli.launcher", "start a profile's services as child processes"),
    "puma": ("services.puma.__main__", "the PUMA 560 proxy service"),
    "force": ("services.force.__main__", "the force sensor service"),
    "decision": ("services.decision.__main__", "the DecisionServer (supervisor)"),
    "master": ("services.master.__main__", "the master station"),
    "haply-fake": ("services.master.fake_haply", "a fake Haply Inverse Service (no device)"),
    "vision": ("services.vision.__main__", "the stereo vision service"),
    "console": ("services.console.__main__", "the web console"),
    "bench": ("services.cli.bench", "measure the system against the paper's figures"),
    "record": ("services.record.__main__", "record a session to MCAP"),
    "replay": ("services.record.replay", "replay an MCAP recording"),
    "report": ("services.record.report", "summarize an MCAP recording"),
    "demo": ("services.cli.demo", "run a task scenario with the console"),
    "workcell": ("services.workcell.__main__", "the simulated workcell (objects, gripper, bottle)"),
    "tasks": ("services.tasks.__main__", "run the paper's evaluation tasks (1, 2, 3)"),
    "ros2": ("services.ros2.__main__", "show the system to ROS 2 (rmw_zenoh), no ROS needed"),
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
    from services.cli import introspect

    p = argparse.ArgumentParser(prog="telerobot", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for name, (_module, help_) in commands.items():
        sub.add_parser(name, help=help_, add_help=False)
    introspect.add_parsers(sub)
    args = p.parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as e:
        print(f"telerobot: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
