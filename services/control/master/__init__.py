"""The master station: the operator's device, the paper's eq. 5 with master-shift, and
force feedback (docs/master.md). Bus-free; `__main__.py` wires it to Zenoh."""
