"""Tools a person runs: the `telerobot` command (`cli`), the bench, the paper's evaluation
tasks, recording, replay and reports (`record`), and the cell layer they and the tests share
to run the system (`cell`: the in-process sim cell, child processes, waits, ports)."""
