"""`telerobot console`: the operator's web console (3D mirror of the arm, stereo video, force,
controls and a virtual master). Prints `console: http://HOST:PORT` once it serves.

Settings: the deployment TOML's `[console]` table (`--config`), overridden by the flags below.
See docs/console.md.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from services.bus import keys
from services.bus.config import NodeConfig, section, service_table
from services.bus.lifecycle import CONFIG_EXIT, ServiceContext, run_service
from services.frontends.console.config import ConsoleConfig
from services.world.workcell.messages import WORKCELL_STATE
from services.world.workcell.scene_file import deploy_scene

MASTER_TAKEN_WAIT_S = 0.5
"""How long start-up looks for a master already using the console's master id."""


def console_node_config(cfg: NodeConfig, config: ConsoleConfig) -> NodeConfig:
    """The console's session. Zenoh hands it robot/force at `force_rate_hz` (the plots show
    fewer points than that), robot/state, robot/arm/target, workcell/state and the passivity
    figures (the decision server's at its 500 Hz) at twice the GUI rate (the page is drawn
    at the GUI rate): the rest is dropped on arrival, before any Python runs, instead of a
    thousand callbacks a second."""
    mirror_hz = 2.0 * config.gui_rate_hz
    rules = (
        (keys.FORCE.key, config.force_rate_hz),
        (keys.STATE.key, mirror_hz),
        (keys.ARM_TARGET.key, mirror_hz),
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


def serve(ctx: ServiceContext, config: ConsoleConfig) -> int | None:
    """Serve the console (and its master if `config.master`) until the service stops. Every
    exit closes the console, then the master (which leaves the arm held), then the nodes."""
    scene = deploy_scene(ctx.deploy)  # [scene] file (a bad one fails before any session)
    from services.frontends.console.app import Console

    node = ctx.open(console_node_config(ctx.node_config, config))
    if config.master:
        from services.control.master.config import MasterConfig
        from services.control.master.service import MasterService

        if node.alive.wait(f"master/{config.master_id}", MASTER_TAKEN_WAIT_S):
            print(
                f"telerobot console: master {config.master_id!r} is already running; "
                "use --master-id to start another or --no-master to drive that one",
                file=sys.stderr,
            )
            return CONFIG_EXIT
        # A virtual device that engages only when the console says so (once the hand is
        # at the tool pose), never at start-up.
        mcfg = MasterConfig(master_id=config.master_id, device="virtual", engage_on_start=False)
        mnode = ctx.open(
            master_node_config(ctx.node_config, mcfg.rate_hz),
            name="master",
            instance=config.master_id,
        )
        ctx.closing(MasterService(mnode, mcfg))
    console = Console(node, config, scene=scene)
    ctx.closing(console)
    print(f"console: {console.url}", flush=True)
    return None


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", type=int, default=None, help="HTTP port (default 8080; 0: any)")
    p.add_argument("--host", default=None, help="address to serve on (default 127.0.0.1)")
    p.add_argument(
        "--master",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="start an in-process virtual master driven by the gizmo (default: on)",
    )
    p.add_argument("--master-id", default=None, help="the master the gizmo drives")


def start(ctx: ServiceContext) -> int | None:
    args = ctx.args
    overrides = {
        "port": args.port,
        "host": args.host,
        "master": args.master,
        "master_id": args.master_id,
    }
    config = section(ConsoleConfig, service_table(ctx.deploy, "console", overrides), "console")
    return serve(ctx, config)


def main(argv: list[str] | None = None) -> int:
    return run_service("console", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
