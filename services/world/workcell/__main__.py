"""`python -m services.world.workcell`: the simulated workcell's physics as a service of its own.

Settings: the deployment TOML's `[workcell]` table (`--config`); see docs/tasks.md. Its
`[scene] file` names a user's own scene (services.world.workcell.scene_file, docs/sim.md).
"""

from __future__ import annotations

import sys

from services.bus.config import section
from services.bus.lifecycle import ServiceContext, run_service
from services.world.workcell.config import WorkcellConfig
from services.world.workcell.scene_file import deploy_scene


def start(ctx: ServiceContext) -> None:
    config = section(WorkcellConfig, ctx.deploy.get("workcell", {}), "workcell")
    scene = deploy_scene(ctx.deploy)  # [scene] file: a user's own (None: the standard one)
    from services.world.workcell.service import WorkcellService

    ctx.closing(WorkcellService(ctx.open(), config, scene=scene))
    ctx.log.info("workcell simulation up (%g Hz)", config.rate_hz)


def main(argv: list[str] | None = None) -> int:
    return run_service("workcell", argv, start, description=__doc__)


if __name__ == "__main__":
    sys.exit(main())
