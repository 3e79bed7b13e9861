"""Tools a person runs: the `telerobot` command, the bench, the paper's evaluation tasks,
recording, replay and reports."""
