"""`telerobot demo`: the whole system in simulation with an embedded router, and the console.

Starts the `sim` profile (router, puma, force, decision, vision, console) as child
processes, waits until the console is up and prints its URL. Ctrl-C stops everything.
"""

from __future__ import annotations

import argparse
import sys
import threading

from services.bus.config import NodeConfig, load_deploy
from services.bus.lifecycle import Shutdown
from services.bus.node import Node
from services.cli import launcher

CONSOLE_WAIT_S = 60.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot demo", description=__doc__)
    p.add_argument("--profile", default="sim", help="a profile in deploy/ (default: sim)")
    args = p.parse_args(argv)
    profile = launcher.resolve_profile(args.profile)
    deploy = load_deploy(profile)
    port = int(deploy.get("console", {}).get("port", 8080))
    stop = Shutdown()
    status: list[int] = []
    runner = threading.Thread(
        target=lambda: status.append(launcher.run(profile, stop=stop)), name="launcher"
    )
    runner.start()
    connect = tuple(deploy.get("zenoh", {}).get("connect", ["tcp/127.0.0.1:7447"]))
    with Node("demo", NodeConfig(mode="peer", connect=connect)) as node:
        if node.alive.wait("console", CONSOLE_WAIT_S):
            bar = "=" * 60
            print(
                f"\n{bar}\n  Telerobot simulation is up.\n"
                f"  console: http://127.0.0.1:{port}\n"
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
    runner.join()
    return status[0] if status else 1
