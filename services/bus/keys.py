"""Every key expression of the contract, defined once and paired with its message and QoS.

Keys here carry no namespace: a node opened with `--ns cell2` sets Zenoh's `namespace`, so
`robot/cmd` travels as `cell2/robot/cmd` with no change to application code. `with_ns()`
gives the full key for people and for tools that do not use our node.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any, Generic, TypeVar

from services.bus.bounds import MAX_PAYLOAD_BYTES
from services.bus.messages import (
    MAX_FRAME_BYTES,
    ArmDescription,
    ArmTarget,
    Event,
    ForceSample,
    MasterFeedback,
    MasterState,
    Message,
    OperatorCommand,
    PassivityState,
    RobotState,
    StereoFrame,
    VisionStats,
)

M = TypeVar("M", bound=Message)


class QoS(Enum):
    """Delivery class of a stream (PROTOCOL.md §3 'Priorities')."""

    #: commands and force: REAL_TIME, express, block rather than drop
    CONTROL = "control"
    #: robot state: INTERACTIVE_HIGH
    STATE = "state"
    #: video: DATA_LOW, drop on congestion, so it never delays force or commands
    BULK = "bulk"
    #: events and status: DATA, block (events must not be lost)
    RELIABLE = "reliable"


class Delivery(Enum):
    """Reliability of a stream on the link (Zenoh's `Reliability`, docs/deploy.md "QUIC").

    Over TCP and TLS every sample rides one ordered byte stream whatever this says; it
    matters on QUIC with `mixed_rel=1` (best-effort on QUIC datagrams, reliable on streams)
    and on UDP: a lost best-effort sample is gone, and nothing queues behind its
    retransmission."""

    #: latest-wins streams: a lost sample is superseded by the next one within a period
    BEST_EFFORT = "best_effort"
    #: what must arrive whole and once: events, the description, replies, recordings
    RELIABLE = "reliable"


@dataclass(frozen=True, slots=True)
class Topic(Generic[M]):
    """A pub/sub key with its payload type, delivery class, largest payload (bytes):
    anything larger is refused before it is decoded, and its reliability on the link."""

    key: str
    type: type[M]
    qos: QoS
    latest_wins: bool
    max_bytes: int = MAX_PAYLOAD_BYTES
    delivery: Delivery = Delivery.RELIABLE


# Reliability, per stream (Delivery): best-effort for the latest-wins control and state
# streams, which a retransmission would only deliver late behind fresher samples (at
# 700 ms round trip and 1 % loss over TCP: 2–3 s); reliable for what must arrive whole.
#
# robot/cmd: 500 Hz–1 kHz, each one absolute relative to its engagement, the next supersedes
CMD = Topic(
    "robot/cmd", OperatorCommand, QoS.CONTROL, latest_wins=True, delivery=Delivery.BEST_EFFORT
)
# robot/arm/target: absolute and re-sent on every command and hold; robot-host loopback
ARM_TARGET = Topic(
    "robot/arm/target", ArmTarget, QoS.CONTROL, latest_wins=True, delivery=Delivery.BEST_EFFORT
)
# The arm's description (PROTOCOL §1): on change only, kept in the publisher's cache for a
# late subscriber; reliable, as events are: sent on change only, a lost one is never
# re-sent. Large: it carries the URDF.
ARM_DESCRIPTION = Topic(
    "robot/arm/description", ArmDescription, QoS.RELIABLE, latest_wins=True, max_bytes=2 << 20
)
# robot/state: at the arm's state rate, each a whole state
STATE = Topic("robot/state", RobotState, QoS.STATE, latest_wins=True, delivery=Delivery.BEST_EFFORT)
# robot/force: 1 kHz; a lost sample is one millisecond of a continuous signal
FORCE = Topic(
    "robot/force", ForceSample, QoS.CONTROL, latest_wins=True, delivery=Delivery.BEST_EFFORT
)
# robot/events: each one says something once (a fault, a level change): never lost
EVENTS = Topic("robot/events", Event, QoS.RELIABLE, latest_wins=False)
# video: a frame that comes late is worse than none; the next one is a full JPEG
STEREO_L = Topic(
    "vision/stereo/l",
    StereoFrame,
    QoS.BULK,
    True,
    MAX_FRAME_BYTES + 4096,
    delivery=Delivery.BEST_EFFORT,
)
STEREO_R = Topic(
    "vision/stereo/r",
    StereoFrame,
    QoS.BULK,
    True,
    MAX_FRAME_BYTES + 4096,
    delivery=Delivery.BEST_EFFORT,
)
# master/state: at the master's rate, each a whole state of the device
MASTER_STATE = Topic(
    "master/state", MasterState, QoS.STATE, latest_wins=True, delivery=Delivery.BEST_EFFORT
)
# vision/stats: 1 Hz, carries the video level the console shows; reliable as documented
VISION_STATS = Topic("vision/stats", VisionStats, QoS.RELIABLE, latest_wins=True)
# master/feedback: with each master/state, superseded by the next
MASTER_FEEDBACK = Topic(
    "master/feedback", MasterFeedback, QoS.STATE, latest_wins=True, delivery=Delivery.BEST_EFFORT
)
# Time-domain passivity (docs/passivity.md): each side's cumulative port energies, at its
# control rate, on the control class like the command and force they ride along with.
# Cumulative energies: the newest one carries everything the lost ones did (best-effort).
PASSIVITY_MASTER = Topic(
    "robot/passivity/master", PassivityState, QoS.CONTROL, True, delivery=Delivery.BEST_EFFORT
)
PASSIVITY_SLAVE = Topic(
    "robot/passivity/slave", PassivityState, QoS.CONTROL, True, delivery=Delivery.BEST_EFFORT
)

TOPICS: tuple[Topic[Any], ...] = (
    CMD,
    ARM_TARGET,
    ARM_DESCRIPTION,
    STATE,
    FORCE,
    EVENTS,
    STEREO_L,
    STEREO_R,
    MASTER_STATE,
    VISION_STATS,
    MASTER_FEEDBACK,
    PASSIVITY_MASTER,
    PASSIVITY_SLAVE,
)
TOPIC_BY_KEY: dict[str, Topic[Any]] = {t.key: t for t in TOPICS}

SERVICES = ("arm", "force", "decision", "master", "vision", "console")

ALIVE_PREFIX = "alive"
ENCODING = "application/msgpack"


def rpc_key(service: str, method: str = "*") -> str:
    """`robot/<service>/rpc/<method>` (PROTOCOL.md §4)."""
    return f"robot/{service}/rpc/{method}"


def alive_key(service: str, instance: str | None = None) -> str:
    """`alive/<service>`, or `alive/master/<id>` for a master (PROTOCOL.md §5)."""
    return f"{ALIVE_PREFIX}/{service}" + (f"/{instance}" if instance else "")


def with_ns(key: str, ns: str | None) -> str:
    """The key as it travels on a network whose namespace is `ns`."""
    return f"{ns.strip('/')}/{key}" if ns else key


def topic_for(key: str) -> Topic[Any] | None:
    """The topic whose key is `key` (no namespace), or None."""
    return TOPIC_BY_KEY.get(key)
