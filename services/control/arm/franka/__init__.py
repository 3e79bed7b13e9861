"""The `libfranka` arm driver: a Franka FR3 (or Panda) through pylibfranka, Franka's own
bindings (docs/franka.md).

`driver` (`FrankaArm`, the arm service's driver), `rt` (the real-time process that runs
libfranka's 1 kHz control loop beside the service), `shm` (the lock-free block they share:
the newest setpoint one way, the newest robot state the other), `params` (what the driver
sets on the robot, from the model's `franka.toml`), `errors` (libfranka's errors and
reflexes named for the arm's status and events), `frankysim` (franky-sim as a subprocess:
the independent libfranka-protocol simulator the tests drive it against).
"""
