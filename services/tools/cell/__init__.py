"""The cell layer under the bench and the tasks: a robot cell to run, and the helpers that
start, wait on and reach it. Used by the bench, the tasks, the CLI's launcher and the tests.

- `sim`: `SimCell`, the robot side in simulation in one process (arm, workcell, force and
  decision services, each on a node of its own, the workcell of any scene), and
  `light_cell`, its settings for a small shared host (`light_arm` and `LIGHT_FORCE`, the
  link bench's too).
- `procs`: child processes, spawned never forked: `Child` (one process: log file, prefixed
  output or its lines awaited one by one, restart, signals to it or its process group, stop
  with SIGTERM then SIGKILL) and `Children` (named children, stopped in reverse order), the
  readiness waits on them.
- `wait`: `wait_until`, poll a condition to a deadline; its `Waited` answer says what.
- `ports`: `free_port` (outside the ephemeral range), `free_udp_port`, `port_open`.

Nothing here imports the bench, the tasks, the CLI or the recorder (import-linter's `tools`
contract).
"""
