"""Measure what drawing the arm costs the console's GUI thread, per update (a new q).

Not a test (pytest does not collect it). Run from a worktree:

    nice -n 10 .venv/bin/python -m tests.frontends.console.measure_arm --updates 300

On one viser server (no browser: the cost measured is the server's, which is the GUI
thread's), for each shipped model, each update being a joint vector that moves every joint
by about 0.01 rad (a teleoperated arm between two GUI ticks):

- `arm_view_us`: `ArmView.draw(q)` (services/frontends/console/arm.py): `LinkPoses` once,
  one pose per moving joint, sent only when it moved, inside `server.atomic()` as the GUI
  loop does; `setters`: the poses it sent per update;
- `skeleton_us`: the same for the model drawn as its skeleton (the fallback);
- `viser_visualizer_us`: Pinocchio's `ViserVisualizer.display(q)` on the same visuals, the
  alternative weighed (it sets the pose of every visual on every call);
- `link_poses_us`: `LinkPoses.poses(q)` alone, the kinematics under both;
- `setter_us`: one viser pose setter (position, new value) inside `atomic()`: the floor that
  multiplies the count of nodes moved.

Prints one JSON line per model, plus the load average (the machine is shared).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import viser

from services.bus.messages import ArmDescription
from services.control.arm.model import SHIPPED, load_model
from services.frontends.console.arm import ArmView, arm_layout


def _per_call_us(fn: Callable[[Any], Any], args: list[Any], server: viser.ViserServer) -> float:
    for a in args[:10]:
        fn(a)
    t0 = time.perf_counter()
    for a in args:
        with server.atomic():
            fn(a)
    return (time.perf_counter() - t0) / len(args) * 1e6


def measure(name: str, updates: int, server: viser.ViserServer) -> dict[str, Any]:
    from pinocchio.visualize import ViserVisualizer

    model = load_model(name)
    desc = ArmDescription(seq=1, t_ns=time.time_ns(), **model.description())
    rng = np.random.default_rng(1)
    walk = np.clip(
        np.add(model.home, np.cumsum(rng.normal(0.0, 0.01, (updates, model.n)), axis=0)),
        model.q_lo,
        model.q_hi,
    )
    qs = [tuple(float(x) for x in q) for q in walk]

    layout = arm_layout(desc)
    view = ArmView(server.scene, layout, root=f"/measure/{name}")
    sent0 = view.sent
    arm_us = _per_call_us(view.draw, qs, server)
    setters = (view.sent - sent0) / (len(qs) + 10)
    view.remove()

    skel = arm_layout(ArmDescription(seq=1, t_ns=1, **{**model.description(), "model": "x"}))
    skel_view = ArmView(server.scene, skel, root=f"/measure/{name}_skeleton")
    skeleton_us = _per_call_us(skel_view.draw, qs, server)
    skel_view.remove()

    pm = model.pin_model()
    visuals = model.geometry()
    viz = ViserVisualizer(pm, visuals, visuals)
    viz.initViewer(viewer=server)
    viz.loadViewerModel(rootNodeName=f"/measure/{name}_viz")
    viz_us = _per_call_us(lambda q: viz.display(np.array(q)), qs, server)
    for root in (viz.visualRootFrame, viz.collisionRootFrame, viz.framesRootFrame):
        root.remove()

    poses_us = _per_call_us(layout.poses.poses, qs, server)
    return {
        "model": name,
        "n": model.n,
        "visuals": len(layout.parts),
        "joints_drawn": len(layout.groups),
        "arm_view_us": round(arm_us, 1),
        "setters": round(setters, 1),
        "skeleton_us": round(skeleton_us, 1),
        "viser_visualizer_us": round(viz_us, 1),
        "link_poses_us": round(poses_us, 1),
    }


def setter_floor_us(server: viser.ViserServer, n: int) -> float:
    h = server.scene.add_frame("/measure/floor", show_axes=False)
    t0 = time.perf_counter()
    with server.atomic():
        for i in range(n):
            h.position = (i * 1e-3, 0.0, 0.0)
    us = (time.perf_counter() - t0) / n * 1e6
    h.remove()
    return us


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--updates", type=int, default=300)
    args = ap.parse_args()
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        print(json.dumps({"setter_us": round(setter_floor_us(server, 2000), 1)}))
        for name in SHIPPED:
            print(json.dumps(measure(name, args.updates, server)))
        print(json.dumps({"loadavg": os.getloadavg()}))
    finally:
        server.stop()


if __name__ == "__main__":
    main()
