"""A 6-joint master arm on a serial line (`device = "serial_arm"`).

- `backend.py`: `SerialMasterArm`, the `MasterDevice`, and `MasterArmOptions`, its
  `[master]` keys.
- `protocol.py`: the ASCII line protocol (docs/serial-master-protocol.md), pure bytes ↔ values.
- `kinematics.py`: forward kinematics and joint torques from its standard DH table.
- `fake.py`: `FakeMasterArm`, the arm byte for byte on TCP 127.0.0.1.

Not the slave arm's controller link (`services/control/arm/serial_arm.py`): this is the
operator's arm.
"""
