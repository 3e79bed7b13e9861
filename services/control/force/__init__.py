"""The force service: wrist force sensing at 1 kHz, the paper's §2.1.3–2.1.4 (docs/force.md)."""
