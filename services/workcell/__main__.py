"""`python -m services.workcell`: the simulated workcell's physics as a service of its own.

Settings: the deployment TOML's `[workcell]` table (`--config`); see docs/tasks.md.
"""

from __future__ import annotations

import argparse
import sys

from services.bus.config import add_node_args, load_deploy, node_config, section
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.cli.introspect import LOCAL_ROUTER
from services.workcell.config import WorkcellConfig


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot workcell", description=__doc__)
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging")
    add_node_args(p)
    args = p.parse_args(argv)
    log = setup_logging("workcell", args.verbose)
    deploy = load_deploy(args.config)
    config = section(WorkcellConfig, deploy.get("workcell", {}), "workcell")
    from services.workcell.service import WorkcellService

    stop = Shutdown()
    with Node("workcell", node_config(args, deploy, connect=(LOCAL_ROUTER,))) as node:
        svc = WorkcellService(node, config)
        log.info("workcell simulation up (%g Hz)", config.rate_hz)
        try:
            stop.wait()
        finally:
            svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
