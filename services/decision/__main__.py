"""`telerobot decision`: the DecisionServer, supervisor between the masters and the puma.

Settings come from the deployment TOML's `[decision]` table (`--config`); the flags below
override it. See docs/decision.md.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, node_config, service_config
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.decision.config import DecisionConfig
from services.decision.service import DecisionService


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot decision", description=__doc__)
    add_node_args(p)
    p.add_argument(
        "--compliance",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="active compliance (admittance) on or off",
    )
    p.add_argument("--watchdog-ms", type=float, default=None, help="command watchdog (ms)")
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging")
    args = p.parse_args(argv)
    log = setup_logging("decision", args.verbose)
    cfg = node_config(args, connect=("tcp/127.0.0.1:7447",))
    dcfg = service_config(
        DecisionConfig,
        args,
        "decision",
        {"compliance": args.compliance, "watchdog_ms": args.watchdog_ms},
    )
    stop = Shutdown()
    with Node("decision", cfg) as node:
        service = DecisionService(node, dcfg)
        try:
            log.info(
                "decision up: loop %.0f Hz, watchdog %.0f ms, compliance %s",
                dcfg.rate_hz,
                dcfg.watchdog_ms,
                "on" if dcfg.compliance else "off",
            )
            stop.wait()
        finally:
            service.close()
    log.info("decision stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
