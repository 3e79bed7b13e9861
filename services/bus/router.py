"""The embedded router: a Zenoh session in router mode, so one machine needs no zenohd.

`telerobot router` listens on `tcp/0.0.0.0:7447` by default with the admin space on. A
JSON5 router configuration (TLS, user/password, ACL; see deploy/) is applied first with
`--zenoh-config`, exactly as zenohd would read it; flags override it.
"""

from __future__ import annotations

import argparse
import logging

import zenoh

from services.bus.config import NodeConfig, add_node_args, load_deploy, section
from services.bus.lifecycle import Shutdown, setup_logging

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"

log = logging.getLogger("telerobot.router")


def router_config(args: argparse.Namespace) -> NodeConfig:
    """The router's NodeConfig: deployment `[router]` table < flags; mode is always router."""
    deploy = load_deploy(args.config)
    table = {"listen": [DEFAULT_LISTEN], "admin_space": True, **deploy.get("router", {})}
    table["mode"] = "router"
    if args.listen:
        table["listen"] = list(args.listen)
    if args.connect:
        table["connect"] = list(args.connect)
    if args.zenoh_config:
        table["zenoh_config"] = args.zenoh_config
        if not args.listen and "listen" not in deploy.get("router", {}):
            table.pop("listen")
    if args.lease_ms is not None:
        table["lease_ms"] = args.lease_ms
    return section(NodeConfig, table, "router")


def open_router(cfg: NodeConfig) -> zenoh.Session:
    """Open the router session (the caller closes it)."""
    return zenoh.open(cfg.to_zenoh())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot router", description=__doc__)
    add_node_args(p)
    args = p.parse_args(argv)
    setup_logging("router")
    # RUST_LOG=info,zenoh::net::routing::interceptor::access_control=trace shows ACL denials.
    zenoh.try_init_log_from_env()
    cfg = router_config(args)
    stop = Shutdown()
    with open_router(cfg) as session:
        log.info("router %s listening on %s", session.zid(), ", ".join(cfg.listen) or "config")
        print(f"router up: zid={session.zid()} listen={list(cfg.listen)}", flush=True)
        stop.wait()
    log.info("router stopped")
    return 0
