"""`telerobot arm`: the PUMA 560 proxy service (simulated arm or a serial controller)."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.control.arm.config import ArmConfig


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--driver", choices=["sim", "serial"], default=None)
    p.add_argument("--port", default=None, help="serial URL (/dev/ttyUSB0, socket://host:port)")
    p.add_argument("--baudrate", type=int, default=None)
    p.add_argument(
        "--autostart",
        action="store_true",
        help="connect and initialize at start-up (the simulation profile does)",
    )


def start(ctx: ServiceContext) -> None:
    args = ctx.args
    overrides = {"driver": args.driver, "port": args.port, "baudrate": args.baudrate}
    table = service_table(ctx.deploy, "arm", overrides)
    autostart = bool(table.pop("autostart", False)) or args.autostart
    config = ArmConfig.from_mapping(table)
    from services.control.arm.service import ArmService

    svc = ArmService(ctx.open(), config)
    ctx.closing(svc)
    ctx.log.info("PUMA proxy up (%s arm)", config.driver)
    if autostart:
        svc.proxy.rpc_connect({})
        svc.proxy.rpc_initialize({})


def main(argv: list[str] | None = None) -> int:
    return run_service("arm", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
