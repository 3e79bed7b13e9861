"""`telerobot puma`: the PUMA 560 proxy service (simulated arm or a serial controller)."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.control.puma.config import PumaConfig


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--arm", choices=["sim", "serial"], default=None)
    p.add_argument("--port", default=None, help="serial URL (/dev/ttyUSB0, socket://host:port)")
    p.add_argument("--baudrate", type=int, default=None)
    p.add_argument(
        "--autostart",
        action="store_true",
        help="connect and initialize at start-up (the simulation profile does)",
    )


def start(ctx: ServiceContext) -> None:
    args = ctx.args
    overrides = {"arm": args.arm, "port": args.port, "baudrate": args.baudrate}
    table = service_table(ctx.deploy, "puma", overrides)
    autostart = bool(table.pop("autostart", False)) or args.autostart
    config = PumaConfig.from_mapping(table)
    from services.control.puma.service import PumaService

    svc = PumaService(ctx.open(), config)
    ctx.closing(svc)
    ctx.log.info("PUMA proxy up (%s arm)", config.arm)
    if autostart:
        svc.proxy.rpc_connect({})
        svc.proxy.rpc_initialize({})


def main(argv: list[str] | None = None) -> int:
    return run_service("puma", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
