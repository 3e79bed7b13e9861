"""The `arm` service: any arm model, simulated or real, behind one proxy (docs/arm.md).

The model: `model` (an `ArmModel` from its TOML and the URDF it names), `kinematics` (FK,
Jacobian, IK of any model; `puma560` the PUMA's closed-form plug-in), `links` (every link's
frame). The proxy, free of the bus: `proxy` (the paper's IProxyRobot), `control` (the
fixed-rate tick, streamed targets, motions, status), `motions`, `planning` and `trajectory`
(planned joint moves and tool lines), `safety` (the last filter before the joints),
`arguments` (method arguments validated). The drivers: `driver` (the role), `backends`
(the one place that names them), `arm_base` (what they share), `sim_arm` (the arm in the
workcell's MuJoCo), `serial_arm` and `fake_controller` (a retrofitted PUMA controller on a
serial line, and its byte-exact fake); `franka/` the FR3 and Panda through libfranka
(pylibfranka; docs/franka.md), franky-sim its test counterpart. `service` puts it all on
the bus; `config` is the `[arm]` table.
"""
