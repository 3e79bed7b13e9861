"""The `workcell` service: the one process that owns the simulated cell's physics, on
MuJoCo (docs/sim.md).

`scene` (the one description of the cell for physics, rendering and tasks), `bodies` (the
movable objects as every view sees them, and the bottle's liquid), `arm` (the arm as the
physics needs it, from `robot/arm/description`), `mujoco_model` (the cell as one MuJoCo
model built from those descriptions), `engine` (stepping it: joint servos, gripper,
objects, the wrist's force/torque site), `messages` (`workcell/state`), `service` (it on
the bus), `config` (the `[workcell]` table).
"""
