"""A msgpack codec for the `zenoh-cli` tool (PyPI `zenoh-cli`), registered as entry points.

    pip install zenoh-cli
    zenoh --connect tcp/127.0.0.1:7447 subscribe -k 'robot/**' --decoder telerobot
    zenoh --connect tcp/127.0.0.1:7447 put -k robot/cmd --encoder telerobot -v '{"seq": 1, …}'

Payloads on the contract's keys are decoded and validated with the contract's codec;
anything else that is msgpack is shown as JSON. A payload that breaks the contract shows
the rejection instead of failing the subscription.
"""

from __future__ import annotations

import json

from services.bus import codec


def decode(key: str, value: bytes) -> str:
    """zenoh-cli decoder: one JSON line for a msgpack payload on `key`."""
    from services.cli.introspect import decode_sample

    return json.dumps(decode_sample(_plain_key(key), bytes(value)), ensure_ascii=False)


def encode(key: str, value: str) -> bytes:
    """zenoh-cli encoder: a JSON object typed on the command line → msgpack."""
    return codec.pack(json.loads(value))


def _plain_key(key: str) -> str:
    """Drop a namespace prefix: the contract keys start at `robot/`, `vision/` or `master/`."""
    for root in ("robot/", "vision/", "master/", "alive/"):
        i = key.find(root)
        if i > 0 and key[i - 1] == "/":
            return key[i:]
    return key
