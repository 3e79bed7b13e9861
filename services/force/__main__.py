"""`telerobot force`: the force sensor service."""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, load_deploy, node_config, section, service_table
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.cli.introspect import LOCAL_ROUTER
from services.force.config import ForceConfig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot force", description=__doc__)
    p.add_argument("--sensor", choices=["sim", "serial", "netft"], default=None)
    p.add_argument("--port", default=None, help="serial URL (/dev/ttyUSB0, socket://host:port)")
    p.add_argument("--host", default=None, help="Net F/T address")
    p.add_argument("--period-ms", type=float, default=None)
    p.add_argument(
        "--priority",
        default=None,
        choices=["lowest", "below_normal", "normal", "above_normal", "highest"],
    )
    add_node_args(p)
    args = p.parse_args(argv)
    log = setup_logging("force")
    deploy = load_deploy(args.config)
    overrides = {
        "sensor": args.sensor,
        "port": args.port,
        "host": args.host,
        "period_ms": args.period_ms,
        "priority": args.priority,
    }
    table = service_table(deploy, "force", overrides)
    config = section(ForceConfig, table, "force")
    from services.force.service import ForceService

    stop = Shutdown()
    with Node("force", node_config(args, deploy, connect=(LOCAL_ROUTER,))) as node:
        svc = ForceService(node, config)
        log.info("sensing with %s every %.3f ms", config.sensor, config.period_ms)
        try:
            stop.wait()
        finally:
            svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
