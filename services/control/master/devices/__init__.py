"""The master devices: one backend per module or folder, each with its options class.

- `spacemouse.py`: `HidSpaceMouse` (hidapi) and its pure report decoder.
- `keyboard.py`: `KeyboardMaster`, jogging from a terminal.
- `virtual.py`: `VirtualMaster`, a hand set from outside (the web console, the tasks).
- `scripted.py`: `ScriptedMaster`, trajectory files and generated motions.
- `haply/`: `HaplyMaster` (Inverse3 + VerseGrip), the Inverse Service's JSON frames, its fake.
- `master_arm/`: `SerialMasterArm`, its line protocol, its DH kinematics, its fake.

The core (`..service`, `..teleop`, `..config`, …) imports none of them: `..backends` names
each by its `device` key and imports it only when it is chosen (lint-imports keeps it so).
"""
