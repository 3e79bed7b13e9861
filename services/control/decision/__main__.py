"""`telerobot decision`: the DecisionServer, supervisor between the masters and the arm.

Settings come from the deployment TOML's `[decision]` table (`--config`); the flags below
override it. See docs/decision.md.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.config import section, service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.control.decision.config import DecisionConfig
from services.control.decision.service import DecisionService


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--compliance",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="active compliance (admittance) on or off",
    )
    p.add_argument("--watchdog-ms", type=float, default=None, help="command watchdog (ms)")


def start(ctx: ServiceContext) -> None:
    node_cfg = ctx.node_config
    overrides = {"compliance": ctx.args.compliance, "watchdog_ms": ctx.args.watchdog_ms}
    dcfg = section(DecisionConfig, service_table(ctx.deploy, "decision", overrides), "decision")
    ctx.closing(DecisionService(ctx.open(node_cfg), dcfg))
    ctx.log.info(
        "decision up: loop %.0f Hz, watchdog %.0f ms, compliance %s",
        dcfg.rate_hz,
        dcfg.watchdog_ms,
        "on" if dcfg.compliance else "off",
    )


def main(argv: list[str] | None = None) -> int:
    return run_service("decision", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
