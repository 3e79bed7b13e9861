"""rmw_zenoh's conventions as pure functions: key expressions, graph tokens, QoS text, attachments.

Source: ros2/rmw_zenoh docs/design.md, sections "Topic and Service name mapping to Zenoh key
expressions", "Graph Cache", "Publishers" and "Quality of Service"; the QoS text is
`qos_to_keyexpr` of rmw_zenoh_cpp/src/detail/liveliness_utils.cpp, relative to the defaults
of rmw_zenoh_cpp/src/detail/qos.cpp (RELIABLE, VOLATILE, KEEP_LAST, depth 42, infinite
deadline/lifespan/lease, AUTOMATIC liveliness): a field equal to its default is left empty.

- data key: `<domain_id>/<fully qualified name without its leading '/'>/<DDS type>/<RIHS01>`
- node token: `@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>`
- publisher/subscription token: `@ros2_lv/<domain>/<zid>/<nid>/<eid>/MP|MS/<enclave>/
  <namespace>/<node>/<topic>/<DDS type>/<RIHS01>/<qos>`, where enclave, namespace and topic are
  mangled ('/' → '%'; the root namespace and the default enclave "/" become "%").
- attachment of every sample: int64 sequence number (from 1), int64 source timestamp (ns
  since the epoch), a length byte (16) and the 16-byte publisher GID, little-endian, i.e. the
  Zenoh serialization of (i64, i64, [u8; 16]).

What the spec leaves open, and what we chose: the GID is "the publisher GID"; rmw_zenoh
takes an XXH3-128 of the token, we take the first 16 bytes of its SHA-256 (no receiver
recomputes it: ROS reads it from the attachment or from its own graph cache).
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass
from enum import IntEnum

from services.frontends.rosmsg.defs import TypeDef
from services.frontends.rosmsg.typehash import rihs01

LIVELINESS_PREFIX = "@ros2_lv"
GID_BYTES = 16
_ATTACHMENT = struct.Struct("<qqB")
ATTACHMENT_BYTES = _ATTACHMENT.size + GID_BYTES
_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Reliability(IntEnum):
    """rmw_qos_reliability_policy_e"""

    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(IntEnum):
    """rmw_qos_durability_policy_e"""

    TRANSIENT_LOCAL = 1
    VOLATILE = 2


KEEP_LAST = 1
DEFAULT_DEPTH = 42


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS of one endpoint (history KEEP_LAST; deadline, lifespan, liveliness default)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    depth: int = 10

    def __post_init__(self) -> None:
        if not 1 <= self.depth <= 10_000:
            raise ValueError(f"depth {self.depth} outside 1…10000")

    def keyexpr(self) -> str:
        """The compact text of the liveliness token (rmw_zenoh `qos_to_keyexpr`)."""
        rel = "" if self.reliability == Reliability.RELIABLE else str(int(self.reliability))
        dur = "" if self.durability == Durability.VOLATILE else str(int(self.durability))
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        # reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,s,ns
        return f"{rel}:{dur}:,{depth}:,:,:,,"


SENSOR_DATA = Qos(Reliability.BEST_EFFORT, Durability.VOLATILE, 5)
"""rclcpp's SensorDataQoS (best effort, depth 5): images."""
LATCHED = Qos(Reliability.RELIABLE, Durability.TRANSIENT_LOCAL, 1)
"""What robot_state_publisher gives /robot_description: a late subscriber gets the last one."""


def check_name(name: str, what: str) -> str:
    """A ROS namespace or topic name: '/'-separated tokens `[A-Za-z_][A-Za-z0-9_]*`."""
    parts = [p for p in name.strip("/").split("/") if p] if name.strip("/") else []
    if "//" in name or not all(_NAME_TOKEN.fullmatch(p) for p in parts):
        raise ValueError(f"{what} {name!r} is not a valid ROS name")
    return name


def fully_qualified(namespace: str, name: str) -> str:
    """`/ns/name` for a relative name, `name` itself when absolute (starts with '/')."""
    check_name(namespace, "namespace")
    check_name(name, "topic")
    if name.startswith("/"):
        return name
    ns = namespace.strip("/")
    return f"/{ns}/{name}" if ns else f"/{name}"


def mangle(name: str) -> str:
    """rmw_zenoh `mangle_name`: every '/' becomes '%' (so "/" is "%")."""
    return name.replace("/", "%")


def topic_key(domain_id: int, fqn: str, t: TypeDef) -> str:
    """The data key expression of a topic."""
    return f"{domain_id}/{fqn.strip('/')}/{t.dds_name}/{rihs01(t.name)}"


def node_token(domain_id: int, zid: str, nid: int, namespace: str, node: str) -> str:
    """The liveliness token of a node (entity kind NN, default enclave)."""
    return (
        f"{LIVELINESS_PREFIX}/{domain_id}/{zid}/{nid}/{nid}/NN/%/"
        f"{mangle(namespace or '/')}/{mangle(node)}"
    )


def endpoint_token(
    kind: str,
    domain_id: int,
    zid: str,
    nid: int,
    eid: int,
    namespace: str,
    node: str,
    fqn: str,
    t: TypeDef,
    qos: Qos,
) -> str:
    """The liveliness token of a publisher (`MP`) or subscription (`MS`)."""
    if kind not in ("MP", "MS"):
        raise ValueError(f"entity kind {kind!r} is not MP or MS")
    return (
        f"{LIVELINESS_PREFIX}/{domain_id}/{zid}/{nid}/{eid}/{kind}/%/{mangle(namespace or '/')}/"
        f"{mangle(node)}/{mangle(fqn)}/{t.dds_name}/{rihs01(t.name)}/{qos.keyexpr()}"
    )


def gid_of(token: str) -> bytes:
    """Our 16-byte GID of an endpoint: the first 16 bytes of SHA-256 of its token."""
    return hashlib.sha256(token.encode("utf-8")).digest()[:GID_BYTES]


def attachment(seq: int, t_ns: int, gid: bytes) -> bytes:
    """The attachment of one sample (sequence number, source timestamp, GID)."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"a GID has {GID_BYTES} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(seq, t_ns, GID_BYTES) + gid


@dataclass(frozen=True, slots=True)
class Attachment:
    seq: int
    t_ns: int
    gid: bytes


def parse_attachment(data: bytes) -> Attachment:
    """Decode an attachment; ValueError if it is not exactly the layout above."""
    if len(data) != ATTACHMENT_BYTES:
        raise ValueError(f"attachment of {len(data)} bytes, expected {ATTACHMENT_BYTES}")
    seq, t_ns, n = _ATTACHMENT.unpack_from(data)
    if n != GID_BYTES:
        raise ValueError(f"GID length byte {n}, expected {GID_BYTES}")
    return Attachment(seq, t_ns, bytes(data[_ATTACHMENT.size :]))
