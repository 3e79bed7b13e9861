"""`telerobot force`: the force sensor service."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import section, service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.control.force.config import ForceConfig


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sensor", choices=["sim", "serial", "netft", "franka"], default=None)
    p.add_argument("--port", default=None, help="serial URL (/dev/ttyUSB0, socket://host:port)")
    p.add_argument("--host", default=None, help="Net F/T address")
    p.add_argument("--period-ms", type=float, default=None)
    p.add_argument(
        "--priority",
        default=None,
        choices=["lowest", "below_normal", "normal", "above_normal", "highest"],
    )


def start(ctx: ServiceContext) -> None:
    args = ctx.args
    overrides = {
        "sensor": args.sensor,
        "port": args.port,
        "host": args.host,
        "period_ms": args.period_ms,
        "priority": args.priority,
    }
    config = section(ForceConfig, service_table(ctx.deploy, "force", overrides), "force")
    from services.control.force.service import ForceService

    ctx.closing(ForceService(ctx.open(), config))
    ctx.log.info("sensing with %s every %.3f ms", config.sensor, config.period_ms)


def main(argv: list[str] | None = None) -> int:
    return run_service("force", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
