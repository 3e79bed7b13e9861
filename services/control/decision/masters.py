"""What the decision server remembers of each master on robot/cmd: its newest seq and
engagement, and which of its engagements may no longer move the arm.

Bounded: at most MAX_MASTERS records, the least recently heard forgotten first (never the
lease holder's), so a flood of master ids cannot grow memory.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

from services.bus.messages import OperatorCommand

MAX_MASTERS = 64
"""Per-master records kept (oldest forgotten first): a flood of ids cannot grow memory."""
RESTART_GAP_NS = 250_000_000
"""A lower seq sent this long after the newest is a restarted master, not a stale command."""


@dataclass(slots=True)
class MasterRecord:
    """What the supervisor remembers of one master (its newest command's seq/engage)."""

    seq: int
    engage: int
    t_ns: int
    blocked: int = -1
    """Active commands of engagements ≤ this one never move the arm (held or refused)."""

    def block(self, engage: int) -> None:
        """Engagements up to `engage` never move the arm again."""
        self.blocked = max(self.blocked, engage)


class Masters(OrderedDict[str, MasterRecord]):
    """The records by master id, least recently heard first."""

    def classify(self, cmd: OperatorCommand) -> Literal["new", "stale", "restarted"]:
        """Whether `cmd` is newer than its master's record ("new"), stale (a lower or equal
        seq, a lower engage), or from a master that restarted and counts from the beginning
        again (a lower seq sent more than RESTART_GAP_NS after the newest)."""
        rec = self.get(cmd.master)
        if rec is None or (cmd.seq > rec.seq and cmd.engage >= rec.engage):
            return "new"
        if cmd.seq < rec.seq and cmd.t_ns - rec.t_ns > RESTART_GAP_NS:
            return "restarted"
        return "stale"

    def record(self, cmd: OperatorCommand, lease: str | None) -> MasterRecord:
        """Record `cmd` (classified "new"); a new record may push out the oldest one that
        is not the `lease` holder's."""
        rec = self.get(cmd.master)
        if rec is None:
            rec = MasterRecord(cmd.seq, cmd.engage, cmd.t_ns)
            self[cmd.master] = rec
            while len(self) > MAX_MASTERS:
                oldest = next(k for k in self if k != lease)
                del self[oldest]
        else:
            rec.seq, rec.engage, rec.t_ns = cmd.seq, cmd.engage, cmd.t_ns
            self.move_to_end(cmd.master)
        return rec

    def block_all(self) -> None:
        """Every master must engage anew (after an e-stop reset)."""
        for rec in self.values():
            rec.block(rec.engage)
