"""ROS 2 messages without ROS: CDR bytes and REP-2016 type hashes for the few types we bridge.

`defs` holds the type descriptions (the one place a field list is written), `typehash`
computes their RIHS01 hashes, `cdr` the XCDR1 primitives, `msgs` the message types with
their encoders and bounded decoders. Nothing here knows about Zenoh or Telerobot's bus.
"""
