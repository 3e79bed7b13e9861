"""`telerobot console`: the operator's web console (3D mirror of the arm, stereo video, force,
controls and a virtual master). Prints `console: http://HOST:PORT` once it serves.

Settings: the deployment TOML's `[console]` table (`--config`), overridden by the flags below.
See docs/console.md.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from dataclasses import replace

from services.bus import keys
from services.bus.config import (
    NodeConfig,
    add_node_args,
    load_deploy,
    node_config,
    section,
    service_table,
)
from services.bus.lifecycle import Shutdown, setup_logging
from services.bus.node import Node
from services.cli.introspect import LOCAL_ROUTER
from services.console.config import ConsoleConfig
from services.workcell.messages import WORKCELL_STATE

MASTER_TAKEN_WAIT_S = 0.5
"""How long start-up looks for a master already using the console's master id."""


def console_node_config(cfg: NodeConfig, config: ConsoleConfig) -> NodeConfig:
    """The console's session. Zenoh hands it robot/force at `force_rate_hz` (the plots show
    fewer points than that), robot/state, robot/puma/cmd, workcell/state and the passivity
    figures (the decision server's at its 500 Hz) at twice the GUI rate (the page is drawn
    at the GUI rate): the rest is dropped on arrival, before any Python runs, instead of a
    thousand callbacks a second."""
    mirror_hz = 2.0 * config.gui_rate_hz
    rules = (
        (keys.FORCE.key, config.force_rate_hz),
        (keys.STATE.key, mirror_hz),
        (keys.PUMA_CMD.key, mirror_hz),
        (WORKCELL_STATE.key, mirror_hz),
        (keys.PASSIVITY_MASTER.key, mirror_hz),
        (keys.PASSIVITY_SLAVE.key, mirror_hz),
    )
    return replace(cfg, downsampling=(*cfg.downsampling, *rules))


def master_node_config(cfg: NodeConfig, rate_hz: float | None = None) -> NodeConfig:
    """The in-process master's session: the console's, minus its listeners (one process
    cannot listen twice on a port); a console that only listens is reached on loopback.
    The master reads the newest force and robot state once per tick: with `rate_hz` (its
    tick rate), Zenoh hands it those at that rate, not at theirs."""
    connect = cfg.connect or tuple(
        ep.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]") for ep in cfg.listen
    )
    rules = () if rate_hz is None else ((keys.FORCE.key, rate_hz), (keys.STATE.key, rate_hz))
    # a free-port listener (deploy/sim.toml's loopback one) can be opened twice: keep it, or
    # Zenoh's default would listen on every interface
    listen = tuple(ep for ep in cfg.listen if ep.endswith(":0"))
    return replace(cfg, listen=listen, connect=connect, downsampling=(*cfg.downsampling, *rules))


def run(node_cfg: NodeConfig, config: ConsoleConfig, stop: Shutdown) -> int:
    """Serve the console (and its master if `config.master`) until `stop` is set. Every
    exit closes the console, then the master (which leaves the arm held), then the nodes."""
    from services.console.app import Console

    with contextlib.ExitStack() as stack:
        node = stack.enter_context(Node("console", console_node_config(node_cfg, config)))
        if config.master:
            from services.master.config import MasterConfig
            from services.master.service import MasterService

            if node.alive.wait(f"master/{config.master_id}", MASTER_TAKEN_WAIT_S):
                print(
                    f"telerobot console: master {config.master_id!r} is already running; "
                    "use --master-id to start another or --no-master to drive that one",
                    file=sys.stderr,
                )
                return 2
            # A virtual device that engages only when the console says so (once the hand is
            # at the tool pose), never at start-up.
            mcfg = MasterConfig(master_id=config.master_id, device="virtual", engage_on_start=False)
            mnode = stack.enter_context(
                Node(
                    "master",
                    master_node_config(node_cfg, mcfg.rate_hz),
                    instance=config.master_id,
                )
            )
            master = MasterService(mnode, mcfg)
            stack.callback(master.close)
        console = Console(node, config)
        stack.callback(console.close)
        print(f"console: {console.url}", flush=True)
        stop.wait()
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="telerobot console", description=__doc__)
    p.add_argument("--port", type=int, default=None, help="HTTP port (default 8080; 0: any)")
    p.add_argument("--host", default=None, help="address to serve on (default 127.0.0.1)")
    p.add_argument(
        "--master",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="start an in-process virtual master driven by the gizmo (default: on)",
    )
    p.add_argument("--master-id", default=None, help="the master the gizmo drives")
    p.add_argument("--verbose", "-v", action="store_true", help="debug logging")
    add_node_args(p)
    args = p.parse_args(argv)
    setup_logging("console", args.verbose)
    deploy = load_deploy(args.config)
    overrides = {
        "port": args.port,
        "host": args.host,
        "master": args.master,
        "master_id": args.master_id,
    }
    table = service_table(deploy, "console", overrides)
    config = section(ConsoleConfig, table, "console")
    node_cfg = node_config(args, deploy, connect=(LOCAL_ROUTER,))
    return run(node_cfg, config, Shutdown())


if __name__ == "__main__":
    sys.exit(main())
