"""The master station: the operator's device, the paper's eq. 5 with master-shift, and
force feedback (docs/master.md). Bus-free but `service.py`; `__main__.py` wires it to Zenoh.

The core, which imports no device (lint-imports' `master-core` contract):

- `config.py`: `MasterConfig`, the `[master]` keys every station has, and the reader that
  hands the rest to the chosen device's options class.
- `device.py`: the `MasterDevice` role, `HandReading`, its errors, `DeviceOptions` (a
  backend's own keys) and the optional capabilities as Protocols, checked once.
- `backends.py`: the one place that names the devices (`DEVICES`), each imported when
  chosen; `open_master_device(config)`.
- `teleop.py`: eq. 5 and the master-shift state machine. `feedback.py`: slave wrench →
  operator wrench, and the one force path (`ForceDisplay`). `jog.py`: rate devices'
  deflection → hand pose. `status_line.py`: a terminal's one-line status.
- `service.py`: the station on the bus: device → `robot/cmd`, force → the hand.

Beside it: `devices/` (one module or folder per backend, with its options, wire protocol
and fake), `passivity.py` (the master's TDPA port, docs/passivity.md) and `haptic_sim.py`
(the passivity lab's simulated haptic device, `device = "haptic_sim"`).
"""
