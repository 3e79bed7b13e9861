"""A msgpack codec for the `zenoh-cli` tool (PyPI `zenoh-cli`), registered as entry points.

    pip install zenoh-cli
    zenoh --mode client --connect tcp/127.0.0.1:7447 subscribe -k 'robot/**' --decoder telerobot
    zenoh --mode client --connect tcp/127.0.0.1:7447 get -s robot/force/rpc/sensor_status \
        --decoder telerobot
    zenoh --mode client --connect tcp/127.0.0.1:7447 put -k robot/events --encoder telerobot \
        -v '{"seq": 1, "t_ns": 1, "source": "me", "kind": "data", "message": "hello"}'

zenoh-cli (0.7) loads these functions from the `zenoh_cli.codecs.decoders|encoders` entry
point groups when it starts (setup.py registers them), and calls `decode(key, payload)`
with the sample's `zenoh.KeyExpr` (not a `str`) and `encode(key, value)` with the `str` the
user typed; both are accepted here. Everything this module needs is imported when zenoh-cli
loads it, so the first sample is not held up by imports inside Zenoh's callback thread.

Payloads on the contract's keys are decoded and validated with the contract's codec;
anything else that is msgpack is shown as JSON. A payload that breaks the contract shows
the rejection instead of failing the subscription. The encoder refuses, with the field
named, a value that would break the contract on a contract key: nothing malformed is sent.
"""

from __future__ import annotations

import json
from typing import Any

from services.bus import codec, keys
from services.bus.bounds import short
from services.bus.errors import ProtocolError

#: the roots of the contract's keys: whatever precedes one of them is a namespace
_ROOTS = ("robot/", "vision/", "master/", "alive/")


def readable(key: object, payload: bytes) -> Any:
    """A payload for people, as JSON-able data: typed and validated on a contract topic,
    plain msgpack elsewhere, `{"_rejected": why, "_raw": …}` when it cannot be decoded."""
    topic = keys.topic_for(_plain_key(str(key)))
    try:
        if topic is not None:
            return codec.jsonable(codec.decode(topic.type, payload))
        return codec.jsonable(codec.unpack(payload))
    except ProtocolError as e:
        try:
            text = payload.decode("utf-8")
        except UnicodeDecodeError:
            text = f"<{len(payload)} bytes>"
        return {"_rejected": str(e), "_raw": text[:200]}


def decode(key: object, value: bytes) -> str:
    """zenoh-cli decoder: one JSON line for a msgpack payload on `key` (str or KeyExpr)."""
    return json.dumps(readable(key, bytes(value)), ensure_ascii=False)


def encode(key: object, value: str) -> bytes:
    """zenoh-cli encoder: a JSON object typed on the command line → msgpack.

    On a contract topic the object must be a valid message of that topic's type (checked
    with the receivers' own validation); a `get` selector's value is the method's arguments.
    Raises ValueError naming what is wrong.
    """
    try:
        obj = json.loads(value)
    except json.JSONDecodeError as e:
        raise ValueError(f"telerobot encoder: not JSON ({e}): {short(value)}") from None
    if not isinstance(obj, dict):
        raise ValueError("telerobot encoder: the value must be a JSON object {…}")
    payload = codec.pack(obj)
    plain = _plain_key(str(key).split("?", 1)[0])
    topic = keys.topic_for(plain)
    if topic is not None:
        try:
            codec.decode(topic.type, payload)
        except ProtocolError as e:
            raise ValueError(f"telerobot encoder: not a valid {topic.type.__name__}: {e}") from None
    return payload


def _plain_key(key: str) -> str:
    """Drop a namespace prefix: the contract keys start at `robot/`, `vision/` or `master/`."""
    for root in _ROOTS:
        i = key.find(root)
        if i > 0 and key[i - 1] == "/":
            return key[i:]
    return key
