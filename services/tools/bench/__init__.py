"""`telerobot bench` (issue 10): the paper's §3 figures measured on the running system.

`stats` holds the pure statistics (percentiles, seq loss, rates, command matching), `procs`
the bench's view of the real services it runs (the CPU each used, the arm's readiness; they
are spawned and stopped by `services.tools.cell.procs`), `probes` measures them on the bus,
`baselines` runs the raw-TCP and XML-RPC baselines, `report` builds the JSON and the table,
`plot` draws the force-latency figure with OpenCV and `run` strings the phases together.
`render` is the vision rig's own render bench (`python -m services.tools.bench.render`), not
a phase. See docs/bench.md.
"""
