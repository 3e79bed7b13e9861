"""The physics phase: how fast the simulated cell's MuJoCo physics runs, per shipped arm.

For each model, the cell of `services.world.workcell` (the arm from its URDF, the gripper,
the wrist's F/T sensor, the table) with five objects (the scene's three blocks and bottle,
and a fourth block) is stepped at its 1 kHz timestep while the arm follows a smooth joint
motion streamed at 500 Hz, as the arm service streams it, the blocks resting under it.
`physics_<model>_rtf` is simulated time over wall time (≥ 1: it keeps up with real time in
one thread), `physics_<model>_us_per_step` the cost of one step with its bookkeeping (the
objects' phases, the liquid). Pure computation, in this process, no bus.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np

from services.control.arm.model import SHIPPED, load_model
from services.world.workcell.engine import CellPhysics
from services.world.workcell.scene import BLOCK_SIZE_M, TABLE, Box, default_scene

AMPLITUDE_RAD = 0.15
PERIOD_S = 2.0
CTRL_STEPS = 2
"""MuJoCo steps (1 ms) per streamed setpoint: 500 Hz, the arm service's control rate."""


def five_objects() -> Any:
    """The default scene with a fourth block: five movable objects."""
    scene = default_scene()
    extra = Box(
        "block3",
        center=(0.70, -0.25, TABLE.top_z + BLOCK_SIZE_M / 2),
        size=(BLOCK_SIZE_M,) * 3,
        color=(120, 120, 40),
        movable=True,
    )
    return replace(scene, boxes=(*scene.boxes, extra))


def bench_physics(duration_s: float) -> dict[str, Any]:
    """RTF and µs per step of every shipped model's cell over `duration_s` of simulated
    time each (see the module docstring)."""
    if not duration_s > 0.0:
        raise ValueError("duration_s must be > 0")
    scene = five_objects()
    out: dict[str, Any] = {"sim_s": duration_s, "objects": len(scene.movables())}
    for name in SHIPPED:
        arm = load_model(name)
        ph = CellPhysics(arm, scene)
        home = np.array(arm.home)
        dt = ph.model.opt.timestep * CTRL_STEPS
        n = max(1, round(duration_s / dt))
        sign = np.resize([1.0, -1.0], arm.n)
        t0 = time.perf_counter()
        for k in range(n):
            t = k * dt
            s = 0.5 * (1.0 - math.cos(2 * math.pi * t / PERIOD_S))
            ph.command(home + AMPLITUDE_RAD * s * sign)
            ph.step(CTRL_STEPS)
        wall = max(time.perf_counter() - t0, 1e-12)
        out[f"{name}_rtf"] = n * dt / wall
        out[f"{name}_us_per_step"] = wall / (n * CTRL_STEPS) * 1e6
        out[f"{name}_bodies"] = int(ph.model.nbody)
        out[f"{name}_resting"] = sum(b.phase == "resting" for b in ph.bodies())
    return out
