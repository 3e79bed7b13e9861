"""The workcell service's settings: the `[workcell]` table, read once into a frozen dataclass.

`services.bus.config.section(WorkcellConfig, table, "workcell")` reads it; the physics'
parameters are the nested `[workcell.physics]` table. A bad value raises
`ConfigError("workcell.<key>", …)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from services.bus.errors import ConfigError
from services.world.workcell.mujoco_model import PhysicsParams


@dataclass(frozen=True, slots=True)
class WorkcellConfig:
    """Settings of the workcell simulation service.

    rate_hz: loop wake-ups per second: each takes the newest setpoint and grip, steps the
      physics by 1 / rate_hz (in MuJoCo steps of `physics.timestep_s`) and publishes
      `sim/arm/state`.
    publish_rate_hz: `workcell/state` messages per second (≤ rate_hz).
    state_stale_ms: with no robot/state for this long the gripper is left as it was (a
      lost robot stream must not drop what the gripper holds).
    physics: the MuJoCo cell's parameters (services.world.workcell.mujoco_model.PhysicsParams).
    """

    rate_hz: float = 500.0
    publish_rate_hz: float = 50.0
    state_stale_ms: float = 500.0
    physics: PhysicsParams = field(default_factory=PhysicsParams)

    def __post_init__(self) -> None:
        for key in ("rate_hz", "publish_rate_hz", "state_stale_ms"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"workcell.{key}", f"must be a number, got {v!r}")
            if v <= 0:
                raise ConfigError(f"workcell.{key}", f"must be > 0, got {v}")
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise ConfigError("workcell.rate_hz", "must be within 1 … 1000 Hz")
        if self.publish_rate_hz > self.rate_hz:
            raise ConfigError("workcell.publish_rate_hz", "must not exceed rate_hz")

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz
