"""`telerobot puma`: the PUMA 560 proxy service (simulated arm or a serial controller)."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, load_deploy, node_config, service_table
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.cli.introspect import LOCAL_ROUTER
from services.puma.config import PumaConfig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot puma", description=__doc__)
    p.add_argument("--arm", choices=["sim", "serial"], default=None)
    p.add_argument("--port", default=None, help="serial URL (/dev/ttyUSB0, socket://host:port)")
    p.add_argument("--baudrate", type=int, default=None)
    p.add_argument(
        "--autostart",
        action="store_true",
        help="connect and initialize at start-up (the simulation profile does)",
    )
    add_node_args(p)
    args = p.parse_args(argv)
    log = setup_logging("puma")
    deploy = load_deploy(args.config)
    overrides = {"arm": args.arm, "port": args.port, "baudrate": args.baudrate}
    table = service_table(deploy, "puma", overrides)
    autostart = bool(table.pop("autostart", False)) or args.autostart
    config = PumaConfig.from_mapping(table)
    from services.puma.service import PumaService

    stop = Shutdown()
    with Node("puma", node_config(args, deploy, connect=(LOCAL_ROUTER,))) as node:
        svc = PumaService(node, config)
        log.info("PUMA proxy up (%s arm)", config.arm)
        try:
            if autostart:
                svc.proxy.rpc_connect({})
                svc.proxy.rpc_initialize({})
            stop.wait()
        finally:
            svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
