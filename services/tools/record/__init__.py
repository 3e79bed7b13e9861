"""Record, replay and summarize whole sessions in MCAP (issue 12; docs/record.md).

`recorder` (`telerobot record`) writes every stream to MCAP — a JSON view per key for
Foxglove and the exact msgpack payload for replay; `replay` (`telerobot replay`)
republishes the payloads at recorded timing; `report` (`telerobot report`) prints rates,
latencies, seq gaps and events and draws plots. `schemas` holds the file layout and the
JSON Schemas, `archive` reads recordings back (also one whose recorder was killed),
`plots` draws with OpenCV.
"""
