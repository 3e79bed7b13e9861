"""The embedded router: a Zenoh session in router mode, so one machine needs no zenohd.

`telerobot router` listens on `tcp/0.0.0.0:7447` by default with the admin space on. A
JSON5 router configuration (TLS, user/password, ACL; see deploy/) is applied first with
`--zenoh-config`, exactly as zenohd would read it; flags override it.

A router that listens beyond loopback says so loudly at start-up (log warning and a line on
stdout): who can join it (anyone who reaches the port, unless a login and an access-control
list are configured) and that its admin space (`@/**`: every session, publisher and
subscriber) is readable by them. The simulation profile listens on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import errno
import ipaddress
import json
import logging
import socket
import sys
from typing import TYPE_CHECKING

from services.bus.bounds import short
from services.bus.config import ROUTER_PORT, NodeConfig, load_deploy, section
from services.bus.errors import ConfigError
from services.bus.lifecycle import ServiceContext, run_service

if TYPE_CHECKING:  # zenoh is imported where a session opens: `up --help` stays instant
    import zenoh

DEFAULT_LISTEN = f"tcp/0.0.0.0:{ROUTER_PORT}"

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


def is_loopback(endpoint: str) -> bool:
    """True for an endpoint bound to a loopback address (127.0.0.0/8, ::1, localhost)."""
    rest = endpoint.partition("/")[2].split("#", 1)[0]
    host = rest.rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposure_note(cfg: NodeConfig) -> str | None:
    """The loud note for a router listening beyond loopback, or None when it does not."""
    zcfg = cfg.to_zenoh()
    listen = json.loads(zcfg.get_json("listen/endpoints"))
    if isinstance(listen, dict):  # Zenoh's per-mode default
        listen = listen.get("router", [])
    exposed = [e for e in listen if not is_loopback(e)]
    if not exposed:
        return None
    acl = json.loads(zcfg.get_json("access_control/enabled")) is True
    login = json.loads(zcfg.get_json("transport/auth/usrpwd/dictionary_file")) is not None
    admin = json.loads(zcfg.get_json("adminspace/enabled")) is True
    who = (
        "only sessions that log in, with the rights the access-control list gives them"
        if acl and login
        else "ANYONE who reaches the port can join and publish robot/arm/target "
        "(no login and access-control list configured)"
    )
    admin_note = ""
    if admin:
        admin_note = "; the admin space @/** (every session, publisher, subscriber) is " + (
            "on: the access-control list decides who reads it" if acl else "readable by all"
        )
    return (
        f"NOTE: this router listens beyond loopback on {', '.join(exposed)}: {who}{admin_note}. "
        "For one machine listen on tcp/127.0.0.1:7447 (deploy/sim.toml); for a cell see "
        "docs/deploy.md"
    )


def tcp_host_port(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of a `tcp/HOST:PORT` endpoint (IPv6 hosts in brackets), else None."""
    proto, _, rest = endpoint.partition("/")
    host, _, port = rest.split("#", 1)[0].rpartition(":")
    if proto != "tcp" or not host or not port.isdigit() or int(port) > 65535:
        return None
    return host.strip("[]"), int(port)


def endpoint_taken(endpoint: str) -> bool:
    """True when something already listens on this TCP endpoint's port: a bind with
    SO_REUSEADDR fails only against a listener (not against TIME_WAIT leftovers of a
    router that has just stopped). Other protocols and port 0 are never 'taken'."""
    hp = tcp_host_port(endpoint)
    if hp is None or hp[1] == 0:
        return False
    host, port = hp
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno in (errno.EADDRINUSE, errno.EACCES):
                return True
            raise ConfigError("router.listen", f"cannot listen on {endpoint}: {e}") from None
    return False


def already_running(taken: list[str]) -> str:
    """What to tell a user whose router endpoint is taken (issue 23, item 5)."""
    hp = tcp_host_port(taken[0])
    port = hp[1] if hp is not None else taken[0]
    return (
        f"a router already listens on {port}; another Telerobot is running — stop it or use "
        "--listen/--ns"
    )


def open_router(cfg: NodeConfig) -> zenoh.Session:
    """Open the router session (the caller closes it)."""
    import zenoh

    return zenoh.open(cfg.to_zenoh())


def start(ctx: ServiceContext) -> int | None:
    """Open the router, unless its endpoint is taken (status 1) or Zenoh refuses (1)."""
    import zenoh

    # RUST_LOG=info,zenoh::net::routing::interceptor::access_control=trace shows ACL denials.
    zenoh.try_init_log_from_env()
    cfg = router_config(ctx.args)
    note = exposure_note(cfg)
    taken = [e for e in cfg.listen if endpoint_taken(e)]
    if taken:
        print(f"telerobot router: {already_running(taken)}", file=sys.stderr, flush=True)
        return 1
    try:
        session = open_router(cfg)
    except zenoh.ZError as e:
        print(f"telerobot router: cannot start: {short(str(e), 400)}", file=sys.stderr, flush=True)
        return 1
    ctx.closing(session)
    log.info("router %s listening on %s", session.zid(), ", ".join(cfg.listen) or "config")
    print(f"router up: zid={session.zid()} listen={list(cfg.listen)}", flush=True)
    if note:
        log.warning(note)
    return None


def main(argv: list[str] | None = None) -> int:
    return run_service("router", argv, start, description=__doc__)
