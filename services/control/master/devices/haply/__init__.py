"""The Haply Inverse3 with its VerseGrip, through the Inverse Service (`device = "haply"`).

- `backend.py`: `HaplyMaster`, the `MasterDevice`, and `HaplyOptions`, its `[master]` keys.
- `protocol.py`: the simulation channel's JSON frames, as pure functions.
- `fake.py`: `FakeInverseService`, the service message for message on loopback
  (`telerobot haply-fake`).
"""
