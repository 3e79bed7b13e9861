"""`telerobot arm`: the arm service — any arm model (the PUMA 560 by default), simulated or real."""

from __future__ import annotations

import argparse
import sys
from typing import Any, get_args

from services.bus.config import section, service_table
from services.bus.lifecycle import ServiceContext, run_service
from services.control.arm.config import SIM_PHYSICS, ArmConfig
from services.control.arm.driver import DriverName
from services.control.arm.model import DEFAULT_MODEL, SHIPPED


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model",
        default=None,
        help=f"arm model: {', '.join(SHIPPED)} (default {DEFAULT_MODEL}) or an arm's TOML",
    )
    p.add_argument("--driver", choices=list(get_args(DriverName)), default=None)
    p.add_argument("--port", default=None, help="serial URL (/dev/ttyUSB0, socket://host:port)")
    p.add_argument("--baudrate", type=int, default=None)
    p.add_argument("--robot-ip", default=None, help="the Franka's FCI address (libfranka)")
    p.add_argument(
        "--sim-physics",
        choices=SIM_PHYSICS,
        default=None,
        help="driver sim: the arm alone in its own physics, on the workcell service's MuJoCo "
        "cell over the bus, or on that cell run in this process (embedded: the simulation "
        "profile's; docs/sim.md)",
    )
    p.add_argument(
        "--autostart",
        action="store_true",
        help="connect and initialize at start-up (the simulation profile does)",
    )


def arm_table(deploy: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """The deployment's `[arm]` table with the flags given on the command line over it."""
    overrides = {
        "model": args.model,
        "driver": args.driver,
        "port": args.port,
        "baudrate": args.baudrate,
        "robot_ip": args.robot_ip,
        "sim_physics": args.sim_physics,
    }
    return service_table(deploy, "arm", overrides)


def start(ctx: ServiceContext) -> None:
    args = ctx.args
    table = arm_table(ctx.deploy, args)
    autostart = bool(table.pop("autostart", False)) or args.autostart
    config = ArmConfig.from_mapping(table)
    from services.control.arm.service import ArmService

    channel = _embedded_workcell(ctx) if config.sim_physics == "embedded" else None
    svc = ArmService(ctx.open(), config, channel=channel)
    ctx.closing(svc)
    ctx.log.info("arm up: %s, %d joints, %s driver", svc.model.name, svc.model.n, config.driver)
    if autostart:
        svc.proxy.rpc_connect({})
        svc.proxy.rpc_initialize({})


def _embedded_workcell(ctx: ServiceContext) -> Any:
    """The workcell service in this process (its own session as `workcell`, its `[workcell]`
    and `[scene]` tables): the arm's physics, handed over through the returned channel.
    Closed after the arm (registered first), so the arm's last hold reaches the physics."""
    from services.world.workcell.channel import ArmChannel
    from services.world.workcell.config import WorkcellConfig
    from services.world.workcell.scene_file import deploy_scene
    from services.world.workcell.service import WorkcellService

    config = section(WorkcellConfig, ctx.deploy.get("workcell", {}), "workcell")
    scene = deploy_scene(ctx.deploy)
    channel = ArmChannel()
    ctx.closing(WorkcellService(ctx.open(name="workcell"), config, scene=scene, channel=channel))
    ctx.log.info("workcell simulation up in the arm's process (%g Hz)", config.rate_hz)
    return channel


def main(argv: list[str] | None = None) -> int:
    return run_service("arm", argv, start, description=__doc__, add_arguments=arguments)


if __name__ == "__main__":
    sys.exit(main())
