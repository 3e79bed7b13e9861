"""`telerobot bench` (issue 10): the paper's §3 figures measured on the running system.

`stats` holds the pure statistics (percentiles, seq loss, rates, command matching), `procs`
spawns and stops the real services, `probes` measures them on the bus, `baselines` runs the
raw-TCP and XML-RPC baselines, `report` builds the JSON and the table, `plot` draws the
force-latency figure with OpenCV and `run` strings the phases together. See docs/bench.md.
"""
