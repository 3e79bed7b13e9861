"""The wire contract and the bus runtime every service stands on (PROTOCOL.md, docs/protocol.md).

The contract: `messages` (the messages as frozen dataclasses), `codec` (the one module that
knows bytes: strict msgpack and validation), `keys` (every key expression with its message
and QoS), `bounds` (every magnitude an input may carry), `errors` (the one exception
hierarchy). The runtime: `node` (a service's Zenoh session: typed streams, events, rejected
input reported), `streams` (publishers, subscriptions, `Latest`), `intake` (a latest-wins
command stream taken in Zenoh's callback or in batches), `rpc` (methods: queryables and the
calls that reach them), `events` (the event rate limiter), `audience` (who listens),
`rate` (a fixed-rate loop), `config` (Zenoh flags and the deployment TOML), `lifecycle`
(one `run_service()` and signals for every main), `sched` (the session's CPU share),
`peers` and `router` (in-process networks and the embedded router), `registry` (backends
by name, imported when built), `loopback` and `serialport` (what fake devices and serial
ports share), `zenoh_cli_codec` (msgpack for the zenoh CLI).
"""
