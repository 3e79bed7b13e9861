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


@dataclass(frozen=True, slots=True)
class Topic(Generic[M]):
    """A pub/sub key with its payload type, delivery class and largest payload (bytes):
    anything larger is refused before it is decoded."""

    key: str
    type: type[M]
    qos: QoS
    latest_wins: bool
    max_bytes: int = MAX_PAYLOAD_BYTES


CMD = Topic("robot/cmd", OperatorCommand, QoS.CONTROL, latest_wins=True)
ARM_TARGET = Topic("robot/arm/target", ArmTarget, QoS.CONTROL, latest_wins=True)
# The arm's description (PROTOCOL §1): on change only, kept in the publisher's cache for a
# late subscriber; reliable, as events are. Large: it carries the URDF.
ARM_DESCRIPTION = Topic(
    "robot/arm/description", ArmDescription, QoS.RELIABLE, latest_wins=True, max_bytes=2 << 20
)
STATE = Topic("robot/state", RobotState, QoS.STATE, latest_wins=True)
FORCE = Topic("robot/force", ForceSample, QoS.CONTROL, latest_wins=True)
EVENTS = Topic("robot/events", Event, QoS.RELIABLE, latest_wins=False)
STEREO_L = Topic("vision/stereo/l", StereoFrame, QoS.BULK, True, MAX_FRAME_BYTES + 4096)
STEREO_R = Topic("vision/stereo/r", StereoFrame, QoS.BULK, True, MAX_FRAME_BYTES + 4096)
MASTER_STATE = Topic("master/state", MasterState, QoS.STATE, latest_wins=True)
VISION_STATS = Topic("vision/stats", VisionStats, QoS.RELIABLE, latest_wins=True)
MASTER_FEEDBACK = Topic("master/feedback", MasterFeedback, QoS.STATE, latest_wins=True)
# Time-domain passivity (docs/passivity.md): each side's cumulative port energies, at its
# control rate, on the control class like the command and force they ride along with.
PASSIVITY_MASTER = Topic("robot/passivity/master", PassivityState, QoS.CONTROL, latest_wins=True)
PASSIVITY_SLAVE = Topic("robot/passivity/slave", PassivityState, QoS.CONTROL, latest_wins=True)

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
