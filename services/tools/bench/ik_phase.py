"""The IK phase: how fast each shipped arm model solves its inverse kinematics.

- the PUMA 560's analytic IK: all 8 branches of a pose, over poses from FK of random joints
  within the limits (`ik_analytic_per_s`), and one damped-least-squares step of its
  singularity fallback (`ik_dls_per_s`);
- every numerical model (the FR3, the UR5e): `solve` from a warm seed — the previous
  target's solution, the target 1 mm and 5 mrad further along a random smooth path, what a
  1 kHz target stream asks of the arm (`ik_<model>_per_s`), with the error it leaves.
Pure computation, in this process, no bus.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pinocchio as pin

from services.control.arm.model import SHIPPED, load_model

STEP_M = 0.001
STEP_RAD = 0.005


def bench_ik(n: int) -> dict[str, Any]:
    """Solves per second of every shipped model over `n` poses (see the module docstring)."""
    if n < 1:
        raise ValueError("n must be >= 1")
    out: dict[str, Any] = {"n": float(n)}
    rng = np.random.default_rng(560)
    for name in SHIPPED:
        model = load_model(name)
        kin = model.kinematics()
        if kin.analytic:
            qs = rng.uniform(kin.q_lo, kin.q_hi, size=(n, model.n))
            poses = [kin.fk_tool(q) for q in qs]
            t0 = time.perf_counter()
            for pose in poses:
                kin.ik(pose)
            out["analytic_ik_per_s"] = n / max(time.perf_counter() - t0, 1e-12)
            starts = np.clip(qs + rng.normal(0.0, 0.05, size=qs.shape), kin.q_lo, kin.q_hi)
            t0 = time.perf_counter()
            for q, pose in zip(starts, poses, strict=True):
                kin.dls_step(q, pose)
            out["dls_steps_per_s"] = n / max(time.perf_counter() - t0, 1e-12)
            continue
        # A smooth random walk of the tool from home: each target one step from the last.
        q = np.array(model.home)
        oMt = kin.fk_tool(q)
        targets = []
        for _ in range(n):
            dp = rng.normal(size=3)
            dw = rng.normal(size=3)
            oMt = pin.SE3(
                oMt.rotation @ pin.exp3(STEP_RAD * dw / np.linalg.norm(dw)),
                oMt.translation + STEP_M * dp / np.linalg.norm(dp),
            )
            targets.append(oMt)
        worst_m = 0.0
        solved = 0
        t0 = time.perf_counter()
        for target in targets:
            try:
                sol = kin.solve(q, target, seed=q)
            except Exception:  # out of reach or the limits: counted, the walk goes on
                continue
            q = sol.q
            solved += 1
            worst_m = max(worst_m, sol.pos_err_m)
        dt = max(time.perf_counter() - t0, 1e-12)
        out[f"{name}_solve_per_s"] = n / dt
        out[f"{name}_solved"] = solved
        out[f"{name}_worst_err_m"] = worst_m
    return out
